"""2D keypoint detection: the DeepFly2D stacked hourglass and the detection plan.

Torch loads only when a torch-backed name is used, so the plan
(:class:`DetectionPlan`, :meth:`DetectionPlan.view_sources`) is cheap to read.
"""

import lazy_loader as _lazy

# The names and their modules are listed once, in ``__init__.pyi``.
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
