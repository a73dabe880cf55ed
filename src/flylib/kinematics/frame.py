"""The body frame: origin at the thorax-coxa centroid, x anterior, z dorsal, right-handed.

Given point groups (``origin``, ``posterior``, ``anterior``, ``right``, ``left``), the axes
of a pose are

- ``x`` = unit(mean(anterior) - mean(posterior)),
- ``y`` = the left-pointing ``mean(left) - mean(right)`` made orthogonal to ``x``,
- ``z`` = ``x`` cross ``y`` (dorsal for a fly whose left is +y when it faces +x),

and body coordinates are ``R (p - origin)`` with ``R = [x; y; z]`` (rows). Everything is
built from differences and means of the pose's own points, so rotating and translating the
whole pose leaves the body coordinates unchanged."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..config.postprocessing import KinematicsParams
from ..errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

FRAME_KEYS = ("origin", "posterior", "anterior", "right", "left")


def default_frame_points(skeleton) -> dict[str, list[str]]:
    """The fly's body-frame groups from its ``<side><leg>_thorax_coxa`` points (ConfigError
    if the skeleton lacks them: set ``kinematics.body_frame``)."""
    tc = [p for p in skeleton.point_names if p.endswith("thorax_coxa") and len(p) > 2]
    groups = {
        "origin": tc,
        "posterior": [p for p in tc if p[1] == "h"],
        "anterior": [p for p in tc if p[1] == "f"],
        "right": [p for p in tc if p[0] == "r"],
        "left": [p for p in tc if p[0] == "l"],
    }
    empty = [k for k, v in groups.items() if not v]
    if empty:
        raise ConfigError(
            f"kinematics.body_frame: the skeleton has no thorax-coxa points for {', '.join(empty)}; "
            "set kinematics.body_frame: {origin, posterior, anterior, right, left}"
        )
    return groups


def _unit(v: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def frame_from_groups(
    pts: Float[np.ndarray, "*batch P 3"], groups: dict[str, list[int]]
) -> tuple[Float[np.ndarray, "*batch 3 3"], Float[np.ndarray, "*batch 3"]]:
    """Body frame(s) of poses ``(..., P, 3)``: ``(..., 3, 3)`` rotations with rows
    ``x, y, z`` (world -> body) and ``(..., 3)`` origins."""

    def mean(key):
        return pts[..., groups[key], :].mean(axis=-2)

    x = _unit(mean("anterior") - mean("posterior"))
    left = mean("left") - mean("right")
    y = _unit(left - (left * x).sum(-1, keepdims=True) * x)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-2), mean("origin")


def steady_pose(pts: Float[np.ndarray, "T P 3"], indices: list[int]) -> Float[np.ndarray, "P 3"]:
    """One robust position per point over frames ``(T, P, 3)`` -> ``(P, 3)`` (NaN rows for
    points never seen): the mean after dropping frames more than 3 median distances from the
    mean; distances only, so the estimate moves with a rigid motion."""
    out = np.full((pts.shape[1], 3), np.nan)
    for p in indices:
        track = pts[:, p]
        track = track[np.isfinite(track).all(-1)]
        if not len(track):
            continue
        centre = track.mean(0)
        dist = np.linalg.norm(track - centre, axis=-1)
        keep = dist <= 3.0 * np.median(dist) + 1e-12
        out[p] = track[keep].mean(0)
    return out


def body_frame(
    pts3d: Float[np.ndarray, "T P 3"],
    groups: dict[str, list[int]],
    tethered: bool = KinematicsParams.tethered,
) -> tuple[Float[np.ndarray, "*frames 3 3"], Float[np.ndarray, "*frames 3"]]:
    """The body frame ``(rotation, origin)`` of world points ``(T, P, 3)`` (NaN = missing)
    from the ``groups``' point indices: ``(3, 3)`` and ``(3,)`` when ``tethered`` (from each
    frame point's :func:`steady_pose`), else ``(T, 3, 3)`` and ``(T, 3)``."""
    if tethered:
        used = sorted({p for v in groups.values() for p in v})
        return frame_from_groups(steady_pose(pts3d, used), groups)
    return frame_from_groups(pts3d, groups)


def to_body(
    pts3d: Float[np.ndarray, "T P 3"],
    rotation: Float[np.ndarray, "*frames 3 3"],
    origin: Float[np.ndarray, "*frames 3"],
) -> Float[np.ndarray, "T P 3"]:
    """World ``(T, P, 3)`` -> body coordinates with a constant or per-frame frame."""
    rotation = np.asarray(rotation)
    origin = np.asarray(origin)
    if rotation.ndim == 2:
        return (pts3d - origin) @ rotation.T
    return np.einsum("tij,tpj->tpi", rotation, pts3d - origin[:, None, :])
