"""Bundle adjustment of a recording: frame choice, bones, rigid points.

:func:`bundle_adjust_sequence` flattens a recording's ``(V, T, P, 2)`` detections into one
:func:`~.adjust.bundle_adjust` problem; the workflow's stage calls it with
:meth:`~flylib.config.params.BundleAdjustmentParams.sequence_kwargs`."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..config.params import BundleAdjustmentParams
from ..errors import ConfigError
from .adjust import DEFAULT_INIT_THRESHOLD, bundle_adjust, ransac_points
from .sampling import select_frames

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float
    from scipy.optimize import OptimizeResult

    from ..camera.rig import CameraGroup
    from ..skeleton import Skeleton

log = logging.getLogger(__name__)

__all__ = ["THORAX_POINTS", "bundle_adjust_sequence", "length_unknowns"]

#: where the legs join the thorax: one rigid, left/right mirror-symmetric body in any fly
THORAX_POINTS = tuple(f"{leg}_thorax_coxa" for leg in ("lf", "lm", "lh", "rf", "rm", "rh"))
#: a listed rigid point is merged over time only if its starting triangulation stays within
#: this many median bone lengths (median distance to its median position)
DEFAULT_RIGID_TOLERANCE = 0.15
#: ... and within this many pixels: a still point moves by about the detection noise (1.5 px),
#: while merging points that move (DeepFly3D's thorax-coxa, 5 px) keeps the inliers unsettled
DEFAULT_RIGID_PX = 3.0


def bundle_adjust_sequence(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None = None,
    skeleton: Skeleton | None = None,
    *,
    points_to_use: Sequence[str] | None = None,
    max_frames: int | None = BundleAdjustmentParams.max_frames,
    frame_sampling: str = BundleAdjustmentParams.frame_sampling,
    weigh_by_confidence: bool = BundleAdjustmentParams.weigh_by_confidence,
    fixed: Sequence[str] = (),
    shared: Sequence[Sequence[str]] = (),
    bone_prior: bool = False,
    bone_lengths: bool = BundleAdjustmentParams.bone_lengths,
    symmetric_bones: bool = BundleAdjustmentParams.symmetric_bones,
    length_weight: float = BundleAdjustmentParams.length_weight,
    rigid_points: Sequence[str] | None = None,
    rigid_tolerance: float | None = DEFAULT_RIGID_TOLERANCE,
    rigid_px: float | None = DEFAULT_RIGID_PX,
    body_points: Sequence[str] = THORAX_POINTS,
    **kwargs,
) -> tuple[OptimizeResult, CameraGroup, Float[np.ndarray, "T P 3"]]:
    """Bundle-adjust the rig on a recording's 2D detections ``(V, T, P, 2)``.

    Runs :func:`bundle_adjust` on the flattened (frame, point) observations of the chosen frames.

    Parameters
    ----------
    cameras, pts2d, conf
        The rig, detections ``(V, T, P, 2)`` and confidences ``(V, T, P)`` (or ``None``).
    skeleton
        Point names and bones; without it ``points_to_use`` must be ``None``, and no bone rows.
    points_to_use, max_frames, frame_sampling, weigh_by_confidence, fixed, shared
        As in the ``bundle_adjustment`` config table.
    bone_prior
        Pull bone lengths toward the starting rig's (whose errors it then reproduces).
    bone_lengths
        Each used bone (and distance between two ``body_points``, one rigid body) has one unknown
        length ``L`` over the fitted frames, rows ``length_weight * (|Xi - Xj| / L - 1)`` asking
        every frame for it: this, not a target, pins a long-focal rig's shape.
    symmetric_bones
        Left and right bones (names differing only in a leading ``l``/``r``) and mirror-image
        distances between ``body_points`` share one length: when each camera sees one side
        only, the symmetric thorax is what fixes one side against the other.
    length_weight
        Pixels of residual per 100 % deviation from the common length.
    rigid_points
        Points still when the body is fixed (a tethered fly's thorax-coxa joints): one 3D unknown
        each over all frames; unused points are ignored. ``None``: the skeleton's THORAX_POINTS.
    rigid_tolerance, rigid_px
        Use ``rigid_points`` only if their starting triangulation (from ``cameras``) stays
        within this many median bone lengths of its median position (median over frames, worst
        point), and that spread seen from the cameras (focal length over distance, median over
        cameras) is at most ``rigid_px`` pixels. ``None``: no such test. The decision is in
        ``result.report["rigid"]``.
    body_points
        Points of one rigid body (default :data:`THORAX_POINTS`), for ``bone_lengths``.
    **kwargs
        Forwarded to :func:`bundle_adjust` (and from there to ``least_squares``).

    Returns
    -------
    result : OptimizeResult
        As :func:`bundle_adjust`, plus ``frames`` and ``points`` (the fitted indices) and
        ``report["rigid"]`` (whether the rigid points were used and why; ``None`` without).
    cameras : CameraGroup
        The refined rig.
    pts3d : np.ndarray
        ``(T, P, 3)``: the refined points of the fitted frames/points, NaN elsewhere."""
    pts2d = np.asarray(pts2d, float)
    if pts2d.ndim != 4 or pts2d.shape[-1] != 2:
        raise ValueError(f"pts2d must be (V, T, P, 2), got {pts2d.shape}")
    n_views, n_frames, n_points, _ = pts2d.shape
    conf_arr = None if conf is None else np.asarray(conf, float)
    point_idx = _point_indices(points_to_use, skeleton, n_points)
    frames = select_frames(
        pts2d[:, :, point_idx],
        None if conf_arr is None else conf_arr[:, :, point_idx],
        max_frames,
        frame_sampling,
    )
    sub = pts2d[:, frames][:, :, point_idx]  # (V, F, Q, 2)
    n_sel, n_q = sub.shape[1], sub.shape[2]
    sub_conf = None if conf_arr is None else conf_arr[:, frames][:, :, point_idx]

    bones = None
    if bone_prior and skeleton is not None:
        bones = _bone_prior_rows(cameras, pts2d[:, frames], skeleton, point_idx)
    point_ids, rigid_report = _rigid_point_ids(
        cameras, sub, skeleton, point_idx, rigid_points, rigid_tolerance, rigid_px
    )
    if bone_lengths and skeleton is not None:
        if bone_prior:
            log.info("bundle adjustment: bone_lengths replaces bone_prior")
        bones = length_unknowns(skeleton, point_idx, n_sel, symmetric_bones, body_points)
        kwargs["bone_weight"] = length_weight

    result, refined, flat = bundle_adjust(
        cameras,
        sub.reshape(n_views, n_sel * n_q, 2),
        fixed=fixed,
        shared=shared,
        conf=None if sub_conf is None else sub_conf.reshape(n_views, -1),
        weigh_by_confidence=weigh_by_confidence,
        bones=bones,
        point_ids=point_ids,
        **kwargs,
    )
    pts3d = np.full((n_frames, n_points, 3), np.nan)
    pts3d[np.ix_(frames, point_idx)] = flat.reshape(n_sel, n_q, 3)
    result.frames = frames
    result.points = point_idx
    result.report["rigid"] = rigid_report
    return result, refined, pts3d


def _bone_prior_rows(cameras, pts2d, skeleton, point_idx) -> tuple[np.ndarray, ...]:
    """Bone rows ``(i, j, target)`` toward the starting rig's bone lengths over the flattened
    (frame, used point) columns of ``pts2d`` ``(V, F, P, 2)``."""
    from ..pictorial import bone_length_targets

    n_sel, n_q = pts2d.shape[1], len(point_idx)
    bi, bj, targets = bone_length_targets(cameras, pts2d, skeleton)
    position = np.full(pts2d.shape[2], -1)
    position[point_idx] = np.arange(n_q)
    ok = (position[bi] >= 0) & (position[bj] >= 0)
    offsets = (np.arange(n_sel) * n_q)[:, None]
    return (
        (offsets + position[bi[ok]][None]).ravel(),
        (offsets + position[bj[ok]][None]).ravel(),
        np.tile(targets[ok], n_sel),
    )


def _rigid_point_ids(cameras, sub, skeleton, point_idx, rigid_points, tolerance, tolerance_px):
    """``(point_ids, report)``: each flattened observation's 3D unknown, the ``rigid_points`` one
    point over all frames (``None``: one per observation), and :func:`_rigid_decision`'s report
    (``None`` without rigid points); ``sub`` ``(V, F, Q, 2)``: the fitted frames and points."""
    names = list(skeleton.point_names) if skeleton is not None else []
    if rigid_points is None:
        rigid_points = [p for p in THORAX_POINTS if p in names]
    if not rigid_points:
        return None, None
    if skeleton is None:
        raise ValueError("rigid_points names points: pass the skeleton too")
    unknown = [p for p in rigid_points if p not in names]
    if unknown:
        raise ConfigError(
            f"bundle_adjustment.rigid_points: unknown point(s) "
            f"{', '.join(map(repr, unknown))}; use names from skeleton.point_names"
        )
    rigid_q = np.isin(point_idx, [names.index(p) for p in rigid_points])
    report = _rigid_decision(cameras, sub, skeleton, point_idx, rigid_q, tolerance, tolerance_px)
    if not report["used"]:
        return None, report
    n_sel, n_q = sub.shape[1], sub.shape[2]
    ids = np.arange(n_sel * n_q).reshape(n_sel, n_q)
    ids[:, rigid_q] = ids[0, rigid_q]  # every frame observes frame 0's unknown
    return np.unique(ids.ravel(), return_inverse=True)[1], report


def _rigid_decision(cameras, sub, skeleton, point_idx, rigid_q, tolerance, tolerance_px) -> dict:
    """Whether the data show the rigid points still: ``{"used", "spread_bones", ...}``. The
    spread is each rigid point's median distance to its median position over the frames of its
    starting triangulation (of ``sub`` ``(V, F, Q, 2)``), in median bone lengths (worst point)
    and in pixels (times focal length over camera distance, median over the cameras)."""
    out = {
        "used": bool(rigid_q.any()),
        "points": int(rigid_q.sum()),
        "tolerance_bones": tolerance,
        "spread_bones": None,
        "tolerance_px": tolerance_px,
        "spread_px": None,
    }
    if (tolerance is None and tolerance_px is None) or not rigid_q.any():
        return out
    n_views, n_sel, n_q, _ = sub.shape
    flat = sub.reshape(n_views, -1, 2)
    pts = ransac_points(cameras, flat, np.isfinite(flat).all(-1), DEFAULT_INIT_THRESHOLD).reshape(
        n_sel, n_q, 3
    )
    bi, bj = (np.asarray(a) for a in skeleton.bone_index_pairs())
    position = np.full(len(skeleton.point_names), -1)
    position[point_idx] = np.arange(n_q)
    ok = (position[bi] >= 0) & (position[bj] >= 0)
    lengths = np.linalg.norm(pts[:, position[bi[ok]]] - pts[:, position[bj[ok]]], axis=-1)
    bone = float(np.nanmedian(lengths)) if np.isfinite(lengths).any() else float("nan")
    rigid = pts[:, rigid_q]
    with warnings.catch_warnings():  # a point never triangulated: NaN, judged below
        warnings.simplefilter("ignore", RuntimeWarning)
        centre = np.nanmedian(rigid, axis=0)
        spread = np.nanmedian(np.linalg.norm(rigid - centre, axis=-1), axis=0)
    worst_units = float(np.nanmax(spread)) if np.isfinite(spread).any() else float("inf")
    worst = worst_units / bone if bone > 0 else float("inf")
    worst_px = worst_units * _pixels_per_unit(cameras, np.nanmedian(centre, axis=0))
    out["spread_bones"] = round(worst, 4) if np.isfinite(worst) else None
    out["spread_px"] = round(worst_px, 2) if np.isfinite(worst_px) else None
    out["used"] = bool(
        (tolerance is None or worst <= tolerance)
        and (tolerance_px is None or worst_px <= tolerance_px)
    )
    log.info(
        "bundle adjustment: rigid points %s (they move %.3f median bones, %.1f px; "
        "tolerance %s bones, %s px)",
        "used" if out["used"] else "not used: the data show them moving",
        worst,
        worst_px,
        tolerance,
        tolerance_px,
    )
    return out


def _pixels_per_unit(cameras, point) -> float:
    """Median over the cameras of focal length / distance to ``point``: pixels per world unit."""
    from ..camera.model import rvec_to_rmat_numpy

    if not np.isfinite(point).all():
        return float("nan")
    rvecs = np.asarray(cameras.rvecs, float)
    rmats = rvec_to_rmat_numpy(rvecs)
    centres = -np.einsum("vji,vj->vi", rmats, np.asarray(cameras.tvecs, float))
    focal = np.asarray(cameras.intrs, float)[:, :2].mean(axis=1)
    return float(np.median(focal / np.linalg.norm(centres - point, axis=1)))


def length_unknowns(skeleton, point_idx, n_frames, symmetric, body_points=()):
    """Bone rows ``(i, j, 1, group)`` over flattened (frame, used point) columns: one group per
    bone and per pair of ``body_points`` (per left/right mirror pair with ``symmetric``)."""
    names = list(skeleton.point_names)
    bi, bj = (np.asarray(a) for a in skeleton.bone_index_pairs())
    body = [names.index(p) for p in body_points if p in names]
    pairs = {(min(a, b), max(a, b)) for a, b in zip(bi, bj)}
    extra = [
        (a, b)
        for k, a in enumerate(body)
        for b in body[k + 1 :]
        if (min(a, b), max(a, b)) not in pairs
    ]
    if extra:
        bi = np.concatenate([bi, [a for a, _ in extra]]).astype(int)
        bj = np.concatenate([bj, [b for _, b in extra]]).astype(int)
    n_q = len(point_idx)
    position = np.full(len(names), -1)
    position[point_idx] = np.arange(n_q)
    ok = (position[bi] >= 0) & (position[bj] >= 0)
    bi, bj = bi[ok], bj[ok]
    if bi.size == 0:
        return None
    start = np.ones(bi.size)  # placeholder: bundle_adjust starts them from its 3D start

    def side(name):
        mirror = ("r" if name[0] == "l" else "l") + name[1:]
        return name[0] if name[:1] in ("l", "r") and mirror in names else ""

    def key(a, b):
        """The pair's name, side-free with ``symmetric``: lf-rm and rf-lm are one."""
        if not symmetric:
            return (names[a], names[b], "")
        ends = sorted(n[1:] if side(n) else n for n in (names[a], names[b]))
        return (*ends, "same" if side(names[a]) == side(names[b]) else "cross")

    keys = [key(a, b) for a, b in zip(bi, bj)]
    _, group = np.unique(np.array(keys), axis=0, return_inverse=True)
    group = np.asarray(group).ravel()
    offsets = (np.arange(n_frames) * n_q)[:, None]
    return (
        (offsets + position[bi][None]).ravel(),
        (offsets + position[bj][None]).ravel(),
        np.tile(start, n_frames),
        np.tile(group, n_frames),
    )


def _point_indices(points_to_use, skeleton, n_points) -> np.ndarray:
    if points_to_use is None:
        return np.arange(n_points)
    if skeleton is None:
        raise ValueError("points_to_use names points: pass the skeleton too")
    names = list(skeleton.point_names)
    unknown = [p for p in points_to_use if p not in names]
    if unknown:
        raise ConfigError(
            f"bundle_adjustment.points_to_use: unknown point(s) {', '.join(map(repr, unknown))}; "
            f"use names from skeleton.point_names"
        )
    if not points_to_use:
        raise ConfigError(
            "bundle_adjustment.points_to_use is empty; list at least two points "
            "or remove the key to use all points"
        )
    return np.array(sorted({names.index(p) for p in points_to_use}), int)
