"""Bundle adjustment: refine the camera rig against the fly's own detected joints.

``scipy.optimize.least_squares`` over the free camera parameters and the 3D points,
with the analytic Jacobian of :func:`flylib.geometry.project_full_one` from JAX
(``jacfwd``, ``vmap``-ed over observations) assembled as a sparse matrix, float64
throughout. See :mod:`flylib.ba.params` for the ``fixed`` / ``shared`` grammar and
:mod:`flylib.ba.sampling` for ``frame_sampling``.

Robustness and gauge, beyond a plain least-squares fit:

- the starting 3D points come from a two-view consensus triangulation; its outlying
  observations sit out the first round (a short one); after every round observations reprojecting worse than ``outlier_factor`` times the
  median error (at least ``outlier_min_px``) are dropped and the fit repeated with the
  caller's loss, so gross detector errors do not bend the rig;
- an optional (``bone_prior``), weak bone-length prior (one residual per frame and bone, relative to
  :func:`flylib.pictorial.bone_length_targets`) keeps limbs at a plausible length and
  pins the near-affine depth ambiguity of the long-focal rig (letting the lengths
  float instead, ``bones=(i, j, target, group)``, leaves that ambiguity open);
- when no rotation or translation is fixed, the world frame is a free similarity
  (gauge): the refined rig and points are mapped by the similarity that best aligns
  the refined camera centres onto the initial ones, so the result does not drift.
"""

from __future__ import annotations

import logging
import warnings
from typing import TYPE_CHECKING, Sequence

import numpy as np
from scipy.optimize import OptimizeResult

from .ba.lm import ReducedSystem, block_structure, solve_lm, weak_directions
from .ba.params import build_layout, param_slices
from .ba.reseed import image_radius, radial_folds, reseed_gross_cameras, view_errors
from .ba.sampling import FRAME_SAMPLING, select_frames
from .ba.solver import Problem, project_rows
from .camera_model import rmat_to_rvec_numpy, rvec_to_rmat_numpy
from .errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from .cameras import CameraGroup
    from .config import Config
    from .skeleton import Skeleton

log = logging.getLogger(__name__)

__all__ = [
    "FRAME_SAMPLING",
    "bundle_adjust",
    "bundle_adjust_from_config",
    "bundle_adjust_sequence",
    "camera_table",
    "select_frames",
]

DEFAULT_BONE_WEIGHT = 5.0  # px of residual per 100 % bone-length deviation
DEFAULT_LENGTH_WEIGHT = 100.0  # px per 100 % deviation from a bone's common length
DEFAULT_INIT_THRESHOLD = 40.0  # px, inlier radius of the starting triangulation
DEFAULT_OUTLIER_FACTOR = 5.0
DEFAULT_OUTLIER_MIN_PX = 3.0
DEFAULT_MAX_ROUNDS = 10
DEFAULT_SOLVER = "scipy"
DEFAULT_RESEED_PX = 100.0  # px: a camera this far off at the start is resected first
DEFAULT_WARN_RATIO = 1e-9  # weakest / strongest non-gauge direction of the reduced Hessian
LONG_LENS_RADIUS = 0.2  # normalized image-corner radius below which zero distortion stays zero
STABLE_FRACTION = 1e-3  # inlier set "stable": fewer observations than this changed
SOLVERS = ("lm", "scipy")
DISTORTION_MODES = ("auto", "free", "fixed")


def camera_table(cameras: "CameraGroup") -> np.ndarray:
    """``(V, 10 + K)`` table of stacked ``[rvec, tvec, intr, dist]`` rows."""
    intrs = np.asarray(cameras.intrs, float)
    if intrs.shape[1] != 4:
        raise ConfigError("bundle adjustment needs intrinsics packed as [fx, fy, cx, cy]")
    return np.concatenate([np.asarray(cameras.rvecs, float), np.asarray(cameras.tvecs, float),
                           intrs, np.asarray(cameras.dists, float).reshape(len(intrs), -1)],
                          axis=1)


def _cameras_from_table(names, table: np.ndarray) -> "CameraGroup":
    from .cameras import CameraGroup

    return CameraGroup.from_arrays(list(names), table[:, 0:3], table[:, 3:6], table[:, 6:10],
                                   table[:, 10:])


