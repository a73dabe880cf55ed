"""Typed views and checks of the ``refinement`` and ``kinematics`` tables."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import unknown_key
from .checks import (
    boolean,
    choice,
    got,
    integer,
    number,
    number_list,
    param,
    string_list,
)

REFINEMENT_LOSSES = ("linear", "huber", "soft_l1", "cauchy")
BODY_FRAME_KEYS = ("origin", "posterior", "anterior", "right", "left")


@dataclass(frozen=True)
class RefinementParams:
    """The ``refinement`` table (spatiotemporal 3D refinement, :mod:`flylib.refinement`).

    Attributes
    ----------
    loss, scale_px
        Robust loss of the reprojection term and its scale in pixels.
    weigh_by_confidence
        Weight each observation by the detector's confidence.
    smooth_weight, smooth_order, smooth_scale
        Temporal term: weight, difference order (1 velocity, 2 acceleration) and the per-frame
        change in world units that costs as much as ``scale_px``.
    motion_scales
        Smoothness scales tried beside ``smooth_scale``, in units of the recording's own motion
        (median per-frame ``smooth_order``-th difference of the triangulation); the one with the
        lowest held-out-view error is used. ``[]``: ``smooth_scale`` only.
    bone_weight, bone_scale, symmetric_bones
        One length per bone: weight, the deviation in world units that costs as much as
        ``scale_px``, and whether left and right bones share a length.
    rigid_points, rigid_weight, rigid_scale
        Points held at one world position (null: every ``*thorax_coxa`` point, the tethered thorax;
        ``[]``: none), weight and scale in world units.
    gap_length
        Frames a point with no supporting view is filled by the temporal term; longer gaps stay NaN.
    outlier_px
        After the first pass, observations further than this from the refined point are left out.
    max_iterations, chunk_frames, overlap_frames
        Solver iterations per chunk, frames per chunk, and context frames on each side.
    moved_fraction
        Flag points moved more than this fraction of the median bone length from the triangulation.
    """

    loss: str = param("soft_l1", choice(*REFINEMENT_LOSSES))
    scale_px: float = param(3.0, number(0, exclusive=True), kind=float)
    weigh_by_confidence: bool = param(True, boolean)
    smooth_weight: float = param(1.0, number(0), kind=float)
    smooth_order: int = param(2, choice(1, 2))
    smooth_scale: float = param(0.03, number(0, exclusive=True), kind=float)
    motion_scales: tuple[float, ...] = param(
        (1.0, 2.0, 4.0), number_list(0, exclusive=True), kind=tuple
    )
    bone_weight: float = param(1.0, number(0), kind=float)
    bone_scale: float = param(0.005, number(0, exclusive=True), kind=float)
    symmetric_bones: bool = param(False, boolean)
    rigid_points: tuple[str, ...] | None = param(None, string_list(nullable=True), kind=tuple)
    rigid_weight: float = param(1.0, number(0), kind=float)
    rigid_scale: float = param(0.005, number(0, exclusive=True), kind=float)
    gap_length: int = param(5, integer(0))
    outlier_px: float = param(20.0, number(0, exclusive=True), kind=float)
    max_iterations: int = param(10, integer(1))
    chunk_frames: int = param(1024, integer(16))
    overlap_frames: int = param(32, integer(0))
    moved_fraction: float = param(0.05, number(0, exclusive=True), kind=float)


def _triples_problems(value: Any, path: str, point_names: tuple[str, ...]) -> list[str]:
    if value is None:
        return []
    if not isinstance(value, Mapping):
        return [f"{path}: expected a mapping name -> [a, b, c] of point names, {got(value)}"]
    problems = []
    for name, triple in value.items():
        if not (
            isinstance(triple, (list, tuple))
            and len(triple) == 3
            and all(isinstance(p, str) for p in triple)
        ):
            problems.append(f"{path}.{name}: expected three point names [a, b, c], got {triple!r}")
            continue
        unknown = [p for p in triple if point_names and p not in point_names]
        if unknown:
            problems.append(
                f"{path}.{name}: unknown point(s) {unknown} (known: {', '.join(point_names)})"
            )
    return problems


def kinematics_problems(table: Mapping, point_names: tuple[str, ...]) -> list[str]:
    """Problems with the ``kinematics`` table, one ``"kinematics.<key>: ..."`` line each."""
    problems = []
    known = ("angles", "segments", "tethered", "body_frame", "allow_mirrored")
    for key in table:
        if key not in known:
            problems.append(f"kinematics.{key}: {unknown_key('parameter', key, known)}")
    problems += _triples_problems(table.get("angles"), "kinematics.angles", point_names)
    problems += _triples_problems(table.get("segments"), "kinematics.segments", point_names)
    for key in ("tethered", "allow_mirrored"):
        if key in table and boolean(table[key]):
            problems.append(f"kinematics.{key}: {boolean(table[key])}")
    frame = table.get("body_frame")
    if frame is not None:
        if not isinstance(frame, Mapping):
            problems.append(
                f"kinematics.body_frame: expected a mapping with {', '.join(BODY_FRAME_KEYS)}, {got(frame)}"
            )
        else:
            for key, value in frame.items():
                where = f"kinematics.body_frame.{key}"
                if key not in BODY_FRAME_KEYS:
                    problems.append(f"{where}: {unknown_key('key', key, BODY_FRAME_KEYS)}")
                elif string_list()(value) or not value:
                    problems.append(
                        f"{where}: expected a non-empty list of point names, {got(value)}"
                    )
                else:
                    unknown = [p for p in value if point_names and p not in point_names]
                    if unknown:
                        problems.append(f"{where}: unknown point(s) {unknown}")
            missing = [k for k in BODY_FRAME_KEYS if k not in frame]
            if missing:
                problems.append(f"kinematics.body_frame: missing {', '.join(missing)}")
    return problems


@dataclass(frozen=True)
class KinematicsParams:
    """The ``kinematics`` table (body frame and joint angles, :mod:`flylib.kinematics`).

    Attributes
    ----------
    angles
        ``name -> (a, b, c)``: the angle at ``b`` between ``b->a`` and ``b->c`` (Anipose's flexion
        angles); ``None`` = the fly default set.
    segments
        ``name -> (a, b, c)``: yaw, pitch and roll of segment ``a->b`` in the body frame, roll
        measured from the plane through ``c``; ``None`` = the six coxae.
    tethered
        One body frame for the recording (else one per frame).
    body_frame
        ``origin``, ``posterior``, ``anterior``, ``right``, ``left`` point lists; ``None`` = the
        fly's thorax-coxa points.
    allow_mirrored
        Compute angles from a mirror-image 3D anyway (:mod:`flylib.handedness`); by default refused.
    """

    angles: dict[str, tuple[str, str, str]] | None = None
    segments: dict[str, tuple[str, str, str]] | None = None
    tethered: bool = True
    body_frame: dict[str, tuple[str, ...]] | None = None
    allow_mirrored: bool = param(False, boolean, track_default=False)

    @classmethod
    def from_table(cls, table: Mapping) -> KinematicsParams:
        def triples(value):
            return None if value is None else {str(k): tuple(v) for k, v in value.items()}

        frame = table.get("body_frame")
        return cls(
            angles=triples(table.get("angles")),
            segments=triples(table.get("segments")),
            tethered=bool(table.get("tethered", True)),
            body_frame=None if frame is None else {k: tuple(v) for k, v in frame.items()},
            allow_mirrored=bool(table.get("allow_mirrored", False)),
        )
