"""Triangulation of whole recordings: DLT, exhaustive-pair RANSAC and greedy view dropping.

All functions take view-leading 2D points ``(V, *pts, 2)`` (``(V, T, P, 2)`` for a
recording), NaN = missing, and return ``(*pts, 3)``. The points are flattened and
processed in bounded chunks (memory stays bounded on long recordings), all with the
same closed-form, row-normalized DLT as :func:`flylib.geometry.triangulate_dlt`: DLT
and greedy by jitted JAX kernels compiled once per chunk length
(:mod:`flylib.triangulation_kernels`, imported only when those methods run), RANSAC in
NumPy (no compile, no JAX) on runs of points seen by the same views, on a few threads.
Cameras with lens distortion are handled exactly: observations are undistorted
before the linear solve, and reprojection errors are measured in the raw image.

Confidence weighting: with ``weigh_by_confidence=True`` each view's DLT rows are
scaled by ``sqrt(conf)`` and observations with non-positive or non-finite
confidence are treated as missing. RANSAC's inlier vote is never weighted.

The functions take ``(pts2d, cameras, ...)``; the seed's ``(cameras, pts2d, ...)``
order is accepted too.
"""

from __future__ import annotations

import logging
from collections import deque
from itertools import combinations, pairwise

import numpy as np

from . import camera_model
from .cameras import CameraGroup
from .config.constants import TRIANGULATION_METHODS
from .errors import ConfigError
from .resources import thread_map

log = logging.getLogger(__name__)

DEFAULT_CHUNK_POINTS = 4096
RANSAC_CHUNK_POINTS = 16384  # NumPy pieces: large enough to amortize per-call overhead
_CHUNKS_IN_FLIGHT = 4
_RANSAC_THREADS = 4


# -- input handling --------------------------------------------------------------


def _points_and_cameras(a, b):
    """Accept ``(pts2d, cameras)`` or the seed's ``(cameras, pts2d)``."""
    if isinstance(a, CameraGroup):
        a, b = b, a
    if not isinstance(b, CameraGroup):
        raise TypeError(f"expected a CameraGroup, got {type(b).__name__}")
    return np.asarray(a, dtype=np.float64), b


def _check_inputs(pts2d: np.ndarray, cameras: CameraGroup, weights) -> np.ndarray | None:
    if pts2d.ndim < 2 or pts2d.shape[-1] != 2:
        raise ValueError(f"pts2d must be (V, *pts, 2), got shape {pts2d.shape}")
    if pts2d.shape[0] != len(cameras):
        raise ValueError(
            f"pts2d has {pts2d.shape[0]} views but the rig has {len(cameras)} cameras "
            f"{cameras.names}"
        )
    if weights is None:
        return None
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != pts2d.shape[:-1]:
        raise ValueError(
            f"conf/weights must have shape {pts2d.shape[:-1]} (V, *pts), got {weights.shape}"
        )
    return weights


def _weights(conf, weigh_by_confidence: bool, weights):
    if weights is not None:
        return weights
    return conf if (weigh_by_confidence and conf is not None) else None


def _pad_to(n: int, chunk_points: int) -> int:
    """Chunk length for ``n`` points: ``chunk_points``, or a power of two >= 64 below it.

    Kernels are compiled once per chunk length, so lengths come from a short list.
    """
    size = 64
    while size < min(n, chunk_points):
        size *= 2
    return min(size, max(chunk_points, 1))


class _Rig:
    """A camera group's arrays in the form the jitted kernels take."""

    def __init__(self, cameras: CameraGroup):
        self.n_views = len(cameras)
        self.distorted = bool(np.any(cameras.dists))
        pmats = cameras.pmats
        quad, norm = camera_model.dlt_camera_constants(np, pmats)
        self.arrays = {
            "pmats": pmats,
            "quad": quad,
            "norm": norm,
            "rmats": cameras.rmats,
            "tvecs": cameras.tvecs,
            "intrs": cameras.intrs,
            "dists": camera_model.pad_dist_numpy(cameras.dists),
        }


def _padded(arr: np.ndarray, size: int, fill: float) -> np.ndarray:
    """``arr`` (V, n, ...) extended along axis 1 to ``size`` with ``fill``."""
    if arr.shape[1] == size:
        return arr
    out = np.full((arr.shape[0], size, *arr.shape[2:]), fill)
    out[:, : arr.shape[1]] = arr
    return out


