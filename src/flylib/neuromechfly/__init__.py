"""NeuroMechFly joint angles: a recording's 3D aligned to the body model's template and its 42
leg degrees of freedom by inverse kinematics on the model's chains, in flygym's joint names, order
and units (radians), ready for kinematic replay (:func:`compute_nmf_angles`, in :mod:`.angles`);
:mod:`flylib.pipeline.neuromechfly` is the workflow stage."""

import lazy_loader as _lazy

#: The stage's files in the output directory: HDF5, replay CSV, figure (light to import).
FILES: tuple[str, ...] = ("neuromechfly.h5", "joint_angles.csv", "joint_angles.png")

# the rest loads on first use (``__init__.pyi``): JAX comes with the solver, not the Snakefile
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
__all__ = ["FILES", *__all__]
