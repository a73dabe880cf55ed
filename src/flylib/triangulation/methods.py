"""Triangulation of whole recordings: DLT, exhaustive-pair RANSAC and greedy view dropping.

The points (``(V, T, P, 2)`` for a recording) are flattened and processed in bounded chunks,
all with the closed-form, row-normalized DLT of :func:`flylib.camera.jax_model.triangulate_dlt`:
DLT (:meth:`flylib.camera.rig.CameraGroup.triangulate`) and greedy (:mod:`.kernels`) by jitted
JAX kernels compiled once per chunk length and imported only when those methods run, RANSAC in
NumPy (no compile, no JAX) on runs of points seen by the same views, on a few threads. Lens
distortion is handled exactly: observations are undistorted before the linear solve, and
reprojection errors are measured in the raw image."""

from __future__ import annotations

from itertools import combinations, pairwise
from typing import TYPE_CHECKING

import numpy as np

from ..camera import model as camera_model
from ..config.constants import TRIANGULATION_METHODS
from ..config.params import TriangulationParams
from ..resources import thread_map

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

    from ..camera.rig import CameraGroup


DEFAULT_CHUNK_POINTS = 4096  # = camera.jax_model.DLT_CHUNK_POINTS (not imported: no JAX here)
RANSAC_CHUNK_POINTS = 16384  # NumPy pieces: large enough to amortize per-call overhead
_RANSAC_THREADS = 4


# -- input handling --------------------------------------------------------------


def _arguments(func: str, cameras, pts2d, what: str = "pts2d"):
    """``cameras`` checked to be a rig (TypeError: e.g. arguments swapped), ``pts2d`` float64."""
    if not (hasattr(cameras, "pmats") and hasattr(cameras, "undistort_points")):
        raise TypeError(
            f"{func}(cameras, {what}, ...) takes the camera rig first, got "
            f"{type(cameras).__name__} for cameras"
        )
    if hasattr(pts2d, "pmats"):
        raise TypeError(f"{func}(cameras, {what}, ...) got a camera rig for {what}")
    return cameras, np.asarray(pts2d, dtype=np.float64)


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
            f"weights must have shape {pts2d.shape[:-1]} (V, *pts), got {weights.shape}"
        )
    return weights


class _Rig:
    """A camera group's arrays in the form the greedy kernel takes."""

    def __init__(self, cameras: CameraGroup):
        pmats = cameras.pmats
        quad, norm = camera_model.dlt_camera_constants(np, pmats)
        self.distorted = bool(np.any(cameras.dists))
        self.arrays = {
            "pmats": pmats,
            "quad": quad,
            "norm": norm,
            "rmats": cameras.rmats,
            "tvecs": cameras.tvecs,
            "intrs": cameras.intrs,
            "dists": camera_model.pad_dist_numpy(cameras.dists),
        }


# -- RANSAC in NumPy: each hypothesis only where both its views see the point ---------
# Real recordings see each point in only 2-4 of the views, so most of the C(V, 2) pairs have nothing
# to do for most points. The points are sorted by the set of views observing them; a run of points
# with one set is a dense block in which every pair of its views is tried and errors are measured in
# its views only: no wasted pairs, no gathers in the inner loop, and no XLA compile per input size.


class _RansacViews:
    """Reprojection constants of a subset ``views`` ``(K,)`` of a rig."""

    def __init__(self, cameras: CameraGroup, pmats: np.ndarray, views: np.ndarray):
        self.n_sel = len(views)
        self.distorted = bool(np.any(cameras.dists[views]))
        if self.distorted:
            # Through the camera frame [R | t] and the lens model, as in ``project``.
            rows = np.concatenate([cameras.rmats[views], cameras.tvecs[views, :, None]], axis=2)
            self.dists = camera_model.pad_dist_numpy(cameras.dists[views]).T[
                :, :, None
            ]  # (12, K, 1)
            self.intrs = cameras.intrs[views].T[:, :, None]  # (4, K, 1)
        else:
            rows = pmats[views]
        self.rows = np.ascontiguousarray(rows.transpose(1, 0, 2).reshape(3 * self.n_sel, 4))

    def sq_errors(self, pts4, raw_u, raw_v):
        """Squared pixel errors ``(K, n)`` of homogeneous points ``(4, n)`` against
        ``raw_u/v`` ``(K, n)``."""
        k = self.n_sel
        hom = np.einsum("rc,cn->rn", self.rows, pts4)  # no multi-threaded BLAS call
        inv_depth = 1.0 / hom[2 * k :]
        u, v = hom[:k] * inv_depth, hom[k : 2 * k] * inv_depth
        if self.distorted:
            intr = self.intrs
            u, v = camera_model.pixels_from_normalized(
                u, v, intr[0], intr[1], intr[2], intr[3], self.dists
            )
        u -= raw_u
        v -= raw_v
        u *= u
        v *= v
        u += v
        return u


