"""NeuroMechFly joint angles: a recording's 3D aligned to the body model's template and
its 42 leg degrees of freedom by inverse kinematics on the model's chains, in flygym's
joint names, order and units (radians), ready for kinematic replay.

- :mod:`.model`: the model's leg chains, joint names, forward kinematics.
- :mod:`.align`: the similarity from the thorax-coxa points, per-leg scale, the
  tethered check.
- :mod:`.ik`: the JAX solver.
- :mod:`.angles`: :func:`compute_nmf_angles`, the three together, with the
  forward-kinematics residual.
- :mod:`.replay`: flygym's kinematic replay of the angles (flygym optional) and the
  replay table read back from ``joint_angles.csv``.

:mod:`flylib.pipeline.neuromechfly` is the workflow stage (its files).
"""

import lazy_loader as _lazy

#: The stage's files in the output directory: HDF5, replay CSV, figure (declared here,
#: light to import, for the Snakefile).
FILES: tuple[str, ...] = ("neuromechfly.h5", "joint_angles.csv", "joint_angles.png")

# the rest loads on first use (listed in ``__init__.pyi``): JAX comes with the solver,
# not with the Snakefile
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
__all__ = ["FILES", *__all__]