def bundle_adjust(
    cameras: "CameraGroup",
    pts2d: np.ndarray,
    *,
    fixed: Sequence[str] = (),
    shared: Sequence[Sequence[str]] = (),
    pts3d: np.ndarray | None = None,
    conf: np.ndarray | None = None,
    weigh_by_confidence: bool = False,
    bones: tuple[np.ndarray, ...] | None = None,
    bone_weight: float = DEFAULT_BONE_WEIGHT,
    reject_outliers: bool = True,
    init_threshold: float = DEFAULT_INIT_THRESHOLD,
    outlier_factor: float = DEFAULT_OUTLIER_FACTOR,
    outlier_min_px: float = DEFAULT_OUTLIER_MIN_PX,
    max_rounds: int = DEFAULT_MAX_ROUNDS,
    canonical_gauge: bool = True,
    point_ids: np.ndarray | None = None,
    solver: str = DEFAULT_SOLVER,
    distortion: str = "auto",
    reseed_px: float | None = DEFAULT_RESEED_PX,
    warn_ratio: float = DEFAULT_WARN_RATIO,
    **solver_kwargs,
) -> tuple[OptimizeResult, "CameraGroup", np.ndarray]:
    """Bundle-adjust a camera group against observed 2D points.

    Parameters
    ----------
    cameras
        Initial rig; its stacked parameters seed the optimization.
    pts2d
        Observations ``(V, N, 2)`` in pixels, NaN for missing.
    fixed, shared
        Parameter references held constant / tied together (:mod:`flylib.ba.params`).
    pts3d
        Initial 3D points ``(N, 3)``; robustly triangulated from ``cameras`` if omitted.
    conf, weigh_by_confidence
        With ``weigh_by_confidence`` and ``conf`` ``(V, N)``, residuals are scaled by
        ``sqrt(conf)``; non-positive or non-finite confidences drop the observation.
    bones
        Optional bone-length residuals ``(i, j, target)`` or ``(i, j, target, group)``:
        point indices into ``N``, reference lengths and, optionally, which rows share one
        unknown length (the same bone in different frames, or left and right). With
        groups the lengths are unknowns (started at the group's median length over the
        starting points, the target where there is none) and the
        residuals ask only for constancy; without, for the targets themselves. Pairs
        with a non-finite or non-positive target are ignored.
    bone_weight
        Residual scale of the bone rows, pixels per 100 % relative length deviation.
    reject_outliers, init_threshold, outlier_factor, outlier_min_px, max_rounds
        Outlier handling: observations farther than ``outlier_factor`` times the
        median error (at least ``outlier_min_px``) sit out; the threshold is first
        taken from the errors against the starting triangulation (RANSAC with
        ``init_threshold`` px), then after each fit from the fitted errors, every
        observation (also those set aside before) is judged again, and rounds repeat
        until the inlier set is stable or ``max_rounds`` fits were made.
    canonical_gauge
        Report the result in the similarity frame closest to the initial rig when no
        extrinsic parameter is fixed.
    point_ids
        ``(N,)`` which 3D unknown each column of ``pts2d`` observes (default: its own).
        Columns sharing an id are one point, e.g. a rigid point seen in every frame.
    solver
        ``"lm"``: Levenberg-Marquardt on the reduced camera system
        (:mod:`flylib.ba.lm`); ``"scipy"``: ``scipy.optimize.least_squares``.
    distortion
        ``"auto"``: distortion coefficients that start at zero are held at zero on long
        lenses (image corner within ``0.2`` of the optical axis in normalized
        coordinates, where the images cannot tell them from the rig); ``"free"``:
        free unless in ``fixed``; ``"fixed"``: all held. Whatever is free, a fit whose
        radial model folds inside the image is redone with that camera's distortion
        held.
    reseed_px
        Cameras whose median error from the start exceeds this are resected by PnP
        from the others (or re-aimed) before the joint fit; ``None`` turns this off.
    warn_ratio
        Warn (and report) when the weakest direction of the unit-diagonal reduced
        camera Hessian beyond the gauge is below this fraction of the strongest.
    **solver_kwargs
        ``max_nfev``, ``loss``, ``f_scale``, ``ftol``, ``xtol``, ``gtol`` (both solvers);
        with ``solver="scipy"`` any ``scipy.optimize.least_squares`` option
        (``jac="2-point"`` swaps the JAX Jacobian for finite differences).

    Returns
    -------
    result : scipy.optimize.OptimizeResult
        The last fit's result plus ``initial_median_px`` / ``final_median_px``
        (median reprojection error before / after), ``inliers`` ``(V, N)``
        (observations used in the final fit), ``rounds``, ``warnings`` (list of str)
        and ``report`` (a JSON-able dict: solver, what was free, kept fraction per
        camera, rounds, repaired cameras, the Hessian's weakest direction).
    cameras : CameraGroup
        The refined rig.
    pts3d : np.ndarray
        Refined points ``(N, 3)``; NaN for points with fewer than two usable views.

    Raises
    ------
    ConfigError
        For a bad ``fixed`` / ``shared`` reference, solver or distortion mode.
    ValueError
        For arrays of the wrong shape or no usable observations.
    """
    pts2d = np.asarray(pts2d, float)
    n_views = len(cameras)
    if pts2d.ndim != 3 or pts2d.shape[0] != n_views or pts2d.shape[2] != 2:
        raise ValueError(f"pts2d must be (V={n_views}, N, 2), got {pts2d.shape}")
    if solver not in SOLVERS:
        raise ConfigError(f"bundle_adjustment.solver: unknown solver {solver!r}; "
                          f"use one of {', '.join(SOLVERS)}")
    if distortion not in DISTORTION_MODES:
        raise ConfigError(f"bundle_adjustment.distortion: unknown mode {distortion!r}; "
                          f"use one of {', '.join(DISTORTION_MODES)}")
    names = list(cameras.names)
    n_cols = pts2d.shape[1]
    ids = np.arange(n_cols) if point_ids is None else np.asarray(point_ids, int).reshape(n_cols)
    n_unknown = int(ids.max()) + 1 if n_cols else 0
    uses = np.bincount(ids, minlength=n_unknown)
    is_shared = uses > 1

    table_user = camera_table(cameras)
    n_dist = table_user.shape[1] - 10
    held = _held_distortion(table_user, names, distortion)
    layout = build_layout(names, n_dist, [*fixed, *held], shared)
    table_user = layout.unpack(layout.pack(table_user), table_user)  # tied entries start equal

    usable = np.isfinite(pts2d).all(axis=-1)
    weight = np.ones((n_views, n_cols))
    if weigh_by_confidence and conf is not None:
        c = np.asarray(conf, float).reshape(n_views, n_cols)
        usable &= np.isfinite(c) & (c > 0)
        weight = np.sqrt(np.where(usable, c, 0.0))

    def triangulate(table, use):
        return _ransac_points(_cameras_from_table(names, table), pts2d, use, init_threshold)

    table = table_user
    reseeded: list[str] = []
    start_median = None
    if pts3d is None and reseed_px:
        movable = (layout.var_index[:, :6] >= 0).all(axis=1)
        table, reseeded, start_median = reseed_gross_cameras(
            table_user, names, pts2d, usable, float(reseed_px), triangulate, movable=movable)
    # Levenberg-Marquardt steps along the similarity gauge (7 directions no image sees)
    # converge only linearly: hold one camera and one depth during the fit instead; the
    # canonical frame below makes the result independent of which.
    fit_layout, n_gauge = layout, (7 if layout.extrinsics_free else 0)
    if solver == "lm" and layout.extrinsics_free and _untied_extrinsics(layout):
        fit_layout = build_layout(names, n_dist, [*fixed, *held, *_gauge_refs(table, names)],
                                  shared)
        n_gauge = 0
    cols_start = (triangulate(table, usable) if pts3d is None
                  else np.asarray(pts3d, float).reshape(n_cols, 3).copy())
    pts = _unknowns_from_columns(cols_start, ids, n_unknown)

    err = _view_errors(table, pts[ids], pts2d, usable)
    if reject_outliers:
        threshold = max(outlier_min_px, outlier_factor * float(np.nanmedian(err[usable])))
        active = usable & (np.nan_to_num(err, nan=np.inf) <= threshold)
    else:
        active = usable.copy()
    initial_median = float(np.nanmedian(err[active])) if active.any() else float("nan")

    bone_i, bone_j, bone_t, bone_g = _bones_on_unknowns(_valid_bones(bones), ids)
    if bone_g is not None and bone_i.size:
        bone_t = _start_lengths(pts, bone_i, bone_j, bone_t, bone_g)
    lengths = None
    result = None
    stable = not reject_outliers
    rounds = 0
    keep = np.zeros(n_unknown, bool)
    problem = None
    blocks = None
    for rounds in range(1, max(int(max_rounds), 1) + 1):
        problem, keep = _make_problem(table, fit_layout, pts2d, weight, active, pts, ids,
                                      bone_i, bone_j, bone_t if lengths is None else lengths,
                                      bone_g, bone_weight)
        if problem is None:
            raise ValueError("bundle adjustment: no point is seen by two or more views; "
                             "nothing to fit")
        blocks = block_structure(problem, is_shared[keep])
        if solver == "lm":
            result = solve_lm(problem, problem.pack(table, pts[keep]), blocks, **solver_kwargs)
        else:
            result = problem.solve(table, pts[keep], **solver_kwargs)
        table, sub = problem.unpack(result.x)
        lengths = _lengths_per_row(problem, result.x, bone_i, bone_j, bone_t, bone_g, keep,
                                   lengths)
        pts = np.full((n_unknown, 3), np.nan)
        pts[keep] = sub
        if not reject_outliers:
            break
        lost = ~keep & (uses > 0)
        if lost.any():  # judge the observations of points that left the fit too
            again = _unknowns_from_columns(triangulate(table, usable), ids, n_unknown)
            pts[lost] = again[lost]
        err = _view_errors(table, pts[ids], pts2d, usable)
        threshold = max(outlier_min_px, outlier_factor * float(np.nanmedian(err[active])))
        new_active = usable & (np.nan_to_num(err, nan=np.inf) <= threshold)
        changed = int((new_active != active).sum())
        log.info("bundle adjustment round %d: median %.2f px, %d observations beyond %.1f px "
                 "set aside, %d changed", rounds, float(np.nanmedian(err[active])),
                 int(usable.sum() - new_active.sum()), threshold, changed)
        if changed <= STABLE_FRACTION * usable.sum():
            stable = True
            break
        if rounds == max_rounds:
            break
        active = new_active

    folded = _folded_cameras(table, layout, names)
    if folded:
        message = (f"bundle adjustment: the distortion of {', '.join(folded)} folds the image; "
                   f"refitting with it held at its starting values")
        log.warning(message)
        return bundle_adjust(
            cameras, pts2d, fixed=[*fixed, *(f"{n}.dist" for n in folded)], shared=shared,
            pts3d=pts3d, conf=conf, weigh_by_confidence=weigh_by_confidence, bones=bones,
            bone_weight=bone_weight, reject_outliers=reject_outliers,
            init_threshold=init_threshold, outlier_factor=outlier_factor,
            outlier_min_px=outlier_min_px, max_rounds=max_rounds,
            canonical_gauge=canonical_gauge, point_ids=point_ids, solver=solver,
            distortion=distortion, reseed_px=reseed_px, warn_ratio=warn_ratio,
            **solver_kwargs)

    final = ReducedSystem(problem.jacobian(result.x), problem.residuals(result.x), blocks)
    ratio, n_weak = weak_directions(final.schur(0.0)[0], n_gauge)
    warnings_out: list[str] = []
    if ratio < warn_ratio:
        warnings_out.append(
            f"the rig is poorly determined: beyond the {n_gauge} gauge directions the reduced "
            f"camera Hessian's weakest direction is {ratio:.1e} of its strongest "
            f"(< {warn_ratio:.0e}); some cameras or point groups can move with little change "
            f"in the images (e.g. a view that connects both sides is missing): check the "
            f"result, hold more parameters fixed or start from a calibration")
    if not stable:
        warnings_out.append(f"the inlier set did not settle within {rounds} rounds")
    for message in warnings_out:
        log.warning("bundle adjustment: %s", message)
        warnings.warn(f"bundle adjustment: {message}", RuntimeWarning, stacklevel=2)

    if canonical_gauge and layout.extrinsics_free:
        table, pts = _align_gauge(table_user, table, pts)
    refined = _cameras_from_table(names, table)
    out_pts = pts[ids]
    err = _view_errors(table, out_pts, pts2d, active)
    result.initial_median_px = initial_median
    result.final_median_px = float(np.nanmedian(err[active])) if active.any() else float("nan")
    result.inliers = active
    result.rounds = rounds
    result.warnings = warnings_out
    result.report = {
        "solver": solver,
        "free": _free_report(layout, names, held, problem, int(is_shared[keep].sum())),
        "kept_fraction": {n: (round(float(active[v].sum() / usable[v].sum()), 4)
                              if usable[v].any() else None) for v, n in enumerate(names)},
        "rounds": rounds,
        "inliers_stable": bool(stable),
        "reseeded": reseeded,
        "start_median_px": None if start_median is None else {
            n: (None if not np.isfinite(m) else round(float(m), 2))
            for n, m in zip(names, start_median)},
        "weakest_direction": ratio if np.isfinite(ratio) else None,
        "weak_directions": n_weak,
        "initial_median_px": initial_median if np.isfinite(initial_median) else None,
        "final_median_px": (result.final_median_px if np.isfinite(result.final_median_px)
                            else None),
        "warnings": warnings_out,
    }
    log.info("bundle adjustment: median reprojection error %.2f px -> %.2f px "
             "(%d observations, %d set aside, %d round(s), %s)",
             result.initial_median_px, result.final_median_px, int(active.sum()),
             int(usable.sum() - active.sum()), rounds, result.message)
    return result, refined, out_pts