def _ransac_block(cameras, pmats, raw, und, weights, views, threshold, min_inliers):
    """Exhaustive-pair RANSAC for points observed in (at most) ``views`` ``(K,)``.

    ``raw`` / ``und`` ``(K, n, 2)``: raw and undistorted pixels in those views (NaN = missing);
    ``weights`` ``(K, n)`` or None. Returns ``(pts3d (n, 3), inliers (K, n))``."""
    n_sel, n = raw.shape[:2]
    quad, norm = camera_model.dlt_camera_constants(np, pmats[views])
    feats, valid = camera_model.dlt_features(np, und, norm, weights)  # (6, K, n)
    terms = np.einsum("kfc,fkn->kcn", quad, feats)  # (K, 9, n) normal-equation terms
    valid = valid.astype(np.uint8)
    raw_u, raw_v = np.ascontiguousarray(raw[..., 0]), np.ascontiguousarray(raw[..., 1])
    project = _RansacViews(cameras, pmats, views)
    threshold_sq = threshold * threshold
    # Lexicographic (most inliers, then least total inlier error) as one number, count -
    # total * scale: the total is below count * threshold, so the scaled total stays under 1.
    scale = 1.0 / (len(cameras) * threshold + 1.0)
    bits = np.exp2(np.arange(n_sel))[:, None]
    pts4 = np.ones((4, n))
    best_score = np.full(n, -np.inf)
    best_code = np.zeros(n)  # the winning hypothesis' inliers, as bits over ``views``
    for i, j in combinations(np.flatnonzero(valid.any(axis=1)), 2):
        pts4[0], pts4[1], pts4[2] = camera_model.dlt_solve_components(
            np, terms[i] + terms[j], valid[i] + valid[j]
        )
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
    # Points with fewer than two usable views stay NaN. The rest are sorted by the set of views
    # observing them and processed in runs of one set, in pieces of at most ``chunk_points`` (beyond
    # 62 views the key ignores the later ones: less uniform runs cost time, not correctness).
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
            pts3d[sel], inliers = _ransac_block(
                cameras, pmats, raw, und, w, views, threshold, min_inliers
            )
        seen[:] = False
        seen[views] = inliers
        kept[:, sel] = seen

    # NumPy releases the GIL in its loops: pieces run on a few threads (disjoint outputs).
    for _ in thread_map(run, pieces, _RANSAC_THREADS):
        pass
    return pts3d.reshape(*pts_shape, 3), kept.reshape(n_views, *pts_shape)


# -- public API ----------------------------------------------------------------------


def triangulate(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, " V *pts 2"],
    weights: Float[np.ndarray, " V *pts"] | None = None,
    *,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> Float[np.ndarray, "*pts 3"]:
    """NaN-aware (optionally confidence-weighted) DLT triangulation of ``(V, *pts, 2)`` pixels.

    Forwards to :meth:`flylib.camera.rig.CameraGroup.triangulate`. ``weights`` ``(V, *pts)``
    scale each view's rows by ``sqrt(weight)``; a non-positive or non-finite weight drops
    the view. Returns ``(*pts, 3)``, NaN where fewer than two views observe the point.
    TypeError if ``cameras`` is not a rig (arguments swapped), ValueError on a shape mismatch."""
    cameras, pts2d = _arguments("triangulate", cameras, pts2d)
    return cameras.triangulate(pts2d, weights, chunk_points=chunk_points)  # checks the shapes


def reprojection_error(
    cameras: CameraGroup, pts3d: Float[np.ndarray, "*pts 3"], pts2d: Float[np.ndarray, " V *pts 2"]
) -> Float[np.ndarray, " V *pts"]:
    """Per-observation reprojection error in pixels ``(V, *pts)``, NaN where the observation or the
    3D point is missing. TypeError if ``cameras`` is not a rig, ValueError on a shape mismatch."""
    cameras, pts2d = _arguments("reprojection_error", cameras, pts2d, "pts3d, pts2d")
    pts3d = np.asarray(pts3d, dtype=np.float64)
    _check_inputs(pts2d, cameras, None)
    if pts3d.shape[:-1] != pts2d.shape[1:-1] or pts3d.shape[-1:] != (3,):
        raise ValueError(f"pts3d shape {pts3d.shape} does not match pts2d shape {pts2d.shape}")
    diff = cameras.project(pts3d) - pts2d
    return np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)


