"""The camera model's formulas (Rodrigues both ways, ``K``, OpenCV distortion and its
fixed-point inverse, projection, the DLT), written once for any array module ``xp``
(``numpy`` or ``jax.numpy``) or with arithmetic operators only.

:mod:`flylib.camera.jax_model` binds them to ``jax.numpy``, the ``*_numpy`` names here to NumPy.
This module imports no JAX, so host-side code (camera properties, projection, undistortion,
RANSAC, summaries) never pays for it."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from types import ModuleType

    from jax import Array
    from jaxtyping import Bool, Float

    AnyArray = np.ndarray | Array  # the formulas run on either back-end (``xp``)

N_DIST_COEFFS = 12
SMALL_THETA_SQ = 1e-6


def rvec_to_rmat_generic(
    xp: ModuleType, rvec: Float[AnyArray, "*batch 3"]
) -> Float[AnyArray, "*batch 3 3"]:
    """Rodrigues' formula: axis-angle ``(..., 3)`` (norm = angle in radians) -> ``(..., 3, 3)``.
    ``R = I + a W + b (r r^T - theta^2 I)`` with ``W = skew(r)``, ``a = sin(theta) / theta``,
    ``b = (1 - cos(theta)) / theta^2``. Below ``theta^2 = SMALL_THETA_SQ`` ``a`` and ``b`` come from
    their Taylor series (the closed forms lose all precision to cancellation there); the untaken
    branch is evaluated at a safe ``theta`` so JAX gradients stay finite at ``r = 0``."""
    rvec = xp.asarray(rvec, dtype=xp.float64)
    x, y, z = rvec[..., 0], rvec[..., 1], rvec[..., 2]
    theta_sq = x * x + y * y + z * z
    small = theta_sq < SMALL_THETA_SQ
    safe_sq = xp.where(small, 1.0, theta_sq)
    theta = xp.sqrt(safe_sq)
    a = xp.where(small, 1.0 - theta_sq / 6.0 + theta_sq**2 / 120.0, xp.sin(theta) / theta)
    b = xp.where(
        small, 0.5 - theta_sq / 24.0 + theta_sq**2 / 720.0, (1.0 - xp.cos(theta)) / safe_sq
    )
    zero = xp.zeros_like(x)
    skew = xp.reshape(xp.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1), (*x.shape, 3, 3))
    outer = rvec[..., :, None] * rvec[..., None, :]
    eye = xp.eye(3)
    # Matrix-valued terms, not nine stacked entries: XLA's forward-mode Jacobian of those is slow.
    return (
        eye
        + a[..., None, None] * skew
        + b[..., None, None] * (outer - theta_sq[..., None, None] * eye)
    )


def rvec_to_rmat_numpy(rvec: Float[np.ndarray, "*batch 3"]) -> Float[np.ndarray, "*batch 3 3"]:
    """NumPy :func:`rvec_to_rmat_generic` ``(..., 3) -> (..., 3, 3)``: no XLA compilation."""
    return rvec_to_rmat_generic(np, rvec)


def rmat_to_rvec_generic(xp: ModuleType, rmat: Float[AnyArray, "3 3"]) -> Float[AnyArray, " 3"]:
    """Axis-angle vector of one rotation matrix (method: :func:`flylib.camera.jax_model.rmat_to_rvec_one`)."""
    rho = 0.5 * xp.stack(
        [rmat[2, 1] - rmat[1, 2], rmat[0, 2] - rmat[2, 0], rmat[1, 0] - rmat[0, 1]]
    )  # sin(theta) * axis
    sin_theta = xp.linalg.norm(rho)
    cos_theta = 0.5 * (xp.trace(rmat) - 1.0)
    theta = xp.arctan2(sin_theta, cos_theta)

    # Small and moderate angles: rvec = rho * theta / sin(theta).
    small = sin_theta < 1e-6
    safe_sin = xp.where(small, 1.0, sin_theta)
    scale = xp.where(small, 1.0 + sin_theta**2 / 6.0, theta / safe_sin)
    rvec_generic = rho * scale

    # Large angles: axis from the symmetric part, column with the largest diagonal.
    outer = (0.5 * (rmat + rmat.T) - cos_theta * xp.eye(3)) / xp.maximum(1.0 - cos_theta, 1e-300)
    col = outer[:, xp.argmax(xp.diagonal(outer))]
    axis = col / xp.linalg.norm(col)
    axis = xp.where(xp.dot(axis, rho) < 0.0, -axis, axis)
    rvec_large = axis * theta

    return xp.where(cos_theta < 0.0, rvec_large, rvec_generic)


def rmat_to_rvec_numpy(rmat: Float[np.ndarray, "3 3"]) -> Float[np.ndarray, " 3"]:
    """NumPy ``rmat_to_rvec_one``: ``(3, 3)`` rotation -> ``(3,)`` axis-angle, norm in ``[0, pi]``."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # the branch np.where drops
        return rmat_to_rvec_generic(np, np.asarray(rmat, dtype=np.float64))