def _untied_extrinsics(layout) -> bool:
    ext = layout.var_index[:, :6].ravel()
    return np.unique(ext).size == ext.size


def _gauge_refs(table: np.ndarray, names) -> list[str]:
    """References that pin the similarity gauge: the first camera's pose and, for scale,
    the translation entry of the camera farthest from it that scaling moves most."""
    rmats = rvec_to_rmat_numpy(table[:, 0:3])
    centres = -np.einsum("vji,vj->vi", rmats, table[:, 3:6])
    far = int(np.argmax(np.linalg.norm(centres - centres[0], axis=1)))
    if far == 0:
        return [f"{names[0]}.rvec", f"{names[0]}.tvec"]
    d_tvec = -rmats[far] @ (centres[far] - centres[0])
    return [f"{names[0]}.rvec", f"{names[0]}.tvec",
            f"{names[far]}.tvec[{int(np.argmax(np.abs(d_tvec)))}]"]


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
    return [names[v] for v in np.flatnonzero(free)
            if radial_folds(table[v, 10:], image_radius(table[v]))]


def _free_report(layout, names, held, problem, n_rigid) -> dict:
    slices = param_slices(layout.var_index.shape[1] - 10)
    per_camera = {}
    for v, name in enumerate(names):
        free = layout.var_index[v] >= 0
        per_camera[name] = [p for p, (lo, hi) in slices.items() if hi > lo and free[lo:hi].any()]
    return {"camera_variables": int(layout.n_free), "per_camera": per_camera,
            "distortion_held_at_zero": len(held), "points": int(problem.n_points),
            "rigid_points": n_rigid, "bone_lengths": int(problem.n_len),
            "bone_rows": int(problem.n_bones)}