def triangulate_ransac(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, " V *pts 2"],
    *,
    threshold: float = TriangulationParams.ransac_threshold,
    min_inliers: int = TriangulationParams.min_inliers,
    weights: Float[np.ndarray, " V *pts"] | None = None,
    chunk_points: int = RANSAC_CHUNK_POINTS,
) -> tuple[Float[np.ndarray, "*pts 3"], Bool[np.ndarray, " V *pts"]]:
    """Robust triangulation from the largest set of mutually consistent views.

    Every two-view hypothesis (all ``C(V, 2)`` pairs: the deterministic limit of RANSAC for a
    handful of cameras) is triangulated and scored by the number of views that reproject
    within ``threshold`` pixels (unweighted; NaN views never count); ties go to the smaller
    total inlier error. The point is refitted from the winning inliers (weighted when
    ``weights`` are given) if there are at least ``min_inliers`` (>= 2).

    Returns ``pts3d`` ``(*pts, 3)`` (NaN for a rejected point) and ``inliers`` ``(V, *pts)``
    bool, the views the point was fitted from. TypeError if ``cameras`` is not a rig,
    ValueError if ``min_inliers < 2`` or ``threshold <= 0``."""
    cameras, pts2d = _arguments("triangulate_ransac", cameras, pts2d)
    if int(min_inliers) < 2:
        raise ValueError(f"min_inliers must be >= 2, got {min_inliers}")
    if not threshold > 0:
        raise ValueError(f"threshold must be a positive number of pixels, got {threshold}")
    w = _check_inputs(pts2d, cameras, weights)
    return _ransac_numpy(pts2d, cameras, w, chunk_points, float(threshold), int(min_inliers))


def _triangulate_greedy(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, " V *pts 2"],
    *,
    reproj_threshold: float,
    max_drops: int,
    weights: Float[np.ndarray, " V *pts"] | None = None,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> tuple[Float[np.ndarray, "*pts 3"], Bool[np.ndarray, " V *pts"]]:
    """:func:`reconstruct`'s ``greedy`` (``max_drops < 0`` is a ValueError): ``pts3d`` (NaN below
    two views) and ``kept`` ``(V, *pts)``, the views the final point was fitted from."""
    if int(max_drops) < 0:
        raise ValueError(f"max_drops must be >= 0, got {max_drops}")
    w = _check_inputs(pts2d, cameras, weights)
    from ..camera.jax_model import run_chunked
    from .kernels import greedy_chunk

    rig = _Rig(cameras)
    n_views, pts_shape = pts2d.shape[0], pts2d.shape[1:-1]
    raw = pts2d.reshape(n_views, -1, 2)
    # the kernel measures errors through the lens model exactly when it gets ``und``
    und = cameras.undistort_points(raw) if rig.distorted else None
    flat_w = None if w is None else w.reshape(n_views, -1)
    pts3d, kept = run_chunked(
        greedy_chunk,
        rig.arrays,
        [(raw, np.nan), (und, np.nan), (flat_w, 0.0)],
        n_views,
        chunk_points,
        threshold=float(reproj_threshold),
        max_drops=int(max_drops),
    )
    return pts3d.reshape(*pts_shape, 3), kept.reshape(n_views, *pts_shape)


def reconstruct(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, " V *pts 2"],
    params: TriangulationParams | None = None,
    conf: Float[np.ndarray, " V *pts"] | None = None,
) -> tuple[
    Float[np.ndarray, "*pts 3"], Float[np.ndarray, " V *pts 2"], Float[np.ndarray, " V *pts"]
]:
    """Triangulate with the method and knobs of ``params`` (a ``triangulation`` table,
    default :class:`~flylib.config.params.TriangulationParams`): the one dispatcher.

    ``ransac`` runs :func:`triangulate_ransac`, ``greedy`` the DLT dropping each point's
    worst-reprojecting view while its error exceeds ``reproj_threshold`` (at most
    ``max_drops`` times), ``dlt`` :func:`triangulate`; each reads only its own knobs
    (:meth:`~flylib.config.params.TriangulationParams.method_kwargs`). ``conf`` ``(V, *pts)``
    are the weights when ``weigh_by_confidence``.

    Returns ``pts3d`` ``(*pts, 3)`` (NaN where the method could not reconstruct the point),
    ``pts2d_clean`` ``(V, *pts, 2)`` (the views each point was solved from; the rejected ones
    NaN) and the reprojection error ``(V, *pts)`` in pixels against it. TypeError if
    ``cameras`` is not a rig, ValueError for an unknown ``params.method``."""
    cameras, pts2d = _arguments("reconstruct", cameras, pts2d)
    params = TriangulationParams() if params is None else params
    if params.method not in TRIANGULATION_METHODS:
        raise ValueError(
            f"unknown triangulation method {params.method!r}; use one of {TRIANGULATION_METHODS}"
        )
    weights = conf if (params.weigh_by_confidence and conf is not None) else None
    knobs = params.method_kwargs()
    if params.method == "ransac":
        pts3d, kept = triangulate_ransac(cameras, pts2d, weights=weights, **knobs)
    elif params.method == "greedy":
        pts3d, kept = _triangulate_greedy(cameras, pts2d, weights=weights, **knobs)
    else:
        pts3d, kept = triangulate(cameras, pts2d, weights), None
    clean = pts2d if kept is None else np.where(kept[..., None], pts2d, np.nan)
    return pts3d, clean, reprojection_error(cameras, pts3d, clean)