def split_intr(
    intr: Float[AnyArray, "*batch P"],
) -> tuple[
    Float[AnyArray, "*batch"],
    Float[AnyArray, "*batch"],
    Float[AnyArray, "*batch"],
    Float[AnyArray, "*batch"],
]:
    """``(fx, fy, cx, cy)`` from packed ``[fx, fy, cx, cy]`` or ``[f, cx, cy]``."""
    return intr[..., 0], intr[..., -3], intr[..., -2], intr[..., -1]


def intr_to_kmat_generic(
    xp: ModuleType, intr: Float[AnyArray, "*batch P"]
) -> Float[AnyArray, "*batch 3 3"]:
    """Camera matrices ``(..., 3, 3)`` from packed ``(..., 4)`` ``[fx, fy, cx, cy]`` or ``(..., 3)`` ``[f, cx, cy]``."""
    intr = xp.asarray(intr, dtype=xp.float64)
    fx, fy, cx, cy = split_intr(intr)
    zero, one = xp.zeros_like(fx), xp.ones_like(fx)
    rows = ((fx, zero, cx), (zero, fy, cy), (zero, zero, one))
    return xp.stack([xp.stack(row, axis=-1) for row in rows], axis=-2)


def intr_to_kmat_numpy(intr: Float[np.ndarray, "*batch P"]) -> Float[np.ndarray, "*batch 3 3"]:
    """NumPy :func:`intr_to_kmat_generic`: ``(..., 4)`` or ``(..., 3)`` -> ``(..., 3, 3)``."""
    return intr_to_kmat_generic(np, intr)


def pad_dist_generic(
    xp: ModuleType, dist: Float[AnyArray, "*batch K"]
) -> Float[AnyArray, "*batch 12"]:
    """``(..., K)`` distortion coefficients zero-padded to ``(..., 12)``; more than 12 is a ValueError."""
    dist = xp.asarray(dist, dtype=xp.float64)
    k = dist.shape[-1]
    if k > N_DIST_COEFFS:
        raise ValueError(f"at most {N_DIST_COEFFS} distortion coefficients are supported, got {k}")
    pad = [(0, 0)] * (dist.ndim - 1) + [(0, N_DIST_COEFFS - k)]
    return xp.pad(dist, pad)


def pad_dist_numpy(dist: Float[np.ndarray, "*batch K"]) -> Float[np.ndarray, "*batch 12"]:
    """NumPy ``pad_dist``: ``(..., K)`` coefficients zero-padded to ``(..., 12)``."""
    return pad_dist_generic(np, dist)


def distortion_terms(x, y, d):
    """Radial factor and additive tangential + thin-prism terms (any array module)."""
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + d[0] * r2 + d[1] * r4 + d[4] * r6) / (1.0 + d[5] * r2 + d[6] * r4 + d[7] * r6)
    add_x = 2.0 * d[2] * xy + d[3] * (r2 + 2.0 * x2) + d[8] * r2 + d[9] * r4
    add_y = d[2] * (r2 + 2.0 * y2) + 2.0 * d[3] * xy + d[10] * r2 + d[11] * r4
    return radial, add_x, add_y