def _unknowns_from_columns(cols: np.ndarray, ids: np.ndarray, n_unknown: int) -> np.ndarray:
    """Per-unknown start: the column's point, or the median over the columns sharing it."""
    pts = np.full((n_unknown, 3), np.nan)
    pts[ids] = cols
    shared = np.flatnonzero(np.bincount(ids, minlength=n_unknown) > 1)
    for u in shared:
        rows = cols[ids == u]
        rows = rows[np.isfinite(rows).all(axis=1)]
        pts[u] = np.median(rows, axis=0) if len(rows) else np.nan
    return pts


def _bones_on_unknowns(bones, ids):
    """Bone rows re-indexed onto the 3D unknowns, duplicates (rigid pairs) merged."""
    bi, bj, bt, bg = bones
    if bi.size == 0:
        return bi, bj, bt, bg
    ui, uj = ids[bi], ids[bj]
    key = np.stack([np.minimum(ui, uj), np.maximum(ui, uj),
                    bg if bg is not None else np.zeros_like(ui)], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    first = np.sort(first)
    first = first[ui[first] != uj[first]]
    return ui[first], uj[first], bt[first], None if bg is None else bg[first]


def _lengths_per_row(problem, x, bone_i, bone_j, bone_t, bone_g, keep, previous):
    """Each bone row's current length (the fitted unknown), to restart the next round."""
    if bone_g is None or not problem.n_len or bone_i.size == 0:
        return previous
    ok = keep[bone_i] & keep[bone_j]
    fitted = x[problem.n_cam + 3 * problem.n_points:]
    out = (bone_t if previous is None else previous).copy()
    _, group_compact = np.unique(bone_g[ok], return_inverse=True)
    out[ok] = fitted[group_compact]
    return out


def _start_lengths(pts, bone_i, bone_j, target, group):
    """Each row's group median of the starting 3D lengths (the target where none)."""
    length = np.linalg.norm(pts[bone_i] - pts[bone_j], axis=1)
    out = target.copy()
    for g in np.unique(group):
        rows = group == g
        ok = rows & np.isfinite(length) & (length > 0)
        if ok.any():
            out[rows] = np.median(length[ok])
    return out


def _valid_bones(bones):
    if bones is None:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), None
    i, j, t = (np.asarray(a) for a in bones[:3])
    group = np.asarray(bones[3]).astype(int) if len(bones) > 3 and bones[3] is not None else None
    ok = np.isfinite(t) & (t > 0)
    return (i[ok].astype(int), j[ok].astype(int), t[ok].astype(float),
            None if group is None else group[ok])


