"""Bundle adjustment: refine the camera rig against the fly's own detected joints.

:func:`bundle_adjust` (``adjust``) fits one flattened problem, :func:`bundle_adjust_sequence`
(``sequence``) a recording's ``(V, T, P, 2)`` detections; each module's docstring says its part."""

import lazy_loader as _lazy

# Names and modules are listed in ``__init__.pyi``: JAX and SciPy load with the solver, not
# with the parameter grammar (``params``) that planning reads for every run and cluster job.
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
