"""Kinematics: the body frame of the fly and its joint angles.

:func:`compute_kinematics` works on a ``(T, P, 3)`` array and a skeleton;
:mod:`flylib.pipeline.kinematics` is the workflow stage (``kinematics.h5``, ``angles.csv`` in
Anipose's angles layout, ``angles.png``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config.postprocessing import KinematicsParams
from ..errors import ConfigError
from .angles import default_angles, default_segments, flexion, segment_orientation
from .frame import FRAME_KEYS, body_frame, default_frame_points, frame_from_groups, to_body

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..skeleton import Skeleton

#: What the kinematics stage writes into a recording's output directory.
FILES = ("kinematics.h5", "angles.csv", "angles.png")

__all__ = [
    "FILES",
    "FRAME_KEYS",
    "Kinematics",
    "body_frame",
    "compute_kinematics",
    "default_angles",
    "default_frame_points",
    "default_segments",
    "flexion",
    "frame_from_groups",
    "segment_orientation",
    "to_body",
]


@dataclass
class Kinematics:
    """Angles and body-frame 3D of one recording.

    ``angles`` ``(T, A)`` in degrees (NaN where a point is missing), columns ``angle_names``:
    flexion angles first, then ``<segment>_yaw/_pitch/_roll``; ``definitions`` maps each to
    the ``[a, b, c]`` point names it is computed from. ``points3d_body`` ``(T, P, 3)`` is the
    pose in the body frame ``rotation``, ``origin``: ``(3, 3)``/``(3,)`` (tethered) or
    ``(T, 3, 3)``/``(T, 3)``."""

    angle_names: list[str]
    angles: Float[np.ndarray, "T A"]
    definitions: dict[str, list[str]]
    points3d_body: Float[np.ndarray, "T P 3"]
    rotation: Float[np.ndarray, "*frames 3 3"]
    origin: Float[np.ndarray, "*frames 3"]


def _indices(skeleton, names, what: str) -> list[int]:
    missing = [n for n in names if n not in skeleton.point_names]
    if missing:
        raise ConfigError(
            f"kinematics.{what}: unknown point(s) {missing} (known: {', '.join(skeleton.point_names)})"
        )
    return [skeleton.index(n) for n in names]


def compute_kinematics(
    pts3d: Float[np.ndarray, "T P 3"],
    skeleton: Skeleton,
    *,
    angles: Mapping[str, Sequence[str]] | None = None,
    segments: Mapping[str, Sequence[str]] | None = None,
    tethered: bool = KinematicsParams.tethered,
    body_frame_points: Mapping[str, Sequence[str]] | None = None,
) -> Kinematics:
    """Body frame, body-frame 3D and joint angles of world points ``(T, P, 3)`` (NaN = missing).

    ``angles`` (flexion at ``b``) and ``segments`` (orientations) map ``name -> (a, b, c)`` point
    names; ``body_frame_points`` gives the ``origin, posterior, anterior, right, left`` groups;
    ``None`` takes :func:`default_angles`, :func:`default_segments`, :func:`default_frame_points`.
    ``tethered``: one body frame for the recording, else one per frame."""
    pts3d = np.asarray(pts3d, np.float64)
    groups_names = body_frame_points or default_frame_points(skeleton)
    groups = {k: _indices(skeleton, groups_names[k], f"body_frame.{k}") for k in FRAME_KEYS}
    rotation, origin = body_frame(pts3d, groups, tethered)
    body = to_body(pts3d, rotation, origin)
    angles = default_angles(skeleton) if angles is None else angles
    segments = default_segments(skeleton) if segments is None else segments
    names, columns, definitions = [], [], {}
    for name, triple in angles.items():
        a, b, c = _indices(skeleton, triple, f"angles.{name}")
        names.append(name)
        columns.append(flexion(pts3d, a, b, c))
        definitions[name] = list(triple)
    for name, triple in segments.items():
        a, b, c = _indices(skeleton, triple, f"segments.{name}")
        for key, values in segment_orientation(body, a, b, c).items():
            names.append(f"{name}_{key}")
            columns.append(values)
            definitions[f"{name}_{key}"] = list(triple)
    values = np.stack(columns, axis=1) if columns else np.zeros((pts3d.shape[0], 0))
    return Kinematics(names, values, definitions, body, np.asarray(rotation), np.asarray(origin))