def _ransac_points(cameras, pts2d, usable, threshold):
    """Consensus-triangulated columns ``(N, 3)`` from the usable observations."""
    from .triangulation import triangulate_ransac

    masked = np.where(usable[..., None], pts2d, np.nan)
    pts3d, _ = triangulate_ransac(cameras, masked, threshold=threshold)
    return np.asarray(pts3d, float)


def _make_problem(table0, layout, pts2d, weight, active, pts, ids, bone_i, bone_j, bone_t,
                  bone_g, bone_weight):
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
        table0=table0, layout=layout, view=view, point=compact[ids[col]],
        xy=pts2d[view, col], weight=weight[view, col], n_points=int(keep.sum()),
        bone_i=compact[bone_i[bones_ok]], bone_j=compact[bone_j[bones_ok]],
        bone_target=bone_t[bones_ok], bone_weight=float(bone_weight),
        bone_group=None if bone_g is None else np.unique(bone_g[bones_ok],
                                                         return_inverse=True)[1])
    return problem, keep


def _view_errors(table, pts_cols, pts2d, usable):
    """``(V, N)`` reprojection errors of the usable observations, NaN elsewhere."""
    return view_errors(table, pts_cols, pts2d, usable)


def _errors(table, pts, view, point, xy):
    """Reprojection error (pixels) of observations ``xy`` of ``pts[point]`` in ``view``."""
    if view.size == 0:
        return np.zeros(0)
    proj = project_rows(np.nan_to_num(pts[point]), table[view])
    err = np.linalg.norm(proj - xy, axis=1)
    return np.where(np.isfinite(pts[point]).all(axis=1), err, np.nan)


