"""Camera geometry primitives in float64 JAX on the CPU.

Conventions (shared by the whole package):

* rotations are axis-angle vectors ``rvec`` (OpenCV Rodrigues); a camera maps a world point
  ``X`` to camera coordinates ``R(rvec) @ X + tvec``;
* intrinsics are packed ``[fx, fy, cx, cy]`` (``[f, cx, cy]`` is accepted too);
* distortion is OpenCV's 12 coefficients ``[k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4]``;
  missing trailing ones are zero, exactly as ``cv2.projectPoints`` reads them;
* arrays are view-leading: ``(V, *pts, 2)`` for image points; NaN marks a missing observation.

The formulas of :mod:`flylib.camera.model`, bound to ``jax.numpy``: ``*_one`` functions (one
point, one camera) compose with ``jax.vmap`` and ``jax.jacfwd``; the batched ones are jitted."""

from __future__ import annotations

import os
from collections import deque
from typing import TYPE_CHECKING

import jax
import numpy as np

from ..paths import cache_dir

if TYPE_CHECKING:  # pragma: no cover
    from collections.abc import Callable

    from jax import Array
    from jaxtyping import Bool, Float

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_platforms", "cpu")
if not os.environ.get("FLYLIB_NO_JAX_CACHE"):
    # Every workflow job is a fresh process: kernels cached on disk are compiled only once.
    jax.config.update("jax_compilation_cache_dir", str(cache_dir() / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)

import jax.numpy as jnp  # noqa: E402

from .model import (  # noqa: E402,F401 - the formulas and their NumPy bindings, re-exported
    distort_normalized,
    dlt_camera_constants,
    dlt_features,
    dlt_solve,
    dlt_solve_terms,
    intr_to_kmat_generic,
    intr_to_kmat_numpy,
    pad_dist_generic,
    pad_dist_numpy,
    pixels_from_normalized,
    project_generic,
    ray_from_normalized,
    rmat_to_rvec_generic,
    rvec_to_rmat_generic,
    rvec_to_rmat_numpy,
    split_intr as _split_intr,  # noqa: E402
    undistort_normalized,
    undistort_step,
)

_UNDISTORT_FIXED_POINT_ITERS = 20
_UNDISTORT_NEWTON_ITERS = 2


def rvec_to_rmat_one(rvec: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """Rodrigues: ``(3,)`` axis * angle (radians) -> ``(3, 3)``, exact and differentiable at 0."""
    return rvec_to_rmat_generic(jnp, rvec)


def rmat_to_rvec_one(rmat: Float[Array, "3 3"]) -> Float[Array, " 3"]:
    """Axis-angle ``(3,)``, norm in ``[0, pi]``, of one rotation matrix (inverse of
    :func:`rvec_to_rmat_one`). The angle is ``atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2)``,
    accurate over the whole range. Below 90 degrees the axis is the direction of the antisymmetric
    part; above, where that part vanishes at ``theta = pi``, it is read from the symmetric part
    ``(R + R^T) / 2 - cos(theta) I = (1 - cos(theta)) a a^T``, its sign from the antisymmetric."""
    return rmat_to_rvec_generic(jnp, jnp.asarray(rmat, dtype=jnp.float64))


@jax.jit
def rvec_to_rmat(rvec: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Batched :func:`rvec_to_rmat_one`: ``(..., 3) -> (..., 3, 3)``."""
    return rvec_to_rmat_generic(jnp, rvec)


@jax.jit
def rmat_to_rvec(rmat: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Batched :func:`rmat_to_rvec_one`: ``(..., 3, 3) -> (..., 3)``."""
    rmat = jnp.asarray(rmat, dtype=jnp.float64)
    flat = rmat.reshape(-1, 3, 3)
    return jax.vmap(rmat_to_rvec_one)(flat).reshape(*rmat.shape[:-2], 3)


@jax.jit
def intr_to_kmat(intr: Float[Array, "*batch P"]) -> Float[Array, "*batch 3 3"]:
    """Camera matrices ``K`` ``(..., 3, 3)`` from ``[fx, fy, cx, cy]`` or ``[f, cx, cy]``."""
    return intr_to_kmat_generic(jnp, intr)


def pad_dist(dist: Float[Array, "*batch K"]) -> Float[Array, "*batch 12"]:
    """``(..., K)`` OpenCV distortion coefficients zero-padded to ``(..., 12)``; ``K > 12`` is a ValueError."""
    return pad_dist_generic(jnp, dist)


def distort_one(xy: Float[Array, " 2"], dist: Float[Array, " K"]) -> Float[Array, " 2"]:
    """OpenCV distortion of one normalized point ``(x, y) = (X / Z, Y / Z)``, ``K <= 12``."""
    xy = jnp.asarray(xy, dtype=jnp.float64)
    if jnp.shape(dist)[-1] == 0:
        return xy
    return jnp.stack(distort_normalized(xy[0], xy[1], pad_dist(dist)))


def undistort_one(xy_dist: Float[Array, " 2"], dist: Float[Array, " K"]) -> Float[Array, " 2"]:
    """Invert :func:`distort_one` for ``xy_dist = ((u - cx) / fx, (v - cy) / fy)``: OpenCV's
    fixed-point scheme (as ``cv2.undistortPoints``), then Newton steps on ``distort_one(xy) =
    xy_dist``, exact to machine precision wherever the fixed point converges (moderate
    distortion); an empty ``dist`` is the identity."""
    xy_dist = jnp.asarray(xy_dist, dtype=jnp.float64)
    if jnp.shape(dist)[-1] == 0:
        return xy_dist
    d = pad_dist(dist)

    def fixed_point(_, xy):
        return jnp.stack(undistort_step(xy[0], xy[1], xy_dist[0], xy_dist[1], d))

    xy = jax.lax.fori_loop(0, _UNDISTORT_FIXED_POINT_ITERS, fixed_point, xy_dist)

    def newton(_, xy):
        jac = jax.jacfwd(distort_one)(xy, d)
        return xy - jnp.linalg.solve(jac, distort_one(xy, d) - xy_dist)

    return jax.lax.fori_loop(0, _UNDISTORT_NEWTON_ITERS, newton, xy)


@jax.jit
def distort(
    pts2d: Float[Array, "V *pts 2"], dists: Float[Array, "V K"] | Float[Array, " K"]
) -> Float[Array, "V *pts 2"]:
    """Batched :func:`distort_one` of ``(V, *pts, 2)`` by ``(V, K)`` or shared ``(K,)`` dists."""
    pts2d = jnp.asarray(pts2d, dtype=jnp.float64)
    dists = jnp.asarray(dists, dtype=jnp.float64)
    if dists.shape[-1] == 0:
        return pts2d
    n_views = pts2d.shape[0]
    dists = jnp.broadcast_to(dists, (n_views, dists.shape[-1]))
    flat = pts2d.reshape(n_views, -1, 2)
    out = jax.vmap(jax.vmap(distort_one, in_axes=(0, None)))(flat, dists)
    return out.reshape(pts2d.shape)


def project_full_one(
    pt3d: Float[Array, " 3"],
    rvec: Float[Array, " 3"],
    tvec: Float[Array, " 3"],
    intr: Float[Array, " P"],
    dist: Float[Array, " K"],
) -> Float[Array, " 2"]:
    """Pixel ``(u, v)`` (``v`` grows downwards) of one world point through one camera:
    pinhole, ``(K,)`` distortion, ``intr`` ``[fx, fy, cx, cy]`` (or ``[f, cx, cy]``)."""
    p_cam = rvec_to_rmat_one(rvec) @ jnp.asarray(pt3d, dtype=jnp.float64) + tvec
    d = pad_dist(dist) if jnp.shape(dist)[-1] else None
    fx, fy, cx, cy = _split_intr(jnp.asarray(intr, dtype=jnp.float64))
    return jnp.stack(
        pixels_from_normalized(p_cam[0] / p_cam[2], p_cam[1] / p_cam[2], fx, fy, cx, cy, d)
    )


@jax.jit
def project_full(
    pts3d: Float[Array, "*pts 3"],
    rvecs: Float[Array, "V 3"],
    tvecs: Float[Array, "V 3"],
    intrs: Float[Array, "V P"] | Float[Array, " P"],
    dists: Float[Array, "V K"] | Float[Array, " K"],
) -> Float[Array, "V *pts 2"]:
    """World points ``(*pts, 3)`` through every camera of a stacked rig -> ``(V, *pts, 2)``;
    ``intrs`` ``(V, 4)`` and ``dists`` ``(V, K)`` may be shared ``(4,)`` / ``(K,)``."""
    rvecs = jnp.asarray(rvecs, dtype=jnp.float64)
    n_views = rvecs.shape[0]
    tvecs = jnp.asarray(tvecs, dtype=jnp.float64)
    intrs = jnp.broadcast_to(jnp.asarray(intrs, dtype=jnp.float64), (n_views, jnp.shape(intrs)[-1]))
    dists = jnp.broadcast_to(jnp.asarray(dists, dtype=jnp.float64), (n_views, jnp.shape(dists)[-1]))
    return project_generic(jnp, pts3d, rvec_to_rmat_generic(jnp, rvecs), tvecs, intrs, dists)


@jax.jit
def project_pmat(
    pts3d: Float[Array, "*pts 3"], pmats: Float[Array, "*cams 3 4"]
) -> Float[Array, "... 2"]:  # (*cams, *pts, 2): one variadic dim per shape
    """Project world points ``(*pts, 3)`` with ``(*cams, 3, 4)`` projection matrices
    (typically ``K @ [R | t]``, no distortion) -> ``(*cams, *pts, 2)``."""
    pts3d = jnp.asarray(pts3d, dtype=jnp.float64)
    pmats = jnp.asarray(pmats, dtype=jnp.float64)
    flat_p = pmats.reshape(-1, 3, 4)
    flat_x = pts3d.reshape(-1, 3)
    hom = jnp.einsum("cij,nj->cni", flat_p[:, :, :3], flat_x) + flat_p[:, None, :, 3]
    out = hom[..., :2] / hom[..., 2:]
    return out.reshape(*pmats.shape[:-2], *pts3d.shape[:-1], 2)


@jax.jit
def triangulate_dlt(
    pts2d: Float[Array, "V *pts 2"],
    pmats: Float[Array, "V 3 4"],
    weights: Float[Array, " V *pts"] | None = None,
) -> Float[Array, "*pts 3"]:
    """Weighted, NaN-aware linear (DLT) triangulation of ``(V, *pts, 2)`` pixels -> ``(*pts, 3)``.

    Each view contributes the rows ``u p3 - p1`` and ``v p3 - p2`` of the linear system in
    ``[X, Y, Z, 1]``. Every row is divided by the norm of its first three entries (an angle-like
    residual, not one scaled by focal length and depth) and multiplied by ``sqrt(weight)``; the
    inhomogeneous 3x3 normal equations are solved in closed form, which unlike an eigen-solve of the
    raw system keeps full float64 precision with long focal lengths (~2e4 px). A NaN coordinate, or
    a non-finite or non-positive weight ``(V, *pts)``, drops that view; a uniform weight changes
    nothing. NaN where fewer than two views remain or the geometry is degenerate."""
    return dlt_solve(jnp, pts2d, pmats, weights)


DLT_CHUNK_POINTS = 4096
_CHUNKS_IN_FLIGHT = 4


@jax.jit
def dlt_chunk(
    consts: dict[str, Array],
    pts2d: Float[Array, "V N 2"],
    weights: Float[Array, "V N"] | None,
) -> tuple[Float[Array, "N 3"], Bool[Array, "V N"]]:
    """The DLT of :func:`triangulate_dlt` on one chunk -> ``(pts3d (N, 3), valid (V, N))``;
    ``consts`` is ``{"quad", "norm"}`` of :func:`dlt_camera_constants`, ``pts2d`` undistorted."""
    feats, valid = dlt_features(jnp, pts2d, consts["norm"], weights)
    terms = jnp.einsum("fvn,vfk->kn", feats, consts["quad"])
    return dlt_solve_terms(jnp, terms, valid.sum(axis=0)), valid


def chunk_length(n: int, chunk_points: int) -> int:
    """Chunk length for ``n`` points: ``chunk_points``, or a power of two >= 64 below it
    (kernels compile once per input length, so lengths come from a short list)."""
    size = 64
    while size < min(n, chunk_points):
        size *= 2
    return min(size, max(int(chunk_points), 1))


def _padded(arr: np.ndarray, size: int, fill: float) -> np.ndarray:
    """``arr`` ``(V, n, ...)`` padded along axis 1 to ``size``."""
    if arr.shape[1] == size:
        return arr
    out = np.full((arr.shape[0], size, *arr.shape[2:]), fill)
    out[:, : arr.shape[1]] = arr
    return out


def run_chunked(
    kernel: Callable,
    consts: dict,
    inputs: list[tuple[np.ndarray | None, float]],
    n_views: int,
    chunk_points: int = DLT_CHUNK_POINTS,
    **params,
) -> tuple[Float[np.ndarray, "N 3"], Bool[np.ndarray, "V N"]]:
    """Run a jitted ``kernel(consts, *chunks, **params)`` -> ``(pts3d (size, 3), kept (V, size))``
    over ``n`` points in fixed-length chunks (bounded memory) -> ``(pts3d (n, 3), kept (V, n))``.
    Each ``(array (V, n, ...) or None, fill)`` of ``inputs`` is cut along axis 1, the last chunk
    padded with ``fill``."""
    n = next(a.shape[1] for a, _ in inputs if a is not None)
    size = chunk_length(n, chunk_points)
    pts3d = np.full((n, 3), np.nan)
    kept = np.zeros((n_views, n), dtype=bool)
    in_flight: deque = deque()

    def collect() -> None:
        start, stop, (x, k) = in_flight.popleft()
        pts3d[start:stop] = np.asarray(x)[: stop - start]
        kept[:, start:stop] = np.asarray(k)[:, : stop - start]

    for start in range(0, n, size):
        stop = min(start + size, n)
        chunks = [
            None if a is None else _padded(a[:, start:stop], size, fill) for a, fill in inputs
        ]
        # JAX dispatches asynchronously: chunks in flight overlap the kernels with this loop.
        in_flight.append((start, stop, kernel(consts, *chunks, **params)))
        if len(in_flight) > _CHUNKS_IN_FLIGHT:
            collect()
    while in_flight:
        collect()
    return pts3d, kept


def triangulate_dlt_chunked(
    pts2d: Float[np.ndarray, "V *pts 2"],
    pmats: Float[np.ndarray, "V 3 4"],
    weights: Float[np.ndarray, " V *pts"] | None = None,
    chunk_points: int = DLT_CHUNK_POINTS,
) -> Float[np.ndarray, "*pts 3"]:
    """:func:`triangulate_dlt` of undistorted pixels for any number of points, in bounded
    memory, to NumPy: the bulk path behind :meth:`flylib.camera.rig.CameraGroup.triangulate`."""
    pts2d = np.asarray(pts2d, dtype=np.float64)
    n_views, pts_shape = pts2d.shape[0], pts2d.shape[1:-1]
    quad, norm = dlt_camera_constants(np, pmats)
    flat_w = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(n_views, -1)
    pts3d, _ = run_chunked(
        dlt_chunk,
        {"quad": quad, "norm": norm},
        [(pts2d.reshape(n_views, -1, 2), np.nan), (flat_w, 0.0)],
        n_views,
        chunk_points,
    )
    return pts3d.reshape(*pts_shape, 3)


def backproject_ray_one(
    pixel: Float[Array, " 2"],
    rvec: Float[Array, " 3"],
    tvec: Float[Array, " 3"],
    intr: Float[Array, " P"],
    dist: Float[Array, " K"],
) -> tuple[Float[Array, " 3"], Float[Array, " 3"]]:
    """World ray ``(origin, direction)`` of one pixel through one camera (inverse of
    :func:`project_full_one`): the centre ``-R^T t`` and an unnormalized direction."""
    pixel = jnp.asarray(pixel, dtype=jnp.float64)
    fx, fy, cx, cy = _split_intr(jnp.asarray(intr, dtype=jnp.float64))
    xy = undistort_one(jnp.stack([(pixel[0] - cx) / fx, (pixel[1] - cy) / fy]), dist)
    return ray_from_normalized(jnp, xy[0], xy[1], rvec_to_rmat_one(rvec), tvec)


def closest_point_on_ray(
    origin: Float[Array, " 3"], direction: Float[Array, " 3"], target: Float[Array, " 3"]
) -> Float[Array, " 3"]:
    """Orthogonal projection of ``target`` onto the line ``origin + s * direction`` (any norm)."""
    origin = jnp.asarray(origin, dtype=jnp.float64)
    direction = jnp.asarray(direction, dtype=jnp.float64)
    s = jnp.dot(jnp.asarray(target) - origin, direction) / jnp.dot(direction, direction)
    return origin + s * direction