def _run_chunked(kernel, pts2d, cameras, weights, chunk_points, **params):
    """Flatten ``(V, *pts, 2)``, run a jitted kernel on fixed-length chunks, reshape back.

    Returns ``(pts3d (*pts, 3), kept (V, *pts) bool)``.
    """
    rig = _Rig(cameras)
    n_views = pts2d.shape[0]
    pts_shape = pts2d.shape[1:-1]
    raw_all = pts2d.reshape(n_views, -1, 2)
    und_all = cameras.undistort_points(raw_all) if rig.distorted else raw_all
    n = raw_all.shape[1]
    w_all = None if weights is None else weights.reshape(n_views, -1)
    size = _pad_to(n, chunk_points)
    pts3d = np.full((n, 3), np.nan)
    kept = np.zeros((n_views, n), dtype=bool)
    in_flight: deque = deque()

    def collect() -> None:
        start, stop, (x, k) = in_flight.popleft()
        pts3d[start:stop] = np.asarray(x)[: stop - start]
        kept[:, start:stop] = np.asarray(k)[:, : stop - start]

    for start in range(0, n, size):
        stop = min(start + size, n)
        raw = _padded(raw_all[:, start:stop], size, np.nan)
        und = _padded(und_all[:, start:stop], size, np.nan) if rig.distorted else None
        # a zero or non-finite weight drops the view inside the kernels (dlt_features)
        w = None if w_all is None else _padded(w_all[:, start:stop], size, 0.0)
        # JAX dispatches asynchronously: keep a few chunks in flight so the kernels
        # overlap with this loop (and with each other on several cores).
        in_flight.append((start, stop, kernel(rig.arrays, raw, und, w, **params)))
        if len(in_flight) > _CHUNKS_IN_FLIGHT:
            collect()
    while in_flight:
        collect()
    return pts3d.reshape(*pts_shape, 3), kept.reshape(n_views, *pts_shape)


# -- RANSAC in NumPy: each hypothesis only where both its views see the point ---------
# Real recordings see each point in only 2-4 of the views (the default rig's side
# cameras see one side of the fly), so most of the C(V, 2) pairs have nothing to do
# for most points. The points are sorted by the set of views observing them; a run
# of points with one set is a dense block in which every pair of its views is tried
# and errors are measured in its views only: no wasted pairs, no gathers in the inner
# loop, and no XLA compile per input size (short workflow jobs pay nothing up front).


class _RansacViews:
    """Reprojection constants of a subset ``views`` ``(K,)`` of a rig."""

    def __init__(self, cameras: CameraGroup, pmats: np.ndarray, views: np.ndarray):
        self.n_sel = len(views)
        self.distorted = bool(np.any(cameras.dists[views]))
        if self.distorted:
            # Through the camera frame [R | t] and the lens model, as in ``project``.
            rows = np.concatenate([cameras.rmats[views], cameras.tvecs[views, :, None]], axis=2)
            self.dists = camera_model.pad_dist_numpy(cameras.dists[views]).T[:, :, None]  # (12, K, 1)
            self.intrs = cameras.intrs[views].T[:, :, None]  # (4, K, 1)
        else:
            rows = pmats[views]
        self.rows = np.ascontiguousarray(rows.transpose(1, 0, 2).reshape(3 * self.n_sel, 4))

    def sq_errors(self, pts4, raw_u, raw_v):
        """Squared pixel errors ``(K, n)`` of homogeneous points ``(4, n)`` against ``raw_u/v`` ``(K, n)``."""
        k = self.n_sel
        hom = np.einsum("rc,cn->rn", self.rows, pts4)  # no multi-threaded BLAS call
        inv_depth = 1.0 / hom[2 * k :]
        u, v = hom[:k] * inv_depth, hom[k : 2 * k] * inv_depth
        if self.distorted:
            radial, add_x, add_y = camera_model.distortion_terms(u, v, self.dists)
            intr = self.intrs
            u = intr[0] * (u * radial + add_x) + intr[2]
            v = intr[1] * (v * radial + add_y) + intr[3]
        u -= raw_u
        v -= raw_v
        u *= u
        v *= v
        u += v
        return u