def _camera_anchors(table: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """Each camera's centre and the point ``depths[v]`` ahead on its optical axis.

    Returns ``(2V, 3)``: centres first, then the viewing targets.
    """
    rmats = rvec_to_rmat_numpy(table[:, 0:3])
    centres = -np.einsum("vji,vj->vi", rmats, table[:, 3:6])
    targets = centres + depths[:, None] * rmats[:, 2]
    return np.concatenate([centres, targets])


def _align_gauge(table0: np.ndarray, table: np.ndarray, pts: np.ndarray):
    """Map the refined rig + points by the similarity that best restores the initial rig.

    Umeyama's least-squares similarity between the two rigs' camera centres *and*
    viewing targets (a point at the initial camera distance along each optical axis).
    Centres alone leave a near-gauge free: with long lenses far from the fly, moving
    the fly sideways while every camera turns to follow it barely changes any image,
    so the solution would drift; the targets pin where the rig looks.
    ``X' = s R X + t`` for points, and per camera ``R_c' = R_c R^T``,
    ``t_c' = s t_c - R_c' t`` (projections are unchanged).
    """
    if len(table) < 2:
        return table, pts
    depths = np.linalg.norm(table0[:, 3:6], axis=1)
    src, dst = _camera_anchors(table, depths), _camera_anchors(table0, depths)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    var_s = (a ** 2).sum() / len(src)
    if var_s <= 0:
        return table, pts
    scale = np.trace(np.diag(sig) @ d) / var_s
    shift = mu_d - scale * rot @ mu_s
    out = table.copy()
    for v, rmat in enumerate(rvec_to_rmat_numpy(table[:, 0:3])):
        rc = rmat @ rot.T
        out[v, 0:3] = rmat_to_rvec_numpy(rc)
        out[v, 3:6] = scale * table[v, 3:6] - rc @ shift
    return out, (scale * pts @ rot.T + shift)


def bundle_adjust_sequence(
    cameras: "CameraGroup",
    pts2d: np.ndarray,
    conf: np.ndarray | None = None,
    skeleton: "Skeleton | None" = None,
    *,
    points_to_use: Sequence[str] | None = None,
    max_frames: int | None = 200,
    frame_sampling: str = "even",
    weigh_by_confidence: bool = False,
    fixed: Sequence[str] = (),
    shared: Sequence[Sequence[str]] = (),
    bone_prior: bool = False,
    bone_lengths: bool = False,
    symmetric_bones: bool = False,
    length_weight: float = DEFAULT_LENGTH_WEIGHT,
    rigid_points: Sequence[str] = (),
    **kwargs,
) -> tuple[OptimizeResult, "CameraGroup", np.ndarray]:
    """Bundle-adjust the rig on a recording's 2D detections ``(V, T, P, 2)``.

    Chooses up to ``max_frames`` frames (``frame_sampling``), keeps the points named in
    ``points_to_use`` (all when ``None``; names need ``skeleton``), adds the skeleton's
    bone lengths (``bone_lengths``, or the older ``bone_prior``), makes the
    ``rigid_points`` one 3D point over all frames, and runs :func:`bundle_adjust` on
    the flattened (frame, point) observations.

    Parameters
    ----------
    cameras, pts2d, conf
        The rig, detections ``(V, T, P, 2)`` and confidences ``(V, T, P)`` (or ``None``).
    skeleton
        Supplies point names and bones; without it ``points_to_use`` must be ``None``
        and there is no bone prior.
    points_to_use, max_frames, frame_sampling, weigh_by_confidence, fixed, shared
        As in the ``bundle_adjustment`` config table.
    bone_prior
        Add the bone-length prior toward fixed targets (off by default: its targets come
        from the starting rig, whose errors it then reproduces).
    bone_lengths
        Each bone of the skeleton (among the used points) has one unknown length over
        all fitted frames; residual rows ``length_weight * (|Xi - Xj| - L) / L0`` ask
        every frame for it. This, not a target, is what pins a long-focal rig's shape.
    symmetric_bones
        Left and right bones (names differing only in a leading ``l``/``r``) share one
        length.
    length_weight
        Pixels of residual per 100 % deviation from the common length.
    rigid_points
        Point names that do not move over the recording (a tethered fly's thorax-coxa
        joints): one 3D unknown each instead of one per frame. Names that are not
        used points are ignored.
    **kwargs
        Forwarded to :func:`bundle_adjust` (and from there to ``least_squares``).

    Returns
    -------
    result : OptimizeResult
        As :func:`bundle_adjust`, plus ``frames`` (the fitted frame indices) and
        ``points`` (the fitted point indices).
    cameras : CameraGroup
        The refined rig.
    pts3d : np.ndarray
        ``(T, P, 3)``: the refined points of the fitted frames/points, NaN elsewhere.
    """
    pts2d = np.asarray(pts2d, float)
    if pts2d.ndim != 4 or pts2d.shape[-1] != 2:
        raise ValueError(f"pts2d must be (V, T, P, 2), got {pts2d.shape}")
    n_views, n_frames, n_points, _ = pts2d.shape
    conf_arr = None if conf is None else np.asarray(conf, float)
    point_idx = _point_indices(points_to_use, skeleton, n_points)
    frames = select_frames(pts2d[:, :, point_idx], None if conf_arr is None
                           else conf_arr[:, :, point_idx], max_frames, frame_sampling)
    sub = pts2d[:, frames][:, :, point_idx]  # (V, F, Q, 2)
    n_sel, n_q = sub.shape[1], sub.shape[2]
    sub_conf = None if conf_arr is None else conf_arr[:, frames][:, :, point_idx]

    bones = None
    if bone_prior and skeleton is not None:
        from .pictorial import bone_length_targets

        bi, bj, targets = bone_length_targets(cameras, pts2d[:, frames], skeleton)
        position = np.full(n_points, -1)
        position[point_idx] = np.arange(n_q)
        ok = (position[bi] >= 0) & (position[bj] >= 0)
        offsets = (np.arange(n_sel) * n_q)[:, None]
        bones = ((offsets + position[bi[ok]][None]).ravel(),
                 (offsets + position[bj[ok]][None]).ravel(),
                 np.tile(targets[ok], n_sel))

    point_ids = None
    names = list(skeleton.point_names) if skeleton is not None else []
    if rigid_points:
        if skeleton is None:
            raise ValueError("rigid_points names points: pass the skeleton too")
        unknown = [p for p in rigid_points if p not in names]
        if unknown:
            raise ConfigError(
                f"bundle_adjustment.rigid_points: unknown point(s) "
                f"{', '.join(map(repr, unknown))}; use names from skeleton.point_names")
        rigid_q = np.isin(point_idx, [names.index(p) for p in rigid_points])
        ids = np.arange(n_sel * n_q).reshape(n_sel, n_q)
        ids[:, rigid_q] = ids[0, rigid_q]  # every frame observes frame 0's unknown
        point_ids = np.unique(ids.ravel(), return_inverse=True)[1]
    if bone_lengths and skeleton is not None:
        if bone_prior:
            log.info("bundle adjustment: bone_lengths replaces bone_prior")
        bones = _length_unknowns(skeleton, point_idx, n_sel, symmetric_bones)
        kwargs["bone_weight"] = length_weight

    result, refined, flat = bundle_adjust(
        cameras, sub.reshape(n_views, n_sel * n_q, 2), fixed=fixed, shared=shared,
        conf=None if sub_conf is None else sub_conf.reshape(n_views, -1),
        weigh_by_confidence=weigh_by_confidence, bones=bones, point_ids=point_ids, **kwargs)
    pts3d = np.full((n_frames, n_points, 3), np.nan)
    pts3d[np.ix_(frames, point_idx)] = flat.reshape(n_sel, n_q, 3)
    result.frames = frames
    result.points = point_idx
    return result, refined, pts3d


def _length_unknowns(skeleton, point_idx, n_frames, symmetric):
    """Bone rows ``(i, j, 1, group)`` over flattened (frame, used point) columns: one
    group per bone (per left/right pair with ``symmetric``)."""
    names = list(skeleton.point_names)
    bi, bj = (np.asarray(a) for a in skeleton.bone_index_pairs())
    n_q = len(point_idx)
    position = np.full(len(names), -1)
    position[point_idx] = np.arange(n_q)
    ok = (position[bi] >= 0) & (position[bj] >= 0)
    bi, bj = bi[ok], bj[ok]
    if bi.size == 0:
        return None
    start = np.ones(bi.size)  # placeholder: bundle_adjust starts them from its 3D start

    def side_free(name):
        if name[:1] in ("l", "r") and ("r" if name[0] == "l" else "l") + name[1:] in names:
            return "*" + name[1:]
        return name

    keys = [(side_free(names[a]), side_free(names[b])) if symmetric else (names[a], names[b])
            for a, b in zip(bi, bj)]
    _, group = np.unique(np.array(keys), axis=0, return_inverse=True)
    group = np.asarray(group).ravel()
    offsets = (np.arange(n_frames) * n_q)[:, None]
    return ((offsets + position[bi][None]).ravel(), (offsets + position[bj][None]).ravel(),
            np.tile(start, n_frames), np.tile(group, n_frames))


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
            f"use names from skeleton.point_names")
    if not points_to_use:
        raise ConfigError("bundle_adjustment.points_to_use is empty; list at least two points "
                          "or remove the key to use all points")
    return np.array(sorted({names.index(p) for p in points_to_use}), int)