def distort_normalized(x, y, d):
    """Distorted normalized coordinates ``(x_d, y_d)`` of ``(x, y)`` (any array module), with
    ``r^2 = x^2 + y^2`` and ``d = [k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4]``::

        x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
              + 2 p1 x y + p2 (r^2 + 2 x^2) + s1 r^2 + s2 r^4
        y_d = y (...) / (...) + p1 (r^2 + 2 y^2) + 2 p2 x y + s3 r^2 + s4 r^4

    ``x``, ``y`` broadcast against each ``d[i]`` (``d`` is coefficient-major, ``(12, ...)``)."""
    radial, add_x, add_y = distortion_terms(x, y, d)
    return x * radial + add_x, y * radial + add_y


def undistort_step(x, y, x_dist, y_dist, d):
    """One sweep of OpenCV's fixed-point inverse of :func:`distort_normalized` (any array module)."""
    radial, add_x, add_y = distortion_terms(x, y, d)
    return (x_dist - add_x) / radial, (y_dist - add_y) / radial


def pixels_from_normalized(x, y, fx, fy, cx, cy, d=None):
    """Pixels ``(u, v)`` of normalized coordinates, through the lens model ``d`` if given."""
    if d is not None:
        x, y = distort_normalized(x, y, d)
    return fx * x + cx, fy * y + cy


def project_generic(
    xp: ModuleType,
    pts3d: Float[AnyArray, "*pts 3"],
    rmats: Float[AnyArray, "V 3 3"],
    tvecs: Float[AnyArray, "V 3"],
    intrs: Float[AnyArray, "V P"],
    dists: Float[AnyArray, "V K"],
) -> Float[AnyArray, "V *pts 2"]:
    """World points ``(*pts, 3)`` through ``V`` stacked cameras -> pixels ``(V, *pts, 2)``:
    ``X_cam = R X + t``, perspective division, :func:`distort_normalized`, then ``u = fx x +
    cx``, ``v = fy y + cy``, as ``cv2.projectPoints``; an all-zero NumPy ``dists`` skips the
    lens model."""
    pts3d = xp.asarray(pts3d, dtype=xp.float64)
    flat = xp.reshape(pts3d, (-1, 3))
    cam = xp.einsum("vij,nj->vin", rmats, flat) + tvecs[:, :, None]  # (V, 3, N)
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    # NumPy can see that a rig has no distortion; under jit the lens model always runs
    lens = dists.shape[-1] > 0 and (xp is not np or bool(np.any(dists)))
    d = pad_dist_generic(xp, dists).T[:, :, None] if lens else None  # (12, V, 1)
    fx, fy, cx, cy = (c[:, None] for c in split_intr(xp.asarray(intrs, dtype=xp.float64)))
    u, v = pixels_from_normalized(x, y, fx, fy, cx, cy, d)
    return xp.reshape(xp.stack([u, v], axis=-1), (rmats.shape[0], *pts3d.shape[:-1], 2))


def ray_from_normalized(
    xp: ModuleType,
    x: float | Float[AnyArray, ""],
    y: float | Float[AnyArray, ""],
    rmat: Float[AnyArray, "3 3"],
    tvec: Float[AnyArray, " 3"],
) -> tuple[Float[AnyArray, " 3"], Float[AnyArray, " 3"]]:
    """World ray ``(origin, direction)``, ``(3,)`` each, of an undistorted normalized ``(x, y)``:
    the centre ``-R^T t`` and the unnormalized ``R^T (x, y, 1)``."""
    rmat = xp.asarray(rmat, dtype=xp.float64)
    direction = rmat.T @ xp.stack([x, y, xp.ones_like(x)])
    return -rmat.T @ xp.asarray(tvec, dtype=xp.float64), direction


def project_numpy(
    pts3d: Float[np.ndarray, "*pts 3"],
    rmats: Float[np.ndarray, "V 3 3"],
    tvecs: Float[np.ndarray, "V 3"],
    intrs: Float[np.ndarray, "V P"],
    dists: Float[np.ndarray, "V K"],
) -> Float[np.ndarray, "V *pts 2"]:
    """NumPy :func:`project_generic`: ``(*pts, 3)`` through ``V`` cameras -> ``(V, *pts, 2)``."""
    return project_generic(
        np,
        pts3d,
        np.asarray(rmats, dtype=np.float64),
        np.asarray(tvecs, dtype=np.float64),
        intrs,
        np.asarray(dists, dtype=np.float64),
    )