def _ransac_block(cameras, pmats, raw, und, weights, views, threshold, min_inliers):
    """Exhaustive-pair RANSAC for points observed in (at most) ``views`` ``(K,)``.

    ``raw`` / ``und`` ``(K, n, 2)``: raw and undistorted pixels in those views (NaN =
    missing); ``weights`` ``(K, n)`` or None. Returns ``(pts3d (n, 3), inliers (K, n))``.
    """
    n_sel, n = raw.shape[:2]
    quad, norm = camera_model.dlt_camera_constants(np, pmats[views])
    feats, valid = camera_model.dlt_features(np, und, norm, weights)  # (6, K, n)
    terms = np.einsum("kfc,fkn->kcn", quad, feats)  # (K, 9, n) normal-equation terms
    valid = valid.astype(np.uint8)
    raw_u, raw_v = np.ascontiguousarray(raw[..., 0]), np.ascontiguousarray(raw[..., 1])
    project = _RansacViews(cameras, pmats, views)
    threshold_sq = threshold * threshold
    # Lexicographic (most inliers, then least total inlier error) as one number,
    # count - total * scale: the total is below count * threshold, so the scaled
    # total stays under 1 and never flips a count.
    scale = 1.0 / (len(cameras) * threshold + 1.0)
    bits = np.exp2(np.arange(n_sel))[:, None]
    pts4 = np.ones((4, n))
    best_score = np.full(n, -np.inf)
    best_code = np.zeros(n)  # the winning hypothesis' inliers, as bits over ``views``
    for i, j in combinations(np.flatnonzero(valid.any(axis=1)), 2):
        pts4[0], pts4[1], pts4[2] = camera_model.dlt_solve_components(np, terms[i] + terms[j], valid[i] + valid[j])
        err_sq = project.sq_errors(pts4, raw_u, raw_v)
        np.fmin(err_sq, threshold_sq, out=err_sq)  # NaN (missing view, no hypothesis) fails
        inlier = err_sq < threshold_sq
        contrib = np.sqrt(err_sq, out=err_sq)
        contrib *= -scale
        contrib += 1.0
        contrib *= inlier
        score = contrib.sum(axis=0)
        better = score > best_score  # the first of equal hypotheses wins, in pair order
        best_score = np.where(better, score, best_score)
        best_code = np.where(better, (inlier * bits).sum(axis=0), best_code)
    inliers = (best_code.astype(np.int64) >> np.arange(n_sel)[:, None]) & 1 == 1
    summed = np.einsum("kcn,kn->cn", terms, inliers)
    pts3d = camera_model.dlt_solve_terms(np, summed, inliers.sum(axis=0), max(min_inliers, 2))
    return pts3d, inliers & np.isfinite(pts3d).all(axis=-1)[None]


def _finite(pts2d):
    """``(..., 2)`` -> ``(...)``: both coordinates finite (faster than ``.all(-1)``)."""
    return np.isfinite(pts2d[..., 0]) & np.isfinite(pts2d[..., 1])