def bundle_adjust_from_config(
    config: "Config",
    cameras: "CameraGroup",
    pts2d: np.ndarray,
    conf: np.ndarray | None = None,
) -> tuple[OptimizeResult, "CameraGroup", np.ndarray]:
    """Run :func:`bundle_adjust_sequence` with the config's ``bundle_adjustment`` table.

    Every named key of :attr:`Config.bundle_adjustment` (``points_to_use``, ``fixed``,
    ``shared``, ``solver``, ``distortion``, outlier rounds, ``reseed_px``, bone lengths,
    ``rigid_points`` ...) is passed on; the remaining flat keys (``max_nfev``, ``loss``,
    ``f_scale``, ...) go to the solver. Bones come from :meth:`Config.skeleton`.

    Returns
    -------
    result, cameras, pts3d
        As :func:`bundle_adjust_sequence`.
    """
    params = config.bundle_adjustment
    skeleton = config.skeleton()
    names = set(skeleton.point_names)
    return bundle_adjust_sequence(
        cameras, pts2d, conf, skeleton,
        points_to_use=params.points_to_use, max_frames=params.max_frames,
        frame_sampling=params.frame_sampling, weigh_by_confidence=params.weigh_by_confidence,
        fixed=params.fixed, shared=params.shared, solver=params.solver,
        distortion=params.distortion, max_rounds=params.max_rounds,
        outlier_factor=params.outlier_factor, outlier_min_px=params.outlier_min_px,
        reseed_px=params.reseed_px, bone_lengths=params.bone_lengths,
        symmetric_bones=params.symmetric_bones, length_weight=params.length_weight,
        rigid_points=[p for p in params.rigid_points if p in names] if params.rigid_points
        else (), warn_ratio=params.warn_ratio, **dict(params.least_squares))
