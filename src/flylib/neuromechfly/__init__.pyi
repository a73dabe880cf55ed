"""flylib.neuromechfly's names and the modules they come from.

``flylib/neuromechfly/__init__.py`` reads this file (``lazy_loader.attach_stub``) and
loads each module on first use of one of its names; ``FILES`` is defined there.
"""

from .angles import NmfAngles as NmfAngles, compute_nmf_angles as compute_nmf_angles
from .model import (
    DOF_SUFFIXES as DOF_SUFFIXES,
    LEGS as LEGS,
    dof_names as dof_names,
    forward_kinematics as forward_kinematics,
)

FILES: tuple[str, ...]