def _ransac_numpy(pts2d, cameras, weights, chunk_points, threshold, min_inliers):
    """:func:`triangulate_ransac` on flattened points, by runs of equally seen points."""
    n_views = len(cameras)
    pmats = cameras.pmats
    pts_shape = pts2d.shape[1:-1]
    raw_all = pts2d.reshape(n_views, -1, 2)
    und_all = cameras.undistort_points(raw_all)
    n = raw_all.shape[1]
    w_all = None if weights is None else weights.reshape(n_views, -1)
    # A dropped observation (zero / bad weight) is missing everywhere, vote included.
    usable = True if w_all is None else np.isfinite(w_all) & (w_all > 0)
    vote = _finite(raw_all) & usable
    valid = vote if und_all is raw_all else _finite(und_all) & usable
    valid_count = valid.sum(axis=0)
    # Points with fewer than two usable views stay NaN. The rest are sorted by the set
    # of views observing them and processed in runs of one set, in pieces of at most
    # ``chunk_points`` (beyond 62 views the key ignores the later ones: runs are then
    # less uniform, which costs time, not correctness).
    key_views = min(n_views, 62)
    key = np.zeros(n, dtype=np.min_scalar_type((1 << key_views) - 1))
    for v in range(key_views):
        key |= vote[v].astype(key.dtype) << v
    todo = np.flatnonzero(valid_count >= 2)
    todo = todo[np.argsort(key[todo], kind="stable")]
    key = key[todo]
    bounds = [0, *(np.flatnonzero(key[1:] != key[:-1]) + 1), len(todo)]
    size = max(int(chunk_points), 1)
    pieces = [
        todo[start : min(start + size, stop)]
        for first, stop in pairwise(bounds)
        for start in range(first, stop, size)
    ]
    pts3d = np.full((n, 3), np.nan)
    kept = np.zeros((n_views, n), dtype=bool)

    def run(sel):
        seen = vote.take(sel, axis=1)
        views = np.flatnonzero(seen.any(axis=1))
        raw = np.where(seen[views, :, None], raw_all.take(sel, axis=1)[views], np.nan)
        und = raw if und_all is raw_all else und_all.take(sel, axis=1)[views]
        w = None if w_all is None else w_all.take(sel, axis=1)[views]
        with np.errstate(all="ignore"):
            pts3d[sel], inliers = _ransac_block(cameras, pmats, raw, und, w, views, threshold, min_inliers)
        seen[:] = False
        seen[views] = inliers
        kept[:, sel] = seen

    # NumPy releases the GIL in its loops: pieces run on a few threads (disjoint outputs).
    for _ in thread_map(run, pieces, _RANSAC_THREADS):
        pass
    return pts3d.reshape(*pts_shape, 3), kept.reshape(n_views, *pts_shape)


# -- public API ----------------------------------------------------------------------


def triangulate(
    pts2d,
    cameras,
    conf=None,
    weigh_by_confidence: bool = False,
    *,
    weights=None,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> np.ndarray:
    """NaN-aware (optionally confidence-weighted) DLT triangulation.

    Parameters
    ----------
    pts2d
        ``(V, *pts, 2)`` pixels, NaN = missing.
    cameras
        The rig (:class:`~flylib.cameras.CameraGroup`).
    conf
        Optional confidences ``(V, *pts)``; used when ``weigh_by_confidence``.
    weigh_by_confidence
        Scale each view's rows by ``sqrt(conf)``.
    weights
        Explicit per-observation weights ``(V, *pts)`` (overrides ``conf``).
    chunk_points
        Points per vectorized chunk.

    Returns
    -------
    np.ndarray
        ``(*pts, 3)``; NaN where fewer than two views observe the point.
    """
    pts2d, cameras = _points_and_cameras(pts2d, cameras)
    w = _check_inputs(pts2d, cameras, _weights(conf, weigh_by_confidence, weights))
    from .triangulation_kernels import dlt_chunk

    return _run_chunked(dlt_chunk, pts2d, cameras, w, chunk_points)[0]


def reprojection_error(pts3d, pts2d, cameras) -> np.ndarray:
    """Per-observation reprojection error in pixels.

    Parameters
    ----------
    pts3d
        ``(*pts, 3)``.
    pts2d
        ``(V, *pts, 2)``.
    cameras
        The rig. (The seed's order ``(cameras, pts3d, pts2d)`` is accepted too.)

    Returns
    -------
    np.ndarray
        ``(V, *pts)``; NaN where the observation or the 3D point is missing.
    """
    if isinstance(pts3d, CameraGroup):
        pts3d, pts2d, cameras = pts2d, cameras, pts3d
    pts3d = np.asarray(pts3d, dtype=np.float64)
    pts2d, cameras = _points_and_cameras(pts2d, cameras)
    _check_inputs(pts2d, cameras, None)
    if pts3d.shape[:-1] != pts2d.shape[1:-1]:
        raise ValueError(f"pts3d shape {pts3d.shape} does not match pts2d shape {pts2d.shape}")
    diff = cameras.project(pts3d) - pts2d
    return np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)


