"""NeuroMechFly's leg chains: the template body, the degrees of freedom and forward kinematics.

The numbers are the zero pose of flygym's body model
(``flygym/data/mjcf/neuromechfly_seqik_kinorder_ypr.xml``, flygym 1.2.1, the model SeqIKPy's
chains follow), in millimetres, in the model's thorax frame (x anterior, y left, z dorsal). Per
leg: the thorax-coxa joint's position in the thorax, then the offsets coxa -> trochanter
(``Femur`` body), trochanter -> femur-tibia (``Tibia``), femur-tibia -> tibia-tarsus
(``Tarsus1``) and tibia-tarsus -> claw (the sum of the ``Tarsus2`` ... ``Tarsus5`` offsets;
flygym's claw is the ``Tarsus5`` body origin).

The hinges, in the order MuJoCo applies them inside each body (each about an axis of the frame
left by the one before): thorax-coxa yaw (x), pitch (y), roll (z); coxa-trochanter pitch (y),
roll (z); femur-tibia pitch (y); tibia-tarsus pitch (y). An angle here is the angle of flygym's
joint of that name, in radians, so the angles drive flygym's model as they are."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

#: The legs in flygym's order (``preprogrammed.all_leg_dofs``).
LEGS: tuple[str, ...] = ("LF", "LM", "LH", "RF", "RM", "RH")
#: flygym's per-leg joint suffixes, in its order: ThC pitch, roll, yaw; CTr pitch, roll;
#: FTi pitch; TiTa pitch.
DOF_SUFFIXES: tuple[str, ...] = (
    "Coxa",
    "Coxa_roll",
    "Coxa_yaw",
    "Femur",
    "Femur_roll",
    "Tibia",
    "Tarsus1",
)
#: The model's joints along a leg chain (ThC is the chain's fixed root).
CHAIN_JOINTS: tuple[str, ...] = ("ThC", "CTr", "FTi", "TiTa", "Claw")

#: Per leg: ThC position in the thorax, then the four segment offsets (mm).
_CHAINS_MM: dict[str, tuple[tuple[float, float, float], ...]] = {
    "LF": (
        (-0.160596, 0.171588, -0.230215),
        (-0.001812, -0.001716, -0.365456),
        (-0.004655, -0.001488, -0.705223),
        (-0.000144, -0.000952, -0.518397),
        (0.006588, -0.001067, -0.564610),
    ),
    "LM": (
        (-0.556871, 0.124901, -0.482209),
        (-0.000216, 0.000149, -0.181447),
        (-0.000971, 0.000055, -0.783670),
        (0.000066, -0.000370, -0.667326),
        (0.001260, -0.000343, -0.606396),
    ),
    "LH": (
        (-0.783722, 0.086993, -0.496612),
        (-0.000177, -0.000227, -0.199417),
        (0.000108, 0.000294, -0.836314),
        (-0.000001, -0.000324, -0.684456),
        (0.000179, 0.000645, -0.697810),
    ),
}
# the model is mirror-symmetric about its sagittal (x-z) plane
_CHAINS_MM.update(
    {"R" + leg[1]: tuple((x, -y, z) for x, y, z in rows) for leg, rows in list(_CHAINS_MM.items())}
)


def dof_names() -> list[str]:
    """flygym's 42 leg joint names, ``joint_<leg><suffix>``, in its order."""
    return [f"joint_{leg}{suffix}" for leg in LEGS for suffix in DOF_SUFFIXES]


def thorax_coxa_template() -> Float[np.ndarray, "6 3"]:
    """The six thorax-coxa joints of the model (mm, thorax frame), rows in :data:`LEGS` order."""
    return np.array([_CHAINS_MM[leg][0] for leg in LEGS], dtype=np.float64)


def segment_offsets() -> Float[np.ndarray, "6 4 3"]:
    """Each leg's four segment offsets in the zero pose (mm), legs in :data:`LEGS` order."""
    return np.array([_CHAINS_MM[leg][1:] for leg in LEGS], dtype=np.float64)


def leg_lengths() -> Float[np.ndarray, " 6"]:
    """Each leg's length, thorax-coxa to claw along the chain (mm)."""
    return np.linalg.norm(segment_offsets(), axis=-1).sum(axis=-1)


def rotations(xp, angle, axis: int):
    c, s = xp.cos(angle), xp.sin(angle)
    one, zero = xp.ones_like(angle), xp.zeros_like(angle)
    if axis == 0:
        rows = ((one, zero, zero), (zero, c, -s), (zero, s, c))
    elif axis == 1:
        rows = ((c, zero, s), (zero, one, zero), (-s, zero, c))
    else:
        rows = ((c, -s, zero), (s, c, zero), (zero, zero, one))
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def leg_forward(angles, root, offsets, xp=np):
    """Forward kinematics of leg chains, in ``xp`` (``numpy`` or ``jax.numpy``): ``angles``
    ``(..., 7)`` radians in :data:`DOF_SUFFIXES` order, ``root`` ``(..., 3)`` the thorax-coxa joint,
    ``offsets`` ``(..., 4, 3)`` of the zero pose -> ``(..., 5, 3)``: ThC, CTr, FTi, TiTa, claw."""
    pitch, roll, yaw, ctr_pitch, ctr_roll, fti, tita = (angles[..., k] for k in range(7))
    rot = rotations(xp, yaw, 0) @ rotations(xp, pitch, 1) @ rotations(xp, roll, 2)
    points = [xp.broadcast_to(root, angles.shape[:-1] + (3,))]
    joint_turns = ((ctr_pitch, ctr_roll), (fti,), (tita,), ())
    for k, turns in enumerate(joint_turns):
        points.append(points[-1] + (rot @ offsets[..., k, :, None])[..., 0])
        for j, angle in enumerate(turns):
            rot = rot @ rotations(xp, angle, 1 if j == 0 else 2)
    return xp.stack(points, axis=-2)


def forward_kinematics(
    angles: Float[np.ndarray, "T 42"], offsets: Float[np.ndarray, "6 4 3"] | None = None
) -> Float[np.ndarray, "T 6 5 3"]:
    """The model's leg joints (mm, thorax frame; legs :data:`LEGS`, joints :data:`CHAIN_JOINTS`)
    for flygym joint ``angles`` (radians, columns :func:`dof_names`); ``offsets``: segment offsets
    of the zero pose, default the model's (:func:`segment_offsets`)."""
    angles = np.asarray(angles, dtype=np.float64).reshape(-1, len(LEGS), len(DOF_SUFFIXES))
    offsets = segment_offsets() if offsets is None else np.asarray(offsets, dtype=np.float64)
    return leg_forward(angles, thorax_coxa_template(), offsets)
