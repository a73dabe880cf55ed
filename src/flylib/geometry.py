"""Camera geometry primitives in float64 JAX on the CPU.

Conventions (shared by the whole package):

* rotations are axis-angle vectors ``rvec`` (OpenCV Rodrigues); a camera maps a
  world point ``X`` to camera coordinates ``R(rvec) @ X + tvec``;
* intrinsics are packed ``[fx, fy, cx, cy]`` (``[f, cx, cy]`` is accepted too);
* distortion is OpenCV's 12-coefficient model
  ``[k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4]``; shorter vectors mean the
  missing coefficients are zero, exactly as ``cv2.projectPoints`` reads them;
* arrays are view-leading: ``(V, *pts, 2)`` for image points;
* NaN marks a missing observation.

The ``*_one`` functions handle one point / one camera and compose with
``jax.vmap`` and ``jax.jacfwd`` (bundle adjustment builds its Jacobian from
:func:`project_full_one`). The batched functions are jitted wrappers.
"""

from __future__ import annotations

import os

import jax

from .paths import cache_dir

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_platforms", "cpu")
if not os.environ.get("FLYLIB_NO_JAX_CACHE"):
    # Every workflow job is a fresh process: keep compiled kernels on disk so only the
    # first job ever pays for XLA compilation (seconds per kernel on a small machine).
    jax.config.update("jax_compilation_cache_dir", str(cache_dir() / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

N_DIST_COEFFS = 12
# Below this theta^2 the Rodrigues coefficients use their Taylor series: the
# closed forms lose all precision to cancellation in 1 - cos(theta).
_SMALL_THETA_SQ = 1e-6
_UNDISTORT_FIXED_POINT_ITERS = 20
_UNDISTORT_NEWTON_ITERS = 2


# -- rotations ---------------------------------------------------------------


def rvec_to_rmat_one(rvec):
    """Rodrigues' formula for one rotation vector.

    Parameters
    ----------
    rvec
        Axis-angle vector of shape ``(3,)`` (direction = axis, norm = angle in
        radians).

    Returns
    -------
    jax.Array
        Rotation matrix of shape ``(3, 3)``; exact and differentiable at
        ``rvec = 0``.
    """
    rvec = jnp.asarray(rvec, dtype=jnp.float64)
    theta_sq = jnp.dot(rvec, rvec)
    small = theta_sq < _SMALL_THETA_SQ
    # Double-where keeps the untaken branch finite so gradients stay finite at 0.
    safe_theta_sq = jnp.where(small, 1.0, theta_sq)
    safe_theta = jnp.sqrt(safe_theta_sq)
    sin_over_theta = jnp.where(
        small, 1.0 - theta_sq / 6.0 + theta_sq**2 / 120.0, jnp.sin(safe_theta) / safe_theta
    )
    one_minus_cos_over_theta_sq = jnp.where(
        small,
        0.5 - theta_sq / 24.0 + theta_sq**2 / 720.0,
        (1.0 - jnp.cos(safe_theta)) / safe_theta_sq,
    )
    skew = _skew(rvec)
    return (
        jnp.eye(3)
        + sin_over_theta * skew
        + one_minus_cos_over_theta_sq * (jnp.outer(rvec, rvec) - theta_sq * jnp.eye(3))
    )


def rmat_to_rvec_one(rmat):
    """Axis-angle vector of one rotation matrix (inverse of :func:`rvec_to_rmat_one`).

    The angle comes from ``atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2)``, accurate
    over the whole range. For angles below 90 degrees the axis is the direction
    of the antisymmetric part; above, where that part shrinks to zero at
    ``theta = pi``, the axis is read from the symmetric part
    ``(R + R^T) / 2 - cos(theta) I = (1 - cos(theta)) a a^T`` and its sign taken
    from the antisymmetric part.

    Parameters
    ----------
    rmat
        Rotation matrix of shape ``(3, 3)``.

    Returns
    -------
    jax.Array
        Axis-angle vector of shape ``(3,)`` with norm in ``[0, pi]``.
    """
    rmat = jnp.asarray(rmat, dtype=jnp.float64)
    rho = 0.5 * jnp.stack(
        [rmat[2, 1] - rmat[1, 2], rmat[0, 2] - rmat[2, 0], rmat[1, 0] - rmat[0, 1]]
    )  # sin(theta) * axis
    sin_theta = jnp.linalg.norm(rho)
    cos_theta = 0.5 * (jnp.trace(rmat) - 1.0)
    theta = jnp.arctan2(sin_theta, cos_theta)

    # Small and moderate angles: rvec = rho * theta / sin(theta).
    small = sin_theta < 1e-6
    safe_sin = jnp.where(small, 1.0, sin_theta)
    scale = jnp.where(small, 1.0 + sin_theta**2 / 6.0, theta / safe_sin)
    rvec_generic = rho * scale

    # Large angles: axis from the symmetric part, column with the largest diagonal.
    outer = (0.5 * (rmat + rmat.T) - cos_theta * jnp.eye(3)) / jnp.maximum(
        1.0 - cos_theta, 1e-300
    )
    col = outer[:, jnp.argmax(jnp.diagonal(outer))]
    axis = col / jnp.linalg.norm(col)
    axis = jnp.where(jnp.dot(axis, rho) < 0.0, -axis, axis)
    rvec_large = axis * theta

    return jnp.where(cos_theta < 0.0, rvec_large, rvec_generic)


@jax.jit
def rvec_to_rmat(rvec):
    """Batched :func:`rvec_to_rmat_one`: ``(..., 3) -> (..., 3, 3)``."""
    rvec = jnp.asarray(rvec, dtype=jnp.float64)
    flat = rvec.reshape(-1, 3)
    return jax.vmap(rvec_to_rmat_one)(flat).reshape(*rvec.shape[:-1], 3, 3)


@jax.jit
def rmat_to_rvec(rmat):
    """Batched :func:`rmat_to_rvec_one`: ``(..., 3, 3) -> (..., 3)``."""
    rmat = jnp.asarray(rmat, dtype=jnp.float64)
    flat = rmat.reshape(-1, 3, 3)
    return jax.vmap(rmat_to_rvec_one)(flat).reshape(*rmat.shape[:-2], 3)


def rvec_to_rmat_numpy(rvec) -> np.ndarray:
    """NumPy :func:`rvec_to_rmat` (``(..., 3) -> (..., 3, 3)``), same Taylor branch.

    Host-side code (camera properties, bundle-adjustment residuals) uses this twin so
    that it never waits for an XLA compilation.
    """
    rvec = np.asarray(rvec, dtype=np.float64)
    flat = rvec.reshape(-1, 3)
    theta_sq = np.einsum("mi,mi->m", flat, flat)
    small = theta_sq < _SMALL_THETA_SQ
    safe_sq = np.where(small, 1.0, theta_sq)
    theta = np.sqrt(safe_sq)
    a = np.where(small, 1.0 - theta_sq / 6.0 + theta_sq**2 / 120.0, np.sin(theta) / theta)
    b = np.where(small, 0.5 - theta_sq / 24.0 + theta_sq**2 / 720.0,
                 (1.0 - np.cos(theta)) / safe_sq)
    x, y, z = flat.T
    zero = np.zeros_like(x)
    skew = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(-1, 3, 3)
    rmat = np.eye(3) + a[:, None, None] * skew + b[:, None, None] * (skew @ skew)
    return rmat.reshape(*rvec.shape[:-1], 3, 3)


def _skew(v):
    return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# -- intrinsics and distortion ---------------------------------------------------


def _split_intr(intr):
    """``(fx, fy, cx, cy)`` from packed ``[fx, fy, cx, cy]`` or ``[f, cx, cy]``."""
    return intr[..., 0], intr[..., -3], intr[..., -2], intr[..., -1]


@jax.jit
def intr_to_kmat(intr):
    """Camera matrices from packed intrinsics.

    Parameters
    ----------
    intr
        ``(..., 4)`` as ``[fx, fy, cx, cy]`` or ``(..., 3)`` as ``[f, cx, cy]``.

    Returns
    -------
    jax.Array
        ``K`` of shape ``(..., 3, 3)``.
    """
    intr = jnp.asarray(intr, dtype=jnp.float64)
    fx, fy, cx, cy = _split_intr(intr)
    zero, one = jnp.zeros_like(fx), jnp.ones_like(fx)
    rows = [
        jnp.stack([fx, zero, cx], axis=-1),
        jnp.stack([zero, fy, cy], axis=-1),
        jnp.stack([zero, zero, one], axis=-1),
    ]
    return jnp.stack(rows, axis=-2)


def intr_to_kmat_numpy(intr) -> np.ndarray:
    """NumPy :func:`intr_to_kmat`: ``(..., 4)`` or ``(..., 3)`` -> ``(..., 3, 3)``."""
    intr = np.asarray(intr, dtype=np.float64)
    fx, fy, cx, cy = _split_intr(intr)
    kmat = np.zeros(intr.shape[:-1] + (3, 3))
    kmat[..., 0, 0], kmat[..., 0, 2] = fx, cx
    kmat[..., 1, 1], kmat[..., 1, 2] = fy, cy
    kmat[..., 2, 2] = 1.0
    return kmat


def pad_dist(dist):
    """Zero-pad OpenCV distortion coefficients to the full 12-vector.

    Parameters
    ----------
    dist
        ``(..., K)`` with ``K <= 12``.

    Returns
    -------
    jax.Array
        ``(..., 12)``.

    Raises
    ------
    ValueError
        If more than 12 coefficients are given.
    """
    dist = jnp.asarray(dist, dtype=jnp.float64)
    k = dist.shape[-1]
    if k > N_DIST_COEFFS:
        raise ValueError(
            f"at most {N_DIST_COEFFS} distortion coefficients are supported, got {k}"
        )
    pad = [(0, 0)] * (dist.ndim - 1) + [(0, N_DIST_COEFFS - k)]
    return jnp.pad(dist, pad)


def _distortion_terms(x, y, d):
    """Radial factor and additive tangential + thin-prism terms (any array module)."""
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + d[0] * r2 + d[1] * r4 + d[4] * r6) / (
        1.0 + d[5] * r2 + d[6] * r4 + d[7] * r6
    )
    add_x = 2.0 * d[2] * xy + d[3] * (r2 + 2.0 * x2) + d[8] * r2 + d[9] * r4
    add_y = d[2] * (r2 + 2.0 * y2) + 2.0 * d[3] * xy + d[10] * r2 + d[11] * r4
    return radial, add_x, add_y


def distort_one(xy, dist):
    """Apply OpenCV distortion to one normalized image point.

    With ``r^2 = x^2 + y^2``::

        x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
              + 2 p1 x y + p2 (r^2 + 2 x^2) + s1 r^2 + s2 r^4
        y_d = y (...) / (...) + p1 (r^2 + 2 y^2) + 2 p2 x y + s3 r^2 + s4 r^4

    Parameters
    ----------
    xy
        Normalized coordinate ``(x, y) = (X / Z, Y / Z)``, shape ``(2,)``.
    dist
        ``(K,)`` coefficients, ``K <= 12`` (missing ones are zero).

    Returns
    -------
    jax.Array
        Distorted normalized coordinate, shape ``(2,)``.
    """
    xy = jnp.asarray(xy, dtype=jnp.float64)
    if jnp.shape(dist)[-1] == 0:
        return xy
    d = pad_dist(dist)
    radial, add_x, add_y = _distortion_terms(xy[0], xy[1], d)
    return jnp.stack([xy[0] * radial + add_x, xy[1] * radial + add_y])


def undistort_one(xy_dist, dist):
    """Invert :func:`distort_one`: distorted normalized coordinate -> undistorted.

    Runs OpenCV's fixed-point scheme (the one behind ``cv2.undistortPoints``)
    from ``xy_dist``, then polishes with Newton steps on ``distort_one(xy) =
    xy_dist`` so the result is the exact inverse to machine precision wherever the
    fixed point converges (moderate distortion).

    Parameters
    ----------
    xy_dist
        ``((u - cx) / fx, (v - cy) / fy)``, shape ``(2,)``.
    dist
        ``(K,)`` coefficients, ``K <= 12``; empty is the identity.

    Returns
    -------
    jax.Array
        Undistorted normalized coordinate, shape ``(2,)``.
    """
    xy_dist = jnp.asarray(xy_dist, dtype=jnp.float64)
    if jnp.shape(dist)[-1] == 0:
        return xy_dist
    d = pad_dist(dist)

    def fixed_point(_, xy):
        radial, add_x, add_y = _distortion_terms(xy[0], xy[1], d)
        return jnp.stack([(xy_dist[0] - add_x) / radial, (xy_dist[1] - add_y) / radial])

    xy = jax.lax.fori_loop(0, _UNDISTORT_FIXED_POINT_ITERS, fixed_point, xy_dist)

    def newton(_, xy):
        jac = jax.jacfwd(distort_one)(xy, d)
        return xy - jnp.linalg.solve(jac, distort_one(xy, d) - xy_dist)

    return jax.lax.fori_loop(0, _UNDISTORT_NEWTON_ITERS, newton, xy)


def undistort_normalized(xy_dist, dist, max_iter: int = 200, tol: float = 1e-15) -> np.ndarray:
    """NumPy batch inverse of :func:`distort_one` for one camera.

    The fixed-point scheme of :func:`undistort_one`, run until no coordinate
    moves by more than ``tol`` (or ``max_iter`` sweeps).

    Parameters
    ----------
    xy_dist
        Distorted normalized coordinates ``(..., 2)``; NaN stays NaN.
    dist
        ``(K,)`` coefficients, ``K <= 12``.

    Returns
    -------
    np.ndarray
        Undistorted normalized coordinates ``(..., 2)``.
    """
    xy_dist = np.asarray(xy_dist, dtype=np.float64)
    if np.size(dist) == 0 or not np.any(dist):
        return xy_dist.copy()
    d = np.asarray(pad_dist(dist))
    xd, yd = xy_dist[..., 0], xy_dist[..., 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(max_iter):
        radial, add_x, add_y = _distortion_terms(x, y, d)
        x_new, y_new = (xd - add_x) / radial, (yd - add_y) / radial
        step = np.nanmax(np.abs(np.stack([x_new - x, y_new - y])), initial=0.0)
        x, y = x_new, y_new
        if step <= tol:
            break
    return np.stack([x, y], axis=-1)


@jax.jit
def distort(pts2d, dists):
    """Batched :func:`distort_one`.

    Parameters
    ----------
    pts2d
        Normalized coordinates ``(V, *pts, 2)``.
    dists
        ``(V, K)`` or shared ``(K,)`` coefficients, ``K <= 12``.

    Returns
    -------
    jax.Array
        Distorted coordinates ``(V, *pts, 2)``.
    """
    pts2d = jnp.asarray(pts2d, dtype=jnp.float64)
    dists = jnp.asarray(dists, dtype=jnp.float64)
    if dists.shape[-1] == 0:
        return pts2d
    n_views = pts2d.shape[0]
    dists = jnp.broadcast_to(dists, (n_views, dists.shape[-1]))
    flat = pts2d.reshape(n_views, -1, 2)
    out = jax.vmap(jax.vmap(distort_one, in_axes=(0, None)))(flat, dists)
    return out.reshape(pts2d.shape)


# -- projection ----------------------------------------------------------------


def project_full_one(pt3d, rvec, tvec, intr, dist):
    """Project one world point through one camera (pinhole + distortion + intrinsics).

    Parameters
    ----------
    pt3d
        World point, shape ``(3,)``.
    rvec, tvec
        Extrinsics, shape ``(3,)`` each.
    intr
        ``[fx, fy, cx, cy]`` (or ``[f, cx, cy]``).
    dist
        ``(K,)`` distortion coefficients, ``K <= 12``.

    Returns
    -------
    jax.Array
        Pixel ``(u, v)``, shape ``(2,)``; ``v`` grows downwards in the image.
    """
    p_cam = rvec_to_rmat_one(rvec) @ jnp.asarray(pt3d, dtype=jnp.float64) + tvec
    xy = distort_one(p_cam[:2] / p_cam[2], dist)
    fx, fy, cx, cy = _split_intr(jnp.asarray(intr, dtype=jnp.float64))
    return jnp.stack([fx * xy[0] + cx, fy * xy[1] + cy])


@jax.jit
def project_full(pts3d, rvecs, tvecs, intrs, dists):
    """Project world points through every camera of a stacked rig.

    Parameters
    ----------
    pts3d
        World points ``(*pts, 3)``.
    rvecs, tvecs
        ``(V, 3)`` each.
    intrs
        ``(V, 4)`` (or shared ``(4,)``).
    dists
        ``(V, K)`` (or shared ``(K,)``), ``K <= 12``.

    Returns
    -------
    jax.Array
        Pixels ``(V, *pts, 2)``.
    """
    pts3d = jnp.asarray(pts3d, dtype=jnp.float64)
    rvecs = jnp.asarray(rvecs, dtype=jnp.float64)
    n_views = rvecs.shape[0]
    intrs = jnp.broadcast_to(jnp.asarray(intrs, dtype=jnp.float64), (n_views, jnp.shape(intrs)[-1]))
    dists = jnp.broadcast_to(jnp.asarray(dists, dtype=jnp.float64), (n_views, jnp.shape(dists)[-1]))
    flat = pts3d.reshape(-1, 3)
    per_view = jax.vmap(project_full_one, in_axes=(0, None, None, None, None))
    out = jax.vmap(per_view, in_axes=(None, 0, 0, 0, 0))(flat, rvecs, tvecs, intrs, dists)
    return out.reshape(n_views, *pts3d.shape[:-1], 2)


@jax.jit
def project_pmat(pts3d, pmats):
    """Project world points with 3x4 projection matrices (no distortion).

    Parameters
    ----------
    pts3d
        ``(*pts, 3)``.
    pmats
        ``(*cams, 3, 4)``, typically ``K @ [R | t]``.

    Returns
    -------
    jax.Array
        ``(*cams, *pts, 2)``.
    """
    pts3d = jnp.asarray(pts3d, dtype=jnp.float64)
    pmats = jnp.asarray(pmats, dtype=jnp.float64)
    flat_p = pmats.reshape(-1, 3, 4)
    flat_x = pts3d.reshape(-1, 3)
    hom = jnp.einsum("cij,nj->cni", flat_p[:, :, :3], flat_x) + flat_p[:, None, :, 3]
    out = hom[..., :2] / hom[..., 2:]
    return out.reshape(*pmats.shape[:-2], *pts3d.shape[:-1], 2)


# -- triangulation and rays ----------------------------------------------------------

# The DLT is written once against the array-API subset NumPy and jax.numpy share
# (``xp``): the jitted :func:`triangulate_dlt` and the chunked NumPy bulk path in
# :mod:`flylib.triangulation` run the very same arithmetic.
#
# View v's two rows are ``a = o * p2 - pr`` (``o`` = u with ``pr = p0``, v with
# ``pr = p1``) on ``[X, Y, Z, 1]``. Each row is divided by ``|a[:3]|`` and scaled
# by ``sqrt(w)``, and the point solves the 3x3 normal equations ``M X = b`` with
# ``M = sum s a3 a3^T``, ``b = -sum s a3 a[3]``, ``s = w / |a3|^2``. Both are
# quadratic in ``o``: ``s a3 a3^T = (s o^2) p2 p2^T - (s o)(p2 pr^T + pr p2^T) +
# s pr pr^T``. So every view's contribution is the feature vector
# ``(s o^2, s o, s)`` for both rows times a constant (6, 9) matrix of the camera,
# and the whole system is one matrix product.

DLT_TERMS = ("m00", "m01", "m02", "m11", "m12", "m22", "b0", "b1", "b2")
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def dlt_camera_constants(xp, pmats):
    """Per-view constants of the DLT normal equations.

    Parameters
    ----------
    xp
        ``numpy`` or ``jax.numpy``.
    pmats
        ``(V, 3, 4)``.

    Returns
    -------
    quad : array
        ``(V, 6, 9)``: maps a view's features ``(s u^2, s u, s, s v^2, s v, s)``
        to its contribution to ``DLT_TERMS``.
    norm : array
        ``(V, 2, 3)``: ``|a3|^2 = c0 o^2 + c1 o + c2`` per row.
    """
    pmats = xp.asarray(pmats, dtype=xp.float64)
    p2 = pmats[:, 2]
    blocks, norms = [], []
    for r in (0, 1):
        pr = pmats[:, r]
        by_power = []
        for lhs, rhs, sign in (((p2, p2), None, 1.0), ((p2, pr), (pr, p2), -1.0), ((pr, pr), None, 1.0)):
            def outer(x, y):
                return [x[:, i] * y[:, j] for i, j in _UPPER] + [-x[:, i] * y[:, 3] for i in range(3)]

            cols = outer(*lhs)
            if rhs is not None:
                cols = [c + d for c, d in zip(cols, outer(*rhs))]
            by_power.append(xp.stack([sign * c for c in cols], axis=-1))  # (V, 9)
        blocks.append(xp.stack(by_power, axis=1))  # (V, 3, 9)
        p2_3, pr_3 = p2[:, :3], pr[:, :3]
        norms.append(
            xp.stack(
                [xp.sum(p2_3 * p2_3, axis=-1), -2.0 * xp.sum(p2_3 * pr_3, axis=-1), xp.sum(pr_3 * pr_3, axis=-1)],
                axis=-1,
            )
        )
    return xp.concatenate(blocks, axis=1), xp.stack(norms, axis=1)


def dlt_features(xp, pts2d, norm, weights=None):
    """Per-observation DLT features.

    Parameters
    ----------
    pts2d
        ``(V, N, 2)`` pixels, NaN = missing.
    norm
        ``(V, 2, 3)`` from :func:`dlt_camera_constants`.
    weights
        Optional ``(V, N)``; non-finite or non-positive drops the view.

    Returns
    -------
    features : array
        ``(6, V, N)``, zero for dropped views.
    valid : array
        ``(V, N)`` bool.
    """
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


def dlt_solve_terms(xp, terms, n_valid, min_views=2):
    """Solve normal equations ``(9, ...)`` (``DLT_TERMS``) in closed form -> ``(..., 3)``.

    NaN where fewer than ``min_views`` views took part or the system is
    (numerically) singular.
    """
    return xp.stack(dlt_solve_components(xp, terms, n_valid, min_views), axis=-1)


def dlt_solve_components(xp, terms, n_valid, min_views=2):
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


def dlt_solve(xp, pts2d, pmats, weights=None):
    """Weighted NaN-aware DLT with array module ``xp`` (see :func:`triangulate_dlt`)."""
    pts2d = xp.asarray(pts2d, dtype=xp.float64)
    n_views = pts2d.shape[0]
    pts_shape = pts2d.shape[1:-1]
    flat = xp.reshape(pts2d, (n_views, -1, 2))
    w = None if weights is None else xp.reshape(xp.asarray(weights, dtype=xp.float64), (n_views, -1))
    quad, norm = dlt_camera_constants(xp, pmats)
    feats, valid = dlt_features(xp, flat, norm, w)
    terms = xp.einsum("fvn,vfk->kn", feats, quad)
    out = dlt_solve_terms(xp, terms, xp.sum(valid, axis=0))
    return xp.reshape(out, (*pts_shape, 3))


@jax.jit
def triangulate_dlt(pts2d, pmats, weights=None):
    """Weighted, NaN-aware linear (DLT) triangulation.

    Each view contributes the two rows ``u p3 - p1`` and ``v p3 - p2`` of the
    linear system in ``[X, Y, Z, 1]``. Every row is divided by the norm of its
    first three entries (so each row's residual is an angle-like error rather than
    one scaled by the focal length and the depth) and multiplied by
    ``sqrt(weight)``; the inhomogeneous 3x3 normal equations are then solved in
    closed form. Unlike an eigen-solve of the raw homogeneous system this keeps
    full float64 precision with long focal lengths (~2e4 px).

    Parameters
    ----------
    pts2d
        ``(V, *pts, 2)`` pixels; a NaN coordinate drops that view.
    pmats
        ``(V, 3, 4)`` projection matrices.
    weights
        Optional ``(V, *pts)``; non-finite or non-positive drops the view. A
        uniform weight changes nothing.

    Returns
    -------
    jax.Array
        ``(*pts, 3)``; NaN where fewer than two views remain or the geometry is
        degenerate.
    """
    return dlt_solve(jnp, pts2d, pmats, weights)


def backproject_ray_one(pixel, rvec, tvec, intr, dist):
    """World-frame viewing ray of one pixel (inverse of :func:`project_full_one`).

    Parameters
    ----------
    pixel
        ``(u, v)``, shape ``(2,)``.
    rvec, tvec, intr, dist
        One camera, as in :func:`project_full_one`.

    Returns
    -------
    origin, direction : jax.Array
        The camera centre ``-R^T t`` and an unnormalized direction; every point
        ``origin + s * direction`` with ``s > 0`` projects onto ``pixel``.
    """
    pixel = jnp.asarray(pixel, dtype=jnp.float64)
    fx, fy, cx, cy = _split_intr(jnp.asarray(intr, dtype=jnp.float64))
    xy = undistort_one(jnp.stack([(pixel[0] - cx) / fx, (pixel[1] - cy) / fy]), dist)
    rmat = rvec_to_rmat_one(rvec)
    direction = rmat.T @ jnp.stack([xy[0], xy[1], jnp.ones(())])
    origin = -rmat.T @ jnp.asarray(tvec, dtype=jnp.float64)
    return origin, direction


def closest_point_on_ray(origin, direction, target):
    """Orthogonal projection of ``target`` onto the line ``origin + s * direction``.

    Parameters
    ----------
    origin, direction, target
        Shape ``(3,)`` each; ``direction`` need not be normalized.

    Returns
    -------
    jax.Array
        The closest point on the line, shape ``(3,)``.
    """
    origin = jnp.asarray(origin, dtype=jnp.float64)
    direction = jnp.asarray(direction, dtype=jnp.float64)
    s = jnp.dot(jnp.asarray(target) - origin, direction) / jnp.dot(direction, direction)
    return origin + s * direction