def triangulate_ransac(
    pts2d,
    cameras,
    threshold: float = 15.0,
    min_inliers: int = 2,
    conf=None,
    weigh_by_confidence: bool = False,
    *,
    weights=None,
    chunk_points: int = RANSAC_CHUNK_POINTS,
) -> tuple[np.ndarray, np.ndarray]:
    """Robust triangulation from the largest set of mutually consistent views.

    Every two-view hypothesis (all ``C(V, 2)`` pairs: the deterministic limit of
    RANSAC for a handful of cameras) is triangulated and scored by the number of
    views that reproject within ``threshold`` pixels (unweighted; NaN views never
    count); ties go to the smaller total inlier error. The point is refitted from
    the winning inliers (confidence-weighted when asked).

    Parameters
    ----------
    pts2d, cameras, conf, weigh_by_confidence, weights, chunk_points
        As in :func:`triangulate`.
    threshold
        Inlier reprojection-error cutoff in pixels.
    min_inliers
        Fewest agreeing views to accept a point (>= 2).

    Returns
    -------
    pts3d : np.ndarray
        ``(*pts, 3)``; NaN below ``min_inliers``.
    inliers : np.ndarray
        ``(V, *pts)`` bool, the views the accepted point was fitted from (all
        False for a rejected point).

    Raises
    ------
    ValueError
        If ``min_inliers < 2`` or ``threshold <= 0``.
    """
    if int(min_inliers) < 2:
        raise ValueError(f"min_inliers must be >= 2, got {min_inliers}")
    if not threshold > 0:
        raise ValueError(f"threshold must be a positive number of pixels, got {threshold}")
    pts2d, cameras = _points_and_cameras(pts2d, cameras)
    w = _check_inputs(pts2d, cameras, _weights(conf, weigh_by_confidence, weights))
    return _ransac_numpy(pts2d, cameras, w, chunk_points, float(threshold), int(min_inliers))


