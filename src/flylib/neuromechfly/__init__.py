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

from importlib import import_module

#: The stage's files in the output directory: HDF5, replay CSV, figure (declared here,
#: light to import, for the Snakefile).
FILES: tuple[str, ...] = ("neuromechfly.h5", "joint_angles.csv", "joint_angles.png")

# the rest loads on first use: JAX comes with the solver, not with the Snakefile
_LAZY = {
    "NmfAngles": "angles",
    "compute_nmf_angles": "angles",
    "DOF_SUFFIXES": "model",
    "LEGS": "model",
    "dof_names": "model",
    "forward_kinematics": "model",
}

__all__ = ["FILES", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
