"""Bundle adjustment of one flattened problem: :func:`bundle_adjust`.

Free camera parameters and 3D points (and optionally shared bone lengths) are fitted to the
observed 2D points by Levenberg-Marquardt on the reduced camera system (:mod:`.lm`) or
``scipy.optimize.least_squares`` (:mod:`.problem`), with the analytic JAX Jacobian, float64
throughout; :func:`bundle_adjust`'s parameters say what it does beyond a plain fit. The
configured rig is kept where the fit's held-out-view error is higher, or it moved a camera far
that no held-out view checks."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config.constants import BA_DISTORTION_MODES, BA_SOLVERS
from ..config.params import BundleAdjustmentParams
from ..errors import ConfigError
from .gauge import align_gauge, gauge_refs, open_gauge_directions, untied_extrinsics
from .lm import ReducedSystem, block_structure, solve_lm, weak_directions
from .messages import (
    fit_report,
    fit_warnings,
    log_summary,
    moved_message,
    unchecked_message,
    warn_user,
    worse_message,
)
from .params import build_layout
from .parts import align_parts, camera_parts, crossing_bones, point_parts
from .problem import Problem
from .reseed import image_radius, radial_folds, reseed_gross_cameras, view_errors
from .unknowns import (
    bones_on_unknowns,
    lengths_per_row,
    start_lengths,
    unknowns_from_columns,
    valid_bones,
)

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float, Int
    from scipy.optimize import OptimizeResult

    from ..camera.rig import CameraGroup

log = logging.getLogger(__name__)

__all__ = ["bundle_adjust", "camera_table", "cameras_from_table", "ransac_points"]

# Defaults the ``bundle_adjustment`` table also has are read from BundleAdjustmentParams.
DEFAULT_BONE_WEIGHT = 5.0  # px of residual per 100 % bone-length deviation
DEFAULT_INIT_THRESHOLD = 40.0  # px, inlier radius of the starting triangulation
#: a camera ending this far around the fly from its start is named as possibly swapped (a
#: rough start moves cameras up to ~8 degrees; neighbouring cameras are 30-45 degrees apart)
MOVED_DEG = 15.0
#: a camera moved that far is trusted only if this fraction of its observations is checked by
#: a held-out view (the point seen by two other cameras too)
CHECKED_FRACTION = 0.1
#: ... and kept unless its held-out-view error is more than this (px) above the starting rig's
WORSE_PX = 0.05
LONG_LENS_RADIUS = 0.2  # normalized image-corner radius below which zero distortion stays zero
FIRST_ROUND_FTOL = 1e-3  # relative cost decrease that ends the first (sorting) round
STABLE_FRACTION = 1e-3  # inlier set "stable": fewer observations than this changed
#: an observation set aside comes back within this fraction of the threshold only, so
#: borderline observations do not flip in and out round after round
RETURN_FRACTION = 0.8
SOLVERS = BA_SOLVERS
DISTORTION_MODES = BA_DISTORTION_MODES


def camera_table(cameras: CameraGroup) -> Float[np.ndarray, "V C"]:
    """``(V, 10 + K)`` table of stacked ``[rvec, tvec, intr, dist]`` rows."""
    intrs = np.asarray(cameras.intrs, float)
    if intrs.shape[1] != 4:
        raise ConfigError("bundle adjustment needs intrinsics packed as [fx, fy, cx, cy]")
    return np.concatenate(
        [
            np.asarray(cameras.rvecs, float),
            np.asarray(cameras.tvecs, float),
            intrs,
            np.asarray(cameras.dists, float).reshape(len(intrs), -1),
        ],
        axis=1,
    )


def cameras_from_table(names, table: np.ndarray) -> CameraGroup:
    from ..camera.rig import CameraGroup

    return CameraGroup.from_arrays(
        list(names), table[:, 0:3], table[:, 3:6], table[:, 6:10], table[:, 10:]
    )


def bundle_adjust(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V N 2"],
    *,
    fixed: Sequence[str] = (),
    shared: Sequence[Sequence[str]] = (),
    pts3d: Float[np.ndarray, "N 3"] | None = None,
    conf: Float[np.ndarray, "V N"] | None = None,
    weigh_by_confidence: bool = BundleAdjustmentParams.weigh_by_confidence,
    bones: tuple[np.ndarray, ...] | None = None,
    bone_weight: float = DEFAULT_BONE_WEIGHT,
    reject_outliers: bool = True,
    init_threshold: float = DEFAULT_INIT_THRESHOLD,
    outlier_factor: float = BundleAdjustmentParams.outlier_factor,
    outlier_min_px: float = BundleAdjustmentParams.outlier_min_px,
    max_rounds: int = BundleAdjustmentParams.max_rounds,
    canonical_gauge: bool = True,
    point_ids: Int[np.ndarray, " N"] | None = None,
    solver: str = BundleAdjustmentParams.solver,
    distortion: str = BundleAdjustmentParams.distortion,
    reseed_px: float | None = BundleAdjustmentParams.reseed_px,
    warn_ratio: float = BundleAdjustmentParams.warn_ratio,
    **solver_kwargs,
) -> tuple[OptimizeResult, CameraGroup, Float[np.ndarray, "N 3"]]:
    """Bundle-adjust a camera group (the start) against observed 2D points.

    ConfigError for a bad ``fixed`` / ``shared`` reference, solver or distortion mode;
    ValueError for arrays of the wrong shape or no usable observations.

    Parameters
    ----------
    pts2d
        Observations ``(V, N, 2)`` in pixels, NaN for missing.
    fixed, shared
        Parameter references held constant / tied together (:mod:`.params`).
    pts3d
        Initial 3D points ``(N, 3)``; robustly triangulated from ``cameras`` if omitted.
    conf, weigh_by_confidence
        With both, residuals are scaled by ``sqrt(conf)`` ``(V, N)``; a non-positive or
        non-finite confidence drops the observation.
    bones
        Bone-length rows ``(i, j, target[, group])``: point indices into ``N``, reference lengths
        and which rows share one unknown length (a bone in every frame, or left and right). With
        groups the lengths are unknowns (started at the group's median starting length) and the
        rows ask only for constancy; without, for the targets. Non-finite or non-positive
        targets are ignored.
    bone_weight
        Pixels of residual per 100 % relative length deviation.
    reject_outliers, init_threshold, outlier_factor, outlier_min_px, max_rounds
        Observations farther than ``outlier_factor`` times the median error (at least
        ``outlier_min_px``) sit out, judged first against the starting triangulation (RANSAC
        with ``init_threshold`` px), then all again after each fit, until the inlier set is
        stable or ``max_rounds`` fits were made.
    canonical_gauge
        With no extrinsic fixed, report the result in the similarity frame that maps the
        refined points onto the starting ones (:func:`~.gauge.align_gauge`).
    point_ids
        ``(N,)`` the 3D unknown each column of ``pts2d`` observes (default: its own), e.g. one
        rigid point seen in every frame.
    solver
        ``"lm"`` (:mod:`.lm`, the reduced camera system) or ``"scipy"`` (``least_squares``).
    distortion
        ``"auto"``: coefficients starting at zero stay zero on long lenses (image corner within
        ``0.2`` of the axis in normalized coordinates: the images cannot tell them from the
        rig); ``"free"``: free unless ``fixed``; ``"fixed"``: all held. A fit whose radial model
        folds inside the image is redone with that camera's distortion held.
    reseed_px
        Cameras whose median error from the start exceeds this are resected by PnP from the
        others (or re-aimed) before the joint fit; ``None``: off.
    warn_ratio
        Warn (and report) when the weakest non-gauge direction of the unit-diagonal reduced
        camera Hessian is below this fraction of the strongest.
    **solver_kwargs
        ``max_nfev``, ``loss``, ``f_scale``, ``ftol``, ``xtol``, ``gtol``; with ``"scipy"`` any
        ``least_squares`` option (``jac="2-point"``: finite differences).

    Returns
    -------
    result : scipy.optimize.OptimizeResult
        The last fit's result plus ``initial_median_px`` / ``final_median_px`` (median
        reprojection error before / after), ``inliers`` ``(V, N)`` (of the final fit),
        ``rounds``, ``warnings`` (list of str) and ``report`` (a JSON-able dict: solver, what
        was free, kept fraction per camera, rounds, repaired cameras, cameras that saw nothing
        (held), the Hessian's weakest direction).
    cameras : CameraGroup
        The refined rig.
    pts3d : np.ndarray
        Refined points ``(N, 3)``; NaN for points with fewer than two usable views."""
    # the arguments as given: a fit whose distortion folds the image is redone with them
    return _adjust(_Arguments(**locals()))


@dataclass(frozen=True, eq=False)
class _Arguments:
    """:func:`bundle_adjust`'s arguments, as given."""

    cameras: CameraGroup
    pts2d: np.ndarray
    fixed: Sequence[str]
    shared: Sequence[Sequence[str]]
    pts3d: np.ndarray | None
    conf: np.ndarray | None
    weigh_by_confidence: bool
    bones: tuple[np.ndarray, ...] | None
    bone_weight: float
    reject_outliers: bool
    init_threshold: float
    outlier_factor: float
    outlier_min_px: float
    max_rounds: int
    canonical_gauge: bool
    point_ids: np.ndarray | None
    solver: str
    distortion: str
    reseed_px: float | None
    warn_ratio: float
    solver_kwargs: dict


@dataclass
class _Rounds:
    """Where the outlier rounds of :func:`_fit_rounds` ended."""

    result: OptimizeResult
    problem: Problem
    blocks: Any
    table: np.ndarray
    pts: np.ndarray
    keep: np.ndarray
    active: np.ndarray
    rounds: int
    stable: bool


def _adjust(args: _Arguments):
    """:func:`bundle_adjust` of ``args``: its steps."""
    pts2d = np.asarray(args.pts2d, float)
    _check_arguments(pts2d, len(args.cameras), args.solver, args.distortion)
    names = list(args.cameras.names)
    n_cols = pts2d.shape[1]
    ids = np.arange(n_cols) if args.point_ids is None else np.asarray(args.point_ids, int)
    ids = ids.reshape(n_cols)
    n_unknown = int(ids.max()) + 1 if n_cols else 0
    uses = np.bincount(ids, minlength=n_unknown)
    is_shared = uses > 1

    table_user = camera_table(args.cameras)
    n_dist = table_user.shape[1] - 10
    held = _held_distortion(table_user, names, args.distortion)
    layout = build_layout(names, n_dist, [*args.fixed, *held], args.shared)
    table_user = layout.unpack(layout.pack(table_user), table_user)  # tied entries start equal
    usable, weight = _usable_observations(pts2d, args.conf, args.weigh_by_confidence)

    def triangulate(table, use):
        return ransac_points(cameras_from_table(names, table), pts2d, use, args.init_threshold)

    movable = (layout.var_index[:, :6] >= 0).all(axis=1)
    table, reseeded, start_median = _reseeded(args, table_user, movable, pts2d, usable, triangulate)
    # a camera that sees none of the points has nothing to fit: held at its start
    observed = usable.any(axis=1)
    unobserved = [n for n, seen in zip(names, observed) if not seen]
    # sides sharing no view: each part's own similarity is held, then put back (.parts)
    cam_part = camera_parts(usable, ids, n_unknown)
    n_parts = int(cam_part.max()) + 1
    fit_layout = _fit_layout(args, table, layout, held, unobserved, observed, cam_part, movable)
    n_gauge = open_gauge_directions(table, fit_layout, observed)
    cols_start = (
        triangulate(table, usable)
        if args.pts3d is None
        else np.asarray(args.pts3d, float).reshape(n_cols, 3).copy()
    )
    pts = unknowns_from_columns(cols_start, ids, n_unknown)
    pts_start = pts.copy()
    active, initial_median = _first_inliers(args, table, pts[ids], pts2d, usable)
    pt_part = point_parts(usable, ids, n_unknown, cam_part)
    bone_rows, dropped_rows = _bone_rows(args.bones, ids, pts, pt_part, n_parts)

    fit = _fit_rounds(
        args,
        table,
        fit_layout,
        pts2d,
        weight,
        usable,
        active,
        pts,
        ids,
        uses,
        bone_rows,
        triangulate,
    )
    folded = _folded_cameras(fit.table, layout, names)
    if folded:
        message = (
            f"bundle adjustment: the distortion of {', '.join(folded)} folds the image; "
            f"refitting with it held at its starting values"
        )
        log.warning(message)
        return _adjust(replace(args, fixed=[*args.fixed, *(f"{n}.dist" for n in folded)]))

    result, problem, active, rounds = fit.result, fit.problem, fit.active, fit.rounds
    final = ReducedSystem(problem.jacobian(result.x), problem.residuals(result.x), fit.blocks)
    ratio, n_weak, direction = weak_directions(final.schur(0.0)[0], n_gauge)
    warnings_out = fit_warnings(args, fit, cam_part, dropped_rows, ratio, direction, fit_layout)
    for message in warnings_out:
        warn_user(message)

    table, pts = fit.table, fit.pts
    if args.canonical_gauge and n_parts > 1:
        table, pts = align_parts(table_user, table, pts, pts_start, cam_part, pt_part, movable)
        table[~observed] = table_user[~observed]
    elif args.canonical_gauge and layout.extrinsics_free:
        table, pts = align_gauge(table_user, table, pts, pts_start)
        table[~observed] = table_user[~observed]
    moved = _moved_degrees(table_user, table, pts)
    suspects = [n for n, deg in zip(names, moved) if deg > MOVED_DEG]
    out_pts = pts[ids]
    kept_start = _held_out_verdict(names, table_user, table, pts2d, active, moved)
    if kept_start:
        # the configured rig, and the points, inliers and errors it gives
        table, suspects, moved = table_user, [], np.zeros(len(names))
        out_pts = cols_start if args.pts3d is not None else triangulate(table, usable)
        active, _ = _first_inliers(args, table, out_pts, pts2d, usable)
        fit = replace(fit, active=active)
        warnings_out.append(kept_start)
        warn_user(kept_start)
    if suspects:
        message = moved_message(suspects, [d for d in moved if d > MOVED_DEG])
        warnings_out.append(message)
        warn_user(message)
    refined = cameras_from_table(names, table)
    err = view_errors(table, out_pts, pts2d, active)
    result.initial_median_px = initial_median
    result.final_median_px = float(np.nanmedian(err[active])) if active.any() else float("nan")
    result.inliers = active
    result.rounds = rounds
    result.warnings = warnings_out
    result.report = fit_report(
        args,
        layout,
        held,
        fit,
        int(is_shared[fit.keep].sum()),
        usable,
        cam_part,
        dropped_rows,
        reseeded,
        unobserved,
        start_median,
        (ratio, n_weak),
        moved,
        initial_median,
        result.final_median_px,
        warnings_out,
    )
    if kept_start:
        result.report["kept_start"] = kept_start
    log_summary(result, usable)
    return result, refined, out_pts


def _held_out_verdict(names, table_start, table, pts2d, active, moved) -> str | None:
    """Why the configured rig is kept instead of the fit (``None``: the fit is kept): the fit's
    held-out-view error is higher, or it moved a camera far that no held-out view can check."""
    from ..accuracy import held_out_errors

    seen = np.where(active[..., None], pts2d, np.nan)[:, None]  # (V, 1, N, 2)
    errors = []
    for rig in (table_start, table):
        cameras = cameras_from_table(names, rig)
        held = held_out_errors(cameras, seen, lambda p, _c, c=cameras: (c.triangulate(p), None))
        errors.append(held["triangulation"][:, 0])
    checked = np.isfinite(errors[0]).sum(axis=1)
    unchecked = [
        (n, d)
        for n, d, c, a in zip(names, moved, checked, active.sum(axis=1))
        if d > MOVED_DEG and c < CHECKED_FRACTION * a
    ]
    if unchecked:
        return unchecked_message(*zip(*unchecked))
    if not checked.any():
        return None
    start_px, fit_px = (float(np.nanmedian(e)) for e in errors)
    log.info("bundle adjustment: held-out-view error %.2f px -> %.2f px", start_px, fit_px)
    return worse_message(start_px, fit_px) if fit_px > start_px + WORSE_PX else None


def _reseeded(args, table_user, movable, pts2d, usable, triangulate):
    """``(table, reseeded, start median per camera or None)``, gross cameras resected (no pts3d)."""
    if args.pts3d is None and args.reseed_px:
        return reseed_gross_cameras(
            table_user,
            list(args.cameras.names),
            pts2d,
            usable,
            float(args.reseed_px),
            triangulate,
            movable=movable,
        )
    return table_user, [], None


def _check_arguments(pts2d: np.ndarray, n_views: int, solver: str, distortion: str) -> None:
    """The observations' shape, the solver and the distortion mode."""
    if pts2d.ndim != 3 or pts2d.shape[0] != n_views or pts2d.shape[2] != 2:
        raise ValueError(f"pts2d must be (V={n_views}, N, 2), got {pts2d.shape}")
    if solver not in SOLVERS:
        raise ConfigError(
            f"bundle_adjustment.solver: unknown solver {solver!r}; use one of {', '.join(SOLVERS)}"
        )
    if distortion not in DISTORTION_MODES:
        raise ConfigError(
            f"bundle_adjustment.distortion: unknown mode {distortion!r}; "
            f"use one of {', '.join(DISTORTION_MODES)}"
        )


def _usable_observations(pts2d, conf, weigh_by_confidence: bool):
    """``(usable (V, N) bool, weight (V, N))``: finite observations (and, weighing by
    confidence, positive finite confidences) and their residual weights."""
    n_views, n_cols = pts2d.shape[:2]
    usable = np.isfinite(pts2d).all(axis=-1)
    weight = np.ones((n_views, n_cols))
    if weigh_by_confidence and conf is not None:
        c = np.asarray(conf, float).reshape(n_views, n_cols)
        usable &= np.isfinite(c) & (c > 0)
        weight = np.sqrt(np.where(usable, c, 0.0))
    return usable, weight


def _fit_layout(args, table, layout, held, unobserved, observed, cam_part, movable):
    """``layout`` with unobserved cameras held and, for LM, each camera group's gauge held."""
    names = list(args.cameras.names)
    n_dist = table.shape[1] - 10
    parts = ("rvec", "tvec", "intr", "dist") if n_dist else ("rvec", "tvec", "intr")
    fit_fixed = [*args.fixed, *held, *(f"{n}.{part}" for n in unobserved for part in parts)]
    n_parts = int(cam_part.max()) + 1
    # LM converges only linearly along the similarity gauge: hold one camera and one depth
    # during the fit instead; the canonical frame makes the result independent of which.
    if args.solver == "lm" and untied_extrinsics(layout):
        if n_parts == 1 and layout.extrinsics_free:
            fit_fixed += gauge_refs(table, names, observed)
        elif n_parts > 1:
            for part in range(n_parts):
                if movable[cam_part == part].all():
                    fit_fixed += gauge_refs(table, names, cam_part == part)
    return (
        build_layout(names, n_dist, fit_fixed, args.shared)
        if fit_fixed != [*args.fixed, *held]
        else layout
    )


def _first_inliers(args, table, pts_cols, pts2d, usable) -> tuple[np.ndarray, float]:
    """The first inlier set ``(V, N)``, judged against the start, and its median error."""
    err = view_errors(table, pts_cols, pts2d, usable)
    if args.reject_outliers:
        threshold = max(args.outlier_min_px, args.outlier_factor * float(np.nanmedian(err[usable])))
        active = usable & (np.nan_to_num(err, nan=np.inf) <= threshold)
    else:
        active = usable.copy()
    initial_median = float(np.nanmedian(err[active])) if active.any() else float("nan")
    return active, initial_median


def _bone_rows(bones, ids, pts, pt_part, n_parts: int):
    """``((bone_i, bone_j, bone_t, bone_g), dropped)``: bone rows on the unknowns, started from
    the start's lengths; none when the cameras form several groups (``dropped`` joined two)."""
    bone_i, bone_j, bone_t, bone_g = bones_on_unknowns(valid_bones(bones), ids)
    if bone_i.size:
        log.info(
            "bundle adjustment: %s",
            "the cameras see the body as one connected group: bone-length, left/right and "
            "thorax constraints used"
            if n_parts <= 1
            else f"the cameras form {n_parts} groups that see no point in common: "
            "length constraints not used (none joining two groups can be checked by the "
            "images, and inside a group its own views fix its shape), the groups' relative "
            "placement held at the starting rig",
        )
    dropped_rows = 0
    if n_parts > 1 and bone_i.size:
        # no image can check a length joining two groups; inside a group its own views fix
        # the shape (within-group lengths barely moved the 3D at 2.6x the solve time)
        dropped_rows = crossing_bones(bone_i, bone_j, pt_part)
        bone_i, bone_j, bone_t = bone_i[:0], bone_j[:0], bone_t[:0]
        bone_g = None
    if bone_g is not None and bone_i.size:
        bone_t = start_lengths(pts, bone_i, bone_j, bone_t, bone_g)
    return (bone_i, bone_j, bone_t, bone_g), dropped_rows


def _fit_rounds(
    args, table, fit_layout, pts2d, weight, usable, active, pts, ids, uses, bone_rows, triangulate
) -> _Rounds:
    """Fit, judge every observation again, refit, until the inlier set is stable."""
    bone_i, bone_j, bone_t, bone_g = bone_rows
    n_unknown = pts.shape[0]
    is_shared = uses > 1
    lengths = None
    result = None
    stable = not args.reject_outliers
    history = [active]
    rounds = 0
    keep = np.zeros(n_unknown, bool)
    problem = None
    blocks = None
    for rounds in range(1, max(int(args.max_rounds), 1) + 1):
        problem, keep = _make_problem(
            table,
            fit_layout,
            pts2d,
            weight,
            active,
            pts,
            ids,
            bone_i,
            bone_j,
            bone_t if lengths is None else lengths,
            bone_g,
            args.bone_weight,
        )
        if problem is None:
            raise ValueError(
                "bundle adjustment: no point is seen by two or more views; nothing to fit"
            )
        blocks = block_structure(problem, is_shared[keep])
        if args.solver == "lm":
            options = dict(args.solver_kwargs)
            if rounds == 1 and args.reject_outliers:
                # the first inlier set still holds most gross outliers: polishing a fit to it
                # only wanders; the next rounds refit on a cleaner set from here
                options["ftol"] = max(options.get("ftol", 1e-8), FIRST_ROUND_FTOL)
            result = solve_lm(problem, problem.pack(table, pts[keep]), blocks, **options)
        else:
            result = problem.solve(table, pts[keep], **args.solver_kwargs)
        table, sub = problem.unpack(result.x)
        lengths = lengths_per_row(problem, result.x, bone_i, bone_j, bone_t, bone_g, keep, lengths)
        pts = np.full((n_unknown, 3), np.nan)
        pts[keep] = sub
        if not args.reject_outliers:
            break
        lost = ~keep & (uses > 0)
        if lost.any():  # judge the observations of points that left the fit too
            again = unknowns_from_columns(triangulate(table, usable), ids, n_unknown)
            pts[lost] = again[lost]
        err = view_errors(table, pts[ids], pts2d, usable)
        threshold = max(args.outlier_min_px, args.outlier_factor * float(np.nanmedian(err[active])))
        err_inf = np.nan_to_num(err, nan=np.inf)
        new_active = usable & (err_inf <= np.where(active, 1.0, RETURN_FRACTION) * threshold)
        changed = int((new_active != active).sum())
        log.info(
            "bundle adjustment round %d (%d evaluations): median %.2f px, %d observations "
            "beyond %.1f px set aside, %d changed",
            rounds,
            result.nfev,
            float(np.nanmedian(err[active])),
            int(usable.sum() - new_active.sum()),
            threshold,
            changed,
        )
        # a set (nearly) seen before is a cycle (borderline observations flipping, or a point
        # seen twice leaving and returning): as settled as it gets
        tolerance = STABLE_FRACTION * usable.sum()
        if min(int((new_active != seen).sum()) for seen in history) <= tolerance:
            stable = True
            break
        if rounds == args.max_rounds:
            break
        active = new_active
        history.append(active)
    return _Rounds(result, problem, blocks, table, pts, keep, active, rounds, stable)


def _moved_degrees(table0, table, pts) -> np.ndarray:
    """``(V,)`` degrees, seen from the fly, between each camera's start and end; NaN without pts."""
    from ..camera.model import rvec_to_rmat_numpy

    finite = pts[np.isfinite(pts).all(axis=1)]
    if not len(finite):
        return np.full(len(table), np.nan)
    fly = np.median(finite, axis=0)
    out = []
    for row0, row in zip(table0, table):
        rays = []
        for r in (row0, row):
            rmat = rvec_to_rmat_numpy(r[None, 0:3])[0]
            ray = -rmat.T @ r[3:6] - fly
            rays.append(ray / np.linalg.norm(ray))
        out.append(np.degrees(np.arccos(np.clip(rays[0] @ rays[1], -1.0, 1.0))))
    return np.array(out)


def _held_distortion(table: np.ndarray, names, mode: str) -> list[str]:
    """References of the distortion entries ``mode`` holds fixed."""
    n_dist = table.shape[1] - 10
    if n_dist == 0 or mode == "free":
        return []
    if mode == "fixed":
        return ["*.dist"]
    held = []
    for name, row in zip(names, table):
        if image_radius(row) / 1.25 < LONG_LENS_RADIUS:
            held += [f"{name}.dist[{k}]" for k in range(n_dist) if row[10 + k] == 0.0]
    return held


def _folded_cameras(table, layout, names) -> list[str]:
    if table.shape[1] == 10:
        return []
    free = (layout.var_index[:, 10:] >= 0).any(axis=1)
    return [
        names[v]
        for v in np.flatnonzero(free)
        if radial_folds(table[v, 10:], image_radius(table[v]))
    ]


def ransac_points(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V N 2"],
    usable: Bool[np.ndarray, "V N"],
    threshold: float,
) -> Float[np.ndarray, "N 3"]:
    """Consensus-triangulated columns of the usable observations (the BA start; others are
    missing), RANSAC inlier ``threshold`` in pixels; NaN where no consensus was found."""
    from ..triangulation import triangulate_ransac

    masked = np.where(usable[..., None], pts2d, np.nan)
    pts3d, _ = triangulate_ransac(cameras, masked, threshold=threshold)
    return np.asarray(pts3d, float)


def _make_problem(
    table0, layout, pts2d, weight, active, pts, ids, bone_i, bone_j, bone_t, bone_g, bone_weight
):
    """The problem over unknowns seen actively from >= 2 views, with a finite start."""
    n_views = active.shape[0]
    n_unknown = pts.shape[0]
    seen = np.zeros((n_views, n_unknown), bool)
    v_all, c_all = np.nonzero(active)
    seen[v_all, ids[c_all]] = True
    keep = (seen.sum(axis=0) >= 2) & np.isfinite(pts).all(axis=1)
    if not keep.any():
        return None, keep
    compact = np.cumsum(keep) - 1
    obs = active & keep[ids][None, :]
    view, col = np.nonzero(obs)
    bones_ok = keep[bone_i] & keep[bone_j] if bone_i.size else np.zeros(0, bool)
    problem = Problem(
        table0=table0,
        layout=layout,
        view=view,
        point=compact[ids[col]],
        xy=pts2d[view, col],
        weight=weight[view, col],
        n_points=int(keep.sum()),
        bone_i=compact[bone_i[bones_ok]],
        bone_j=compact[bone_j[bones_ok]],
        bone_target=bone_t[bones_ok],
        bone_weight=float(bone_weight),
        bone_group=None if bone_g is None else np.unique(bone_g[bones_ok], return_inverse=True)[1],
    )
    return problem, keep
