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
from typing import TYPE_CHECKING, Sequence

import numpy as np
from scipy.optimize import OptimizeResult

from .ba.params import build_layout
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
DEFAULT_INIT_THRESHOLD = 40.0  # px, inlier radius of the starting triangulation
DEFAULT_OUTLIER_FACTOR = 5.0
DEFAULT_OUTLIER_MIN_PX = 3.0
DEFAULT_MAX_ROUNDS = 3
_SORTING_NFEV = 15


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
    bones: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    bone_weight: float = DEFAULT_BONE_WEIGHT,
    reject_outliers: bool = True,
    init_threshold: float = DEFAULT_INIT_THRESHOLD,
    outlier_factor: float = DEFAULT_OUTLIER_FACTOR,
    outlier_min_px: float = DEFAULT_OUTLIER_MIN_PX,
    max_rounds: int = DEFAULT_MAX_ROUNDS,
    canonical_gauge: bool = True,
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
        Initial 3D points ``(N, 3)``; consensus-triangulated from ``cameras`` if omitted.
    conf, weigh_by_confidence
        With ``weigh_by_confidence`` and ``conf`` ``(V, N)``, residuals are scaled by
        ``sqrt(conf)``; non-positive or non-finite confidences drop the observation.
    bones
        Optional bone-length prior ``(i, j, target)`` or ``(i, j, target, group)``:
        point indices into ``N``, target lengths and, optionally, which rows share one
        unknown length (the same bone in different frames); with groups the prior asks
        for constant lengths (initialized at the targets) instead of the targets
        themselves. Pairs with a non-finite or non-positive target are ignored.
    bone_weight
        Residual scale of the prior, pixels per 100 % relative length deviation.
    reject_outliers, init_threshold, outlier_factor, outlier_min_px, max_rounds
        Outlier handling (see the module docstring).
    canonical_gauge
        Report the result in the similarity frame closest to the initial rig when no
        extrinsic parameter is fixed.
    **solver_kwargs
        Passed to ``scipy.optimize.least_squares`` (``max_nfev``, ``loss``,
        ``f_scale``, ``ftol``, ...). ``jac="2-point"`` swaps the JAX Jacobian for
        finite differences with ``jac_sparsity``.

    Returns
    -------
    result : scipy.optimize.OptimizeResult
        The last round's least-squares result, plus ``initial_median_px`` /
        ``final_median_px`` (median reprojection error before / after),
        ``inliers`` ``(V, N)`` (observations used in the final fit) and ``rounds``.
    cameras : CameraGroup
        The refined rig.
    pts3d : np.ndarray
        Refined points ``(N, 3)``; NaN for points with fewer than two usable views.

    Raises
    ------
    ConfigError
        For a bad ``fixed`` / ``shared`` reference.
    ValueError
        For arrays of the wrong shape or no usable observations.
    """
    pts2d = np.asarray(pts2d, float)
    n_views = len(cameras)
    if pts2d.ndim != 3 or pts2d.shape[0] != n_views or pts2d.shape[2] != 2:
        raise ValueError(f"pts2d must be (V={n_views}, N, 2), got {pts2d.shape}")
    n_points = pts2d.shape[1]
    table0 = camera_table(cameras)
    layout = build_layout(list(cameras.names), table0.shape[1] - 10, fixed, shared)
    table0 = layout.unpack(layout.pack(table0), table0)  # tied entries start equal

    usable = np.isfinite(pts2d).all(axis=-1)
    weight = np.ones((n_views, n_points))
    if weigh_by_confidence and conf is not None:
        c = np.asarray(conf, float).reshape(n_views, n_points)
        usable &= np.isfinite(c) & (c > 0)
        weight = np.sqrt(np.where(usable, c, 0.0))

    cams0 = _cameras_from_table(cameras.names, table0)
    if pts3d is None:
        start, active = _ransac_start(cams0, pts2d, usable, init_threshold)
    else:
        start = np.asarray(pts3d, float).reshape(n_points, 3).copy()
        active = usable.copy()
    if not reject_outliers:
        active = usable.copy()

    bone_i, bone_j, bone_t, bone_g = _valid_bones(bones)
    view_idx, point_idx = np.nonzero(usable)
    table, pts = table0, start
    initial_median = None
    result = None
    rounds = 0
    for rounds in range(1, max(int(max_rounds), 1) + 1):
        problem, keep_points = _make_problem(
            table0, layout, pts2d, weight, active, pts, bone_i, bone_j, bone_t, bone_g,
            bone_weight)
        if problem is None:
            raise ValueError("bundle adjustment: no point is seen by two or more views; "
                             "nothing to fit")
        x0 = problem.pack(table, pts[keep_points])
        if initial_median is None:
            initial_median = _median_error(problem, x0)
        # The first of several rounds only sorts inliers from outliers: a few
        # iterations do, the last round gets the caller's full budget.
        sorting = reject_outliers and rounds == 1 and max_rounds > 1
        kwargs = dict(solver_kwargs)
        if sorting:
            kwargs["max_nfev"] = min(kwargs.get("max_nfev") or _SORTING_NFEV, _SORTING_NFEV)
        result = problem.solve(table, pts[keep_points], **kwargs)
        table, sub = problem.unpack(result.x)
        pts = np.full((n_points, 3), np.nan)
        pts[keep_points] = sub
        if not reject_outliers or rounds == max_rounds:
            break
        err = _errors(table, pts, view_idx, point_idx, pts2d[view_idx, point_idx])
        med = np.nanmedian(err[active[view_idx, point_idx]])
        threshold = max(outlier_min_px, outlier_factor * med)
        new_active = np.zeros_like(active)
        new_active[view_idx, point_idx] = np.nan_to_num(err, nan=np.inf) <= threshold
        if np.array_equal(new_active, active) and not sorting:
            break
        log.info("bundle adjustment round %d: %d observations beyond %.1f px set aside",
                 rounds, int(usable.sum() - new_active.sum()), threshold)
        active = new_active
        pts = np.where(np.isnan(pts), start, pts)  # points dropped earlier get a retry

    if canonical_gauge and layout.extrinsics_free:
        table, pts = _align_gauge(table0, table, pts)
    refined = _cameras_from_table(cameras.names, table)
    final_view, final_point = np.nonzero(active)
    final_err = _errors(table, pts, final_view, final_point, pts2d[final_view, final_point])
    result.initial_median_px = float(initial_median)
    result.final_median_px = float(np.nanmedian(final_err)) if final_err.size else float("nan")
    result.inliers = active
    result.rounds = rounds
    log.info("bundle adjustment: median reprojection error %.2f px -> %.2f px "
             "(%d observations, %d set aside, %d round(s), %s)",
             result.initial_median_px, result.final_median_px, int(active.sum()),
             int(usable.sum() - active.sum()), rounds, result.message)
    return result, refined, pts


def _valid_bones(bones):
    if bones is None:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), None
    i, j, t = (np.asarray(a) for a in bones[:3])
    group = np.asarray(bones[3]).astype(int) if len(bones) > 3 and bones[3] is not None else None
    ok = np.isfinite(t) & (t > 0)
    return (i[ok].astype(int), j[ok].astype(int), t[ok].astype(float),
            None if group is None else group[ok])


def _ransac_start(cameras, pts2d, usable, threshold):
    from .triangulation import triangulate_ransac

    masked = np.where(usable[..., None], pts2d, np.nan)
    pts3d, inliers = triangulate_ransac(masked, cameras, threshold=threshold)
    inliers = np.asarray(inliers, bool) & usable
    return np.asarray(pts3d, float), inliers


def _make_problem(table0, layout, pts2d, weight, active, pts, bone_i, bone_j, bone_t, bone_g,
                  bone_weight):
    """The problem over points with >= 2 active views and a finite start."""
    keep_points = (active.sum(axis=0) >= 2) & np.isfinite(pts).all(axis=1)
    if not keep_points.any():
        return None, keep_points
    compact = np.cumsum(keep_points) - 1
    obs = active & keep_points[None, :]
    view, point = np.nonzero(obs)
    bones_ok = keep_points[bone_i] & keep_points[bone_j] if bone_i.size else np.zeros(0, bool)
    problem = Problem(
        table0=table0, layout=layout, view=view, point=compact[point],
        xy=pts2d[view, point], weight=weight[view, point], n_points=int(keep_points.sum()),
        bone_i=compact[bone_i[bones_ok]], bone_j=compact[bone_j[bones_ok]],
        bone_target=bone_t[bones_ok], bone_weight=float(bone_weight),
        bone_group=None if bone_g is None else np.unique(bone_g[bones_ok],
                                                         return_inverse=True)[1])
    return problem, keep_points


def _errors(table, pts, view, point, xy):
    """Reprojection error (pixels) of observations ``xy`` of ``pts[point]`` in ``view``."""
    if view.size == 0:
        return np.zeros(0)
    proj = project_rows(np.nan_to_num(pts[point]), table[view])
    err = np.linalg.norm(proj - xy, axis=1)
    return np.where(np.isfinite(pts[point]).all(axis=1), err, np.nan)


def _median_error(problem: Problem, x: np.ndarray) -> float:
    table, pts = problem.unpack(x)
    return float(np.median(_errors(table, pts, problem.view, problem.point, problem.xy)))


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
    **kwargs,
) -> tuple[OptimizeResult, "CameraGroup", np.ndarray]:
    """Bundle-adjust the rig on a recording's 2D detections ``(V, T, P, 2)``.

    Chooses up to ``max_frames`` frames (``frame_sampling``), keeps the points named in
    ``points_to_use`` (all when ``None``; names need ``skeleton``), adds the skeleton's
    bone-length prior (``bone_prior``) and runs :func:`bundle_adjust` on the flattened
    (frame, point) observations.

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
        Add the bone-length prior (off by default: its targets come from the starting
        rig, and on the synthetic benchmark it costs accuracy, 3D error 1.9 % vs 1.2 %
        of a bone, for no gain in robustness).
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

    result, refined, flat = bundle_adjust(
        cameras, sub.reshape(n_views, n_sel * n_q, 2), fixed=fixed, shared=shared,
        conf=None if sub_conf is None else sub_conf.reshape(n_views, -1),
        weigh_by_confidence=weigh_by_confidence, bones=bones, **kwargs)
    pts3d = np.full((n_frames, n_points, 3), np.nan)
    pts3d[np.ix_(frames, point_idx)] = flat.reshape(n_sel, n_q, 3)
    result.frames = frames
    result.points = point_idx
    return result, refined, pts3d


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

    ``points_to_use``, ``fixed``, ``shared``, ``weigh_by_confidence``, ``max_frames``
    and ``frame_sampling`` come from :attr:`Config.bundle_adjustment`; the remaining
    flat keys (``max_nfev``, ``loss``, ``f_scale``, ...) go to ``least_squares``. The
    bone prior uses :meth:`Config.skeleton`.

    Returns
    -------
    result, cameras, pts3d
        As :func:`bundle_adjust_sequence`.
    """
    params = config.bundle_adjustment
    skeleton = config.skeleton()
    return bundle_adjust_sequence(
        cameras, pts2d, conf, skeleton,
        points_to_use=params.points_to_use, max_frames=params.max_frames,
        frame_sampling=params.frame_sampling, weigh_by_confidence=params.weigh_by_confidence,
        fixed=params.fixed, shared=params.shared, **dict(params.least_squares))
