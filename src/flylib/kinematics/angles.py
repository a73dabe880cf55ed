"""Joint angles: Anipose's flexion angles and segment orientation in the body frame.

A flexion angle ``[a, b, c]`` is the angle at ``b`` between ``b->a`` and ``b->c`` in degrees
(Anipose's ``angles`` convention: 180 = straight). A segment ``[a, b, c]`` gives the
orientation of ``a->b`` in the body frame: ``yaw`` (from +x towards +y, in the horizontal
plane), ``pitch`` (elevation above the body's xy-plane) and ``roll`` (rotation about the
segment of the plane through ``a, b, c``, zero when that plane contains the body's z axis,
positive counter-clockwise looking from ``a`` to ``b``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float


def flexion(pts: Float[np.ndarray, "T P 3"], a: int, b: int, c: int) -> Float[np.ndarray, " T"]:
    """Angle at ``b`` in degrees, ``(T,)`` from ``(T, P, 3)`` (NaN where a point is missing)."""
    v1 = pts[:, a] - pts[:, b]
    v2 = pts[:, c] - pts[:, b]
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = (v1 * v2).sum(-1) / (np.linalg.norm(v1, axis=-1) * np.linalg.norm(v2, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def segment_orientation(
    body: Float[np.ndarray, "T P 3"], a: int, b: int, c: int
) -> dict[str, Float[np.ndarray, " T"]]:
    """``yaw``, ``pitch``, ``roll`` in degrees ``(T,)`` of segment ``a->b`` in body coordinates."""
    v = body[:, b] - body[:, a]
    yaw = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    pitch = np.degrees(np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1])))
    with np.errstate(invalid="ignore", divide="ignore"):
        u = v / np.linalg.norm(v, axis=-1, keepdims=True)
        n = np.cross(u, body[:, c] - body[:, b])
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        ref = np.cross(u, [0.0, 0.0, 1.0])
        ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
    roll = np.degrees(np.arctan2((u * np.cross(ref, n)).sum(-1), (ref * n).sum(-1)))
    return {"yaw": yaw, "pitch": pitch, "roll": roll}


def default_angles(skeleton) -> dict[str, tuple[str, str, str]]:
    """Flexion at every inner joint of the legs (chains named ``*_leg``; all chains when none
    is), named ``<joint>_flex`` (e.g. ``lf_femur_tibia_flex``)."""
    chains = {k: v for k, v in skeleton.limbs.items() if k.endswith("_leg")} or dict(skeleton.limbs)
    out = {}
    for chain in chains.values():
        for a, b, c in zip(chain[:-2], chain[1:-1], chain[2:]):
            out[f"{b}_flex"] = (a, b, c)
    return out


def default_segments(skeleton) -> dict[str, tuple[str, str, str]]:
    """The first segment of every leg chain (the fly's coxae), named ``<leg>_coxa``."""
    out = {}
    for name, chain in skeleton.limbs.items():
        if name.endswith("_leg") and len(chain) >= 3:
            out[f"{name[: -len('_leg')]}_coxa"] = (chain[0], chain[1], chain[2])
    return out