def triangulate_greedy(
    pts2d,
    cameras,
    reproj_threshold: float = 40.0,
    max_drops: int = 5,
    conf=None,
    weigh_by_confidence: bool = False,
    *,
    weights=None,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> tuple[np.ndarray, np.ndarray]:
    """DLT, then repeatedly drop each offending point's worst-reprojecting view.

    While a point's largest reprojection error exceeds ``reproj_threshold``, its
    worst view is removed and the point re-triangulated from the rest, at most
    ``max_drops`` times. A point left with fewer than two views becomes NaN.

    Parameters
    ----------
    pts2d, cameras, conf, weigh_by_confidence, weights, chunk_points
        As in :func:`triangulate`.
    reproj_threshold
        Pixels.
    max_drops
        Most views removed per point.

    Returns
    -------
    pts3d : np.ndarray
        ``(*pts, 3)``.
    kept : np.ndarray
        ``(V, *pts)`` bool, the views the final point was fitted from.
    """
    if int(max_drops) < 0:
        raise ValueError(f"max_drops must be >= 0, got {max_drops}")
    pts2d, cameras = _points_and_cameras(pts2d, cameras)
    w = _check_inputs(pts2d, cameras, _weights(conf, weigh_by_confidence, weights))
    from .triangulation_kernels import greedy_chunk

    return _run_chunked(
        greedy_chunk,
        pts2d,
        cameras,
        w,
        chunk_points,
        threshold=float(reproj_threshold),
        max_drops=int(max_drops),
    )


def _finish(pts3d, pts2d, cameras, kept):
    clean = pts2d if kept is None else np.where(kept[..., None], pts2d, np.nan)
    return pts3d, clean, reprojection_error(pts3d, clean, cameras)


def reconstruct_dlt(pts2d, cameras, conf=None, weigh_by_confidence: bool = False, **kwargs):
    """Plain DLT reconstruction.

    Returns
    -------
    pts3d : np.ndarray
        ``(*pts, 3)``.
    pts2d : np.ndarray
        The input ``(V, *pts, 2)`` (no view is rejected).
    reproj_error : np.ndarray
        ``(V, *pts)`` pixels.
    """
    pts2d, cameras = _points_and_cameras(pts2d, cameras)
    pts3d = triangulate(pts2d, cameras, conf, weigh_by_confidence, **kwargs)
    return _finish(pts3d, pts2d, cameras, None)


def reconstruct_ransac(
    pts2d,
    cameras,
    threshold: float = 15.0,
    min_inliers: int = 2,
    conf=None,
    weigh_by_confidence: bool = False,
    **kwargs,
):
    """:func:`triangulate_ransac` plus cleaned 2D (outlier views NaN) and errors.

    Returns
    -------
    pts3d, pts2d_clean, reproj_error
        ``(*pts, 3)``, ``(V, *pts, 2)`` keeping only the inlier views of accepted
        points, and ``(V, *pts)`` errors against the cleaned 2D.
    """
    pts2d, cameras = _points_and_cameras(pts2d, cameras)
    pts3d, inliers = triangulate_ransac(
        pts2d, cameras, threshold, min_inliers, conf, weigh_by_confidence, **kwargs
    )
    return _finish(pts3d, pts2d, cameras, inliers)


def reconstruct_greedy(
    pts2d,
    cameras,
    reproj_threshold: float = 40.0,
    max_drops: int = 5,
    conf=None,
    weigh_by_confidence: bool = False,
    **kwargs,
):
    """:func:`triangulate_greedy` plus cleaned 2D (dropped views NaN) and errors."""
    pts2d, cameras = _points_and_cameras(pts2d, cameras)
    pts3d, kept = triangulate_greedy(
        pts2d, cameras, reproj_threshold, max_drops, conf, weigh_by_confidence, **kwargs
    )
    return _finish(pts3d, pts2d, cameras, kept)


_PARAMS = {
    "ransac": ("threshold", "min_inliers"),
    "greedy": ("reproj_threshold", "max_drops"),
    "dlt": (),
}


def reconstruct(pts2d, cameras, method: str = "ransac", conf=None, **params):
    """Dispatch to :func:`reconstruct_ransac`, :func:`reconstruct_greedy` or :func:`reconstruct_dlt`.

    Parameters
    ----------
    pts2d, cameras, conf
        As in :func:`triangulate`.
    method
        ``"ransac"``, ``"greedy"`` or ``"dlt"``.
    **params
        ``weigh_by_confidence``, ``chunk_points`` and the method's own knobs:
        ``threshold`` (alias ``ransac_threshold``) and ``min_inliers`` for ransac,
        ``reproj_threshold`` and ``max_drops`` for greedy. Knobs of the other
        methods are ignored.

    Returns
    -------
    pts3d, pts2d_clean, reproj_error
    """
    if method not in _PARAMS:
        raise ValueError(f"unknown triangulation method {method!r}; use one of {TRIANGULATION_METHODS}")
    if "ransac_threshold" in params:
        params.setdefault("threshold", params.pop("ransac_threshold"))
    common = {k: params[k] for k in ("weigh_by_confidence", "chunk_points", "weights") if k in params}
    own = {k: params[k] for k in _PARAMS[method] if k in params}
    func = {"ransac": reconstruct_ransac, "greedy": reconstruct_greedy, "dlt": reconstruct_dlt}[method]
    return func(pts2d, cameras, conf=conf, **own, **common)


def reconstruct_from_config(config, pts2d, cameras, conf=None):
    """Run the triangulation stage as ``config.triangulation`` says.

    Reads ``method``, ``ransac_threshold``, ``min_inliers``, ``weigh_by_confidence``,
    ``reproj_threshold`` and ``max_drops`` (attributes of the params object, or
    keys of a mapping); missing ones take the defaults of :func:`reconstruct`.

    Returns
    -------
    pts3d, pts2d_clean, reproj_error
        ``(T, P, 3)``, ``(V, T, P, 2)``, ``(V, T, P)``.

    Raises
    ------
    ConfigError
        If ``triangulation.method`` is not one of ``ransac``, ``greedy``, ``dlt``.
    """
    params = getattr(config, "triangulation", None)
    if params is None and isinstance(config, dict):
        params = config.get("triangulation")

    def get(name, default):
        if params is None:
            return default
        if isinstance(params, dict):
            return params.get(name, default)
        return getattr(params, name, default)

    method = get("method", "ransac")
    if method not in TRIANGULATION_METHODS:
        raise ConfigError(f"triangulation.method must be one of {list(TRIANGULATION_METHODS)}, got {method!r}")
    log.info("triangulating with %s", method)
    return reconstruct(
        pts2d,
        cameras,
        method=method,
        conf=conf,
        threshold=float(get("ransac_threshold", 15.0)),
        min_inliers=int(get("min_inliers", 2)),
        weigh_by_confidence=bool(get("weigh_by_confidence", False)),
        reproj_threshold=float(get("reproj_threshold", 40.0)),
        max_drops=int(get("max_drops", 5)),
    )
