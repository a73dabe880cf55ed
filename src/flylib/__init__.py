"""flylib: markerless 3D pose estimation of tethered Drosophila from a multi-camera rig.

Every public name is importable from the top level (``from flylib import CameraGroup``).
The names and the modules they come from are listed once, in the type stub
``__init__.pyi``; modules load on first use, so ``import flylib`` does not pull in
JAX or PyTorch until a name that needs them is used.
"""

import lazy_loader as _lazy

__version__ = "0.1.0"

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