def undistort_normalized(
    xy_dist: Float[np.ndarray, "*pts 2"],
    dist: Float[np.ndarray, " K"],
    max_iter: int = 200,
    tol: float = 1e-15,
) -> Float[np.ndarray, "*pts 2"]:
    """NumPy batch inverse of :func:`distort_normalized` for one camera; NaN stays NaN.
    :func:`undistort_step` until no coordinate moves by more than ``tol`` (or ``max_iter``)."""
    xy_dist = np.asarray(xy_dist, dtype=np.float64)
    if np.size(dist) == 0 or not np.any(dist):
        return xy_dist.copy()
    d = pad_dist_numpy(dist)
    xd, yd = xy_dist[..., 0], xy_dist[..., 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(max_iter):
        x_new, y_new = undistort_step(x, y, xd, yd, d)
        step = np.nanmax(np.abs(np.stack([x_new - x, y_new - y])), initial=0.0)
        x, y = x_new, y_new
        if step <= tol:
            break
    return np.stack([x, y], axis=-1)


# The DLT (triangulation): ``triangulate_dlt`` and the chunked bulk path run this arithmetic.
# View v's two rows are ``a = o * p2 - pr`` (``o`` = u with ``pr = p0``, v with ``pr = p1``)
# on ``[X, Y, Z, 1]``. Each row is divided by ``|a[:3]|`` and scaled by ``sqrt(w)``, and the
# point solves the 3x3 normal equations ``M X = b`` with ``M = sum s a3 a3^T``,
# ``b = -sum s a3 a[3]``, ``s = w / |a3|^2``. Both are quadratic in ``o``:
# ``s a3 a3^T = (s o^2) p2 p2^T - (s o)(p2 pr^T + pr p2^T) + s pr pr^T``. So every view's
# contribution is the features ``(s o^2, s o, s)`` for both rows times a constant (6, 9)
# matrix of the camera, and the whole system is one matrix product.

DLT_TERMS = ("m00", "m01", "m02", "m11", "m12", "m22", "b0", "b1", "b2")
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def dlt_camera_constants(
    xp: ModuleType, pmats: Float[AnyArray, "V 3 4"]
) -> tuple[Float[AnyArray, "V 6 9"], Float[AnyArray, "V 2 3"]]:
    """Per-view constants of the DLT normal equations, ``(quad, norm)``: ``quad`` ``(V, 6, 9)``
    maps a view's features ``(s u^2, s u, s, s v^2, s v, s)`` to its contribution to
    ``DLT_TERMS``; ``norm`` ``(V, 2, 3)`` gives ``|a3|^2 = c0 o^2 + c1 o + c2`` per row."""
    pmats = xp.asarray(pmats, dtype=xp.float64)
    p2 = pmats[:, 2]
    blocks, norms = [], []
    for r in (0, 1):
        pr = pmats[:, r]
        by_power = []
        for lhs, rhs, sign in (
            ((p2, p2), None, 1.0),
            ((p2, pr), (pr, p2), -1.0),
            ((pr, pr), None, 1.0),
        ):

            def outer(x, y):
                return [x[:, i] * y[:, j] for i, j in _UPPER] + [
                    -x[:, i] * y[:, 3] for i in range(3)
                ]

            cols = outer(*lhs)
            if rhs is not None:
                cols = [c + d for c, d in zip(cols, outer(*rhs))]
            by_power.append(xp.stack([sign * c for c in cols], axis=-1))  # (V, 9)
        blocks.append(xp.stack(by_power, axis=1))  # (V, 3, 9)
        p2_3, pr_3 = p2[:, :3], pr[:, :3]
        norms.append(
            xp.stack(
                [
                    xp.sum(p2_3 * p2_3, axis=-1),
                    -2.0 * xp.sum(p2_3 * pr_3, axis=-1),
                    xp.sum(pr_3 * pr_3, axis=-1),
                ],
                axis=-1,
            )
        )
    return xp.concatenate(blocks, axis=1), xp.stack(norms, axis=1)


def dlt_features(
    xp: ModuleType,
    pts2d: Float[AnyArray, "V N 2"],
    norm: Float[AnyArray, "V 2 3"],
    weights: Float[AnyArray, "V N"] | None = None,
) -> tuple[Float[AnyArray, "6 V N"], Bool[AnyArray, "V N"]]:
    """DLT features ``(6, V, N)`` and ``valid`` ``(V, N)`` (NaN pixel or weight <= 0: zero)."""
    pts2d = xp.asarray(pts2d, dtype=xp.float64)
    u, v = pts2d[..., 0], pts2d[..., 1]
    valid = xp.isfinite(u) & xp.isfinite(v)
    if weights is None:
        w = xp.where(valid, 1.0, 0.0)
    else:
        w = xp.asarray(weights, dtype=xp.float64)
        w = xp.where(valid & xp.isfinite(w) & (w > 0), w, 0.0)
        valid = w > 0
    feats = []
    for r, obs in enumerate((u, v)):
        obs = xp.where(valid, obs, 0.0)
        c = norm[:, r]
        norm_sq = (c[:, 0:1] * obs + c[:, 1:2]) * obs + c[:, 2:3]
        s = w / xp.where(norm_sq > 0, norm_sq, 1.0)
        so = s * obs
        feats += [so * obs, so, s]
    return xp.stack(feats), valid


def dlt_solve_terms(
    xp: ModuleType,
    terms: Float[AnyArray, " 9 *pts"],
    n_valid: int | Float[AnyArray, "*pts"],
    min_views: int = 2,
) -> Float[AnyArray, "*pts 3"]:
    """Solve normal equations ``(9, ...)`` (``DLT_TERMS``) in closed form -> ``(..., 3)``; NaN
    where fewer than ``min_views`` views took part or the system is (numerically) singular."""
    return xp.stack(dlt_solve_components(xp, terms, n_valid, min_views), axis=-1)


def dlt_solve_components(
    xp: ModuleType,
    terms: Float[AnyArray, " 9 *pts"],
    n_valid: int | Float[AnyArray, "*pts"],
    min_views: int = 2,
) -> tuple[Float[AnyArray, "*pts"], Float[AnyArray, "*pts"], Float[AnyArray, "*pts"]]:
    """:func:`dlt_solve_terms` returning the coordinates ``(x, y, z)`` separately."""
    m00, m01, m02, m11, m12, m22, b0, b1, b2 = (terms[i] for i in range(9))
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    trace = m00 + m11 + m22
    ok = (n_valid >= min_views) & (det > 1e-12 * trace * trace * trace)
    inv_det = xp.where(ok, 1.0 / xp.where(ok, det, 1.0), xp.nan)
    x = (c00 * b0 + c01 * b1 + c02 * b2) * inv_det
    y = (c01 * b0 + c11 * b1 + c12 * b2) * inv_det
    z = (c02 * b0 + c12 * b1 + c22 * b2) * inv_det
    return x, y, z


def dlt_solve(
    xp: ModuleType,
    pts2d: Float[AnyArray, "V *pts 2"],
    pmats: Float[AnyArray, "V 3 4"],
    weights: Float[AnyArray, " V *pts"] | None = None,
) -> Float[AnyArray, "*pts 3"]:
    """Weighted NaN-aware DLT with array module ``xp`` (see :func:`flylib.camera.jax_model.triangulate_dlt`)."""
    pts2d = xp.asarray(pts2d, dtype=xp.float64)
    n_views = pts2d.shape[0]
    pts_shape = pts2d.shape[1:-1]
    flat = xp.reshape(pts2d, (n_views, -1, 2))
    w = (
        None
        if weights is None
        else xp.reshape(xp.asarray(weights, dtype=xp.float64), (n_views, -1))
    )
    quad, norm = dlt_camera_constants(xp, pmats)
    feats, valid = dlt_features(xp, flat, norm, w)
    terms = xp.einsum("fvn,vfk->kn", feats, quad)
    out = dlt_solve_terms(xp, terms, xp.sum(valid, axis=0))
    return xp.reshape(out, (*pts_shape, 3))
