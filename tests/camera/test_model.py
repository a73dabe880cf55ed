"""The camera model (flylib.camera.model) and its JAX binding (flylib.camera.jax_model)
against OpenCV, SciPy and finite differences."""

from __future__ import annotations

import cv2
import jax
import numpy as np
import pytest
from scipy.linalg import expm

from flylib.camera import jax_model as g

from rig_constants import AZIMUTHS, DISTANCE, FOCAL


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


# -- rotations -------------------------------------------------------------------------


def test_rvec_to_rmat_matches_opencv_and_matrix_exponential():
    rng = np.random.default_rng(0)
    rvecs = rng.normal(size=(20, 3))
    got = np.asarray(g.rvec_to_rmat(rvecs))
    for rvec, rmat in zip(rvecs, got):
        np.testing.assert_allclose(rmat, cv2.Rodrigues(rvec)[0], atol=1e-14)
        np.testing.assert_allclose(rmat, expm(_skew(rvec)), atol=1e-14)


def test_rvec_to_rmat_batched_shape_and_single():
    rvecs = np.random.default_rng(1).normal(size=(2, 4, 3))
    out = np.asarray(g.rvec_to_rmat(rvecs))
    assert out.shape == (2, 4, 3, 3)
    np.testing.assert_allclose(out[1, 2], np.asarray(g.rvec_to_rmat_one(rvecs[1, 2])), atol=1e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-4, 1e-2])
def test_rotations_near_zero_are_exact(angle):
    rvec = _unit(np.random.default_rng(2)) * angle
    rmat = np.asarray(g.rvec_to_rmat_one(rvec))
    np.testing.assert_allclose(rmat, expm(_skew(rvec)), atol=1e-16)
    np.testing.assert_allclose(rmat @ rmat.T, np.eye(3), atol=1e-15)
    back = np.asarray(g.rmat_to_rvec_one(rmat))
    np.testing.assert_allclose(back, rvec, rtol=1e-9, atol=1e-20)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 0.7, 3.0, np.pi])
def test_numpy_rodrigues_twin_matches_opencv_and_the_jax_kernel(angle):
    rng = np.random.default_rng(4)
    rvecs = np.stack([_unit(rng) * angle for _ in range(6)]).reshape(2, 3, 3)
    got = g.rvec_to_rmat_numpy(rvecs)
    assert got.shape == (2, 3, 3, 3)
    np.testing.assert_allclose(got, np.asarray(g.rvec_to_rmat(rvecs)), atol=1e-15)
    for rvec, rmat in zip(rvecs.reshape(-1, 3), got.reshape(-1, 3, 3)):
        np.testing.assert_allclose(rmat, expm(_skew(rvec)), atol=1e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.7, 2.0, np.pi - 1e-6, np.pi])
def test_numpy_rmat_to_rvec_twin_matches_the_jax_kernel_and_inverts(angle):
    from flylib.camera.model import rmat_to_rvec_numpy

    rng = np.random.default_rng(5)
    for _ in range(4):
        rvec = _unit(rng) * angle
        rmat = expm(_skew(rvec))
        back = rmat_to_rvec_numpy(rmat)
        assert isinstance(back, np.ndarray) and back.shape == (3,)
        np.testing.assert_allclose(back, np.asarray(g.rmat_to_rvec_one(rmat)), atol=1e-15)
        np.testing.assert_allclose(expm(_skew(back)), rmat, atol=1e-14)  # same rotation
        if angle < np.pi - 1e-3:
            np.testing.assert_allclose(back, rvec, atol=1e-12)


def test_host_side_modules_do_not_import_jax():
    # workflow jobs that only project, undistort, triangulate by RANSAC or assemble must
    # not pay for importing JAX (~0.7 s each)
    import subprocess
    import sys

    code = (
        "import sys, flylib.camera.rig, flylib.triangulation, flylib.results, flylib.stages, "
        "flylib.pipeline.triangulation, flylib.pipeline.assemble, "
        "flylib.pictorial, flylib.visualization; from flylib.config import Config; "
        "rig = flylib.camera.rig.CameraGroup.from_config(Config.default(), "
        "{v: (480, 960) for v in Config.default().view_names()}); "
        "import numpy as np; from flylib.triangulation import triangulate_ransac; "
        "triangulate_ransac(rig, rig.project(np.zeros((2, 3)))); "
        "print('jax' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_numpy_kmat_twin_matches_the_jax_kernel_for_both_intrinsic_forms():
    intrs = np.array([[1200.0, 1100.0, 320.0, 240.0], [900.0, 950.0, 10.0, 20.0]])
    np.testing.assert_array_equal(g.intr_to_kmat_numpy(intrs), np.asarray(g.intr_to_kmat(intrs)))
    np.testing.assert_array_equal(
        g.intr_to_kmat_numpy([500.0, 3.0, 4.0]),
        [[500.0, 0.0, 3.0], [0.0, 500.0, 4.0], [0.0, 0.0, 1.0]],
    )


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_rodrigues_jacobian_at_zero_is_the_skew_generators():
    jac = np.asarray(jax.jacfwd(g.rvec_to_rmat_one)(np.zeros(3)))  # (3, 3, 3)
    assert np.all(np.isfinite(jac))
    for k in range(3):
        np.testing.assert_allclose(jac[..., k], _skew(np.eye(3)[k]), atol=1e-15)


@pytest.mark.parametrize("delta", [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.5])
def test_rotations_near_pi_round_trip(delta):
    rng = np.random.default_rng(3)
    for _ in range(5):
        rvec = _unit(rng) * (np.pi - delta)
        rmat = expm(_skew(rvec))
        back = np.asarray(g.rmat_to_rvec_one(rmat))
        # The same rotation (at exactly pi, rvec and -rvec both are).
        np.testing.assert_allclose(np.asarray(g.rvec_to_rmat_one(back)), rmat, atol=1e-14)
        if delta > 1e-6:
            np.testing.assert_allclose(back, rvec, atol=1e-9)
        assert np.linalg.norm(back) <= np.pi + 1e-12


def test_rmat_to_rvec_matches_opencv_on_generic_rotations():
    rng = np.random.default_rng(4)
    rvecs = np.stack([_unit(rng) * a for a in rng.uniform(0.01, 3.1, size=20)])
    rmats = np.stack([cv2.Rodrigues(r)[0] for r in rvecs])
    got = np.asarray(g.rmat_to_rvec(rmats))
    ref = np.stack([cv2.Rodrigues(m)[0][:, 0] for m in rmats])
    np.testing.assert_allclose(got, ref, atol=1e-12)


# -- projection and distortion ----------------------------------------------------------


def _random_camera(rng, n_dist):
    rvec = rng.normal(size=3) * 0.5
    tvec = np.array([0.1, -0.2, 6.0]) + rng.normal(size=3) * 0.1
    intr = np.array([900.0, 880.0, 330.0, 250.0]) + rng.normal(size=4) * 5
    dist = rng.normal(size=n_dist) * 0.02
    return rvec, tvec, intr, dist


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12])
def test_project_full_matches_cv2_projectpoints(n_dist):
    rng = np.random.default_rng(10 + n_dist)
    pts = rng.normal(size=(4, 10, 3))
    cams = [_random_camera(rng, n_dist) for _ in range(3)]
    rvecs, tvecs, intrs, dists = (np.stack(a) for a in zip(*cams))
    got = np.asarray(g.project_full(pts, rvecs, tvecs, intrs, dists))
    assert got.shape == (3, 4, 10, 2)
    for v, (rvec, tvec, intr, dist) in enumerate(cams):
        kmat = np.asarray(g.intr_to_kmat(intr))
        ref = cv2.projectPoints(pts.reshape(-1, 3), rvec, tvec, kmat, dist if n_dist else None)[0]
        np.testing.assert_allclose(got[v].reshape(-1, 2), ref[:, 0], rtol=1e-9)


def test_short_distortion_vectors_are_zero_padded():
    rng = np.random.default_rng(5)
    xy = rng.normal(size=2) * 0.3
    short = np.array([0.1, -0.05])
    np.testing.assert_allclose(
        np.asarray(g.distort_one(xy, short)),
        np.asarray(g.distort_one(xy, np.concatenate([short, np.zeros(10)]))),
        atol=0,
    )
    with pytest.raises(ValueError, match="at most 12"):
        g.distort_one(xy, np.zeros(13))


@pytest.mark.parametrize("n_dist", [4, 5, 8, 12])
@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_undistort_matches_cv2_and_inverts_distort(n_dist):
    rng = np.random.default_rng(20 + n_dist)
    _, _, intr, dist = _random_camera(rng, n_dist)
    kmat = np.asarray(g.intr_to_kmat(intr))
    undist = rng.uniform(-0.3, 0.3, size=(25, 2))
    distorted = np.asarray(jax.jit(jax.vmap(g.distort_one, in_axes=(0, None)))(undist, dist))
    pixels = distorted * intr[:2] + intr[2:]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16)
    ref = cv2.undistortPoints(pixels[:, None], kmat, dist, None, None, None, criteria)[:, 0]
    ours = np.asarray(jax.jit(jax.vmap(g.undistort_one, in_axes=(0, None)))(distorted, dist))
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ours, undist, atol=1e-13)
    np.testing.assert_allclose(g.undistort_normalized(distorted, dist), undist, atol=1e-13)


def test_project_full_one_jacobian_matches_finite_differences():
    rng = np.random.default_rng(6)
    rvec, tvec, intr, dist = _random_camera(rng, 8)
    pt = rng.normal(size=3)
    args = [pt, rvec, tvec, intr, dist]
    jacs = jax.jit(jax.jacfwd(g.project_full_one, argnums=(0, 1, 2, 3, 4)))(*args)
    project = jax.jit(g.project_full_one)
    eps = 1e-6
    for k, arg in enumerate(args):
        num = np.zeros((2, arg.size))
        for i in range(arg.size):
            hi = [a.copy() for a in args]
            lo = [a.copy() for a in args]
            hi[k][i] += eps
            lo[k][i] -= eps
            num[:, i] = (np.asarray(project(*hi)) - np.asarray(project(*lo))) / (2 * eps)
        np.testing.assert_allclose(
            np.asarray(jacs[k]), num, rtol=1e-6, atol=1e-6 * np.abs(num).max()
        )


def test_project_full_one_composes_with_vmap():
    rng = np.random.default_rng(7)
    rvec, tvec, intr, dist = _random_camera(rng, 5)
    pts = rng.normal(size=(6, 3))
    batched = jax.vmap(g.project_full_one, in_axes=(0, None, None, None, None))(
        pts, rvec, tvec, intr, dist
    )
    np.testing.assert_allclose(
        np.asarray(batched),
        np.asarray(g.project_full(pts, rvec[None], tvec[None], intr[None], dist[None]))[0],
    )


def test_project_pmat_equals_pinhole_projection_and_intr_forms():
    rng = np.random.default_rng(8)
    rvec, tvec, intr, _ = _random_camera(rng, 0)
    kmat = np.asarray(g.intr_to_kmat(intr))
    np.testing.assert_array_equal(kmat, [[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1]])
    np.testing.assert_array_equal(
        np.asarray(g.intr_to_kmat(np.array([500.0, 10.0, 20.0]))),
        [[500, 0, 10], [0, 500, 20], [0, 0, 1]],
    )
    pmat = kmat @ np.column_stack([cv2.Rodrigues(rvec)[0], tvec])
    pts = rng.normal(size=(5, 3))
    np.testing.assert_allclose(
        np.asarray(g.project_pmat(pts, pmat[None]))[0],
        np.asarray(g.project_full(pts, rvec[None], tvec[None], intr[None], np.zeros((1, 0))))[0],
        rtol=1e-12,
    )


# -- triangulation and rays ---------------------------------------------------------------


_AZIMUTHS = tuple(AZIMUTHS.values())


def _orbit_pmats(focal=FOCAL, distance=DISTANCE, azimuths=_AZIMUTHS):
    """Look-at cameras built here with cv2 (independent of flylib.camera.rig)."""
    pmats = []
    for az in np.deg2rad(azimuths):
        out = np.array([np.cos(az), np.sin(az), 0.0])
        z = -out
        x = np.array([-np.sin(az), np.cos(az), 0.0])
        rmat = np.stack([x, np.cross(z, x), z])
        kmat = np.array([[focal, 0, 480.0], [0, focal, 240.0], [0, 0, 1]])
        pmats.append(kmat @ np.column_stack([rmat, -rmat @ (distance * out)]))
    return np.stack(pmats)


def test_triangulate_dlt_is_exact_with_long_focal_length():
    pmats = _orbit_pmats()
    pts = np.random.default_rng(9).uniform(-1.5, 1.5, size=(50, 3))
    obs = np.asarray(g.project_pmat(pts, pmats))
    got = np.asarray(g.triangulate_dlt(obs, pmats))
    np.testing.assert_allclose(got, pts, rtol=1e-9, atol=1e-9 * np.abs(pts).max())
    # Any two views suffice, and the other views being NaN changes nothing.
    obs2 = np.full_like(obs, np.nan)
    obs2[[1, 4]] = obs[[1, 4]]
    np.testing.assert_allclose(np.asarray(g.triangulate_dlt(obs2, pmats)), pts, atol=1e-9)


def test_triangulate_dlt_nan_and_weights():
    pmats = _orbit_pmats()
    rng = np.random.default_rng(10)
    pts = rng.uniform(-1, 1, size=(8, 3))
    obs = np.asarray(g.project_pmat(pts, pmats)) + rng.normal(scale=3.0, size=(7, 8, 2))
    plain = np.asarray(g.triangulate_dlt(obs, pmats))
    # A uniform weight changes nothing; a zero weight is the same as a missing view.
    np.testing.assert_allclose(
        np.asarray(g.triangulate_dlt(obs, pmats, np.full((7, 8), 0.3))), plain, atol=1e-12
    )
    weights = np.ones((7, 8))
    weights[2] = 0.0
    dropped = obs.copy()
    dropped[2] = np.nan
    np.testing.assert_allclose(
        np.asarray(g.triangulate_dlt(obs, pmats, weights)),
        np.asarray(g.triangulate_dlt(dropped, pmats)),
        atol=1e-12,
    )
    # Non-uniform weights pull the point: the result differs from the plain fit.
    weights = rng.uniform(0.1, 1.0, size=(7, 8))
    assert np.abs(np.asarray(g.triangulate_dlt(obs, pmats, weights)) - plain).max() > 1e-6
    # One view only -> NaN.
    single = np.full_like(obs, np.nan)
    single[3] = obs[3]
    assert np.isnan(np.asarray(g.triangulate_dlt(single, pmats))).all()


def test_triangulate_dlt_matches_independent_least_squares():
    pmats = _orbit_pmats()
    rng = np.random.default_rng(11)
    pts = rng.uniform(-1, 1, size=(10, 3))
    obs = np.asarray(g.project_pmat(pts, pmats)) + rng.normal(scale=5.0, size=(7, 10, 2))
    got = np.asarray(g.triangulate_dlt(obs, pmats))
    for n in range(10):
        rows = []
        for (u, v), p in zip(obs[:, n], pmats):
            for r in (u * p[2] - p[0], v * p[2] - p[1]):
                rows.append(r / np.linalg.norm(r[:3]))
        rows = np.array(rows)
        ref = np.linalg.lstsq(rows[:, :3], -rows[:, 3], rcond=None)[0]
        np.testing.assert_allclose(got[n], ref, rtol=1e-9, atol=1e-12)


def test_backprojected_ray_projects_onto_the_pixel():
    rng = np.random.default_rng(12)
    rvec, tvec, intr, dist = _random_camera(rng, 5)
    pixel = np.array([400.0, 200.0])
    origin, direction = (
        np.asarray(a) for a in jax.jit(g.backproject_ray_one)(pixel, rvec, tvec, intr, dist)
    )
    np.testing.assert_allclose(origin, -cv2.Rodrigues(rvec)[0].T @ tvec, atol=1e-12)
    along = origin + np.array([0.5, 3.0, 10.0])[:, None] * direction
    reproj = np.asarray(g.project_full(along, rvec[None], tvec[None], intr[None], dist[None]))[0]
    np.testing.assert_allclose(reproj, np.broadcast_to(pixel, (3, 2)), atol=1e-8)
    target = rng.normal(size=3)
    closest = np.asarray(g.closest_point_on_ray(origin, direction, target))
    assert abs(np.dot(target - closest, direction)) < 1e-12 * np.linalg.norm(direction) * 10
    np.testing.assert_allclose(np.cross(closest - origin, direction), 0, atol=1e-12)


# -- one formula set, two back-ends ------------------------------------------------------
# The camera model is written once (flylib.camera.model, generic over the array module):
# each back-end's binding is checked against OpenCV and against the other.


def _backends():
    import jax.numpy as jnp

    from flylib.camera import model as cm

    return {
        "numpy": {
            "rvec_to_rmat": cm.rvec_to_rmat_numpy,
            "rmat_to_rvec": cm.rmat_to_rvec_numpy,
            "kmat": cm.intr_to_kmat_numpy,
            "project": lambda pts, rvecs, tvecs, intrs, dists: cm.project_numpy(
                pts, cm.rvec_to_rmat_numpy(rvecs), tvecs, intrs, dists
            ),
            "undistort": cm.undistort_normalized,
            "array": np.ndarray,
        },
        "jax": {
            "rvec_to_rmat": g.rvec_to_rmat,
            "rmat_to_rvec": g.rmat_to_rvec,
            "kmat": g.intr_to_kmat,
            "project": g.project_full,
            "undistort": jax.jit(jax.vmap(g.undistort_one, in_axes=(0, None))),
            "array": jnp.ndarray,
        },
    }


@pytest.mark.parametrize("backend", ["numpy", "jax"])
def test_each_backend_rodrigues_matches_opencv_both_ways(backend):
    b = _backends()[backend]
    rng = np.random.default_rng(40)
    angles = np.concatenate([[0.0, 1e-10, 1e-4], rng.uniform(0.01, 3.1, size=20)])
    rvecs = np.stack([_unit(rng) * a for a in angles])
    got = b["rvec_to_rmat"](rvecs)
    assert (
        isinstance(got, b["array"]) and got.dtype == np.float64 and got.shape == (len(rvecs), 3, 3)
    )
    ref = np.stack([cv2.Rodrigues(r)[0] for r in rvecs])
    np.testing.assert_allclose(np.asarray(got), ref, atol=1e-14)
    back = np.stack([np.asarray(b["rmat_to_rvec"](m)) for m in ref])
    np.testing.assert_allclose(back, rvecs, atol=1e-12)
    # OpenCV rounds rotations below ~1e-5 rad to zero; compare where it does not
    big = angles > 1e-3
    np.testing.assert_allclose(
        back[big], np.stack([cv2.Rodrigues(m)[0][:, 0] for m in ref[big]]), atol=1e-12
    )


@pytest.mark.parametrize("backend", ["numpy", "jax"])
@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12])
def test_each_backend_projection_matches_cv2_projectpoints(backend, n_dist):
    b = _backends()[backend]
    rng = np.random.default_rng(50 + n_dist)
    pts = rng.normal(size=(3, 7, 3))
    cams = [_random_camera(rng, n_dist) for _ in range(4)]
    rvecs, tvecs, intrs, dists = (np.stack(a) for a in zip(*cams))
    got = b["project"](pts, rvecs, tvecs, intrs, dists)
    assert isinstance(got, b["array"]) and got.dtype == np.float64 and got.shape == (4, 3, 7, 2)
    for v, (rvec, tvec, intr, dist) in enumerate(cams):
        kmat = np.asarray(b["kmat"](intr))
        np.testing.assert_array_equal(
            kmat, [[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1]]
        )
        ref = cv2.projectPoints(pts.reshape(-1, 3), rvec, tvec, kmat, dist if n_dist else None)[0][
            :, 0
        ]
        np.testing.assert_allclose(np.asarray(got[v]).reshape(-1, 2), ref, rtol=1e-10)


@pytest.mark.parametrize("n_dist", [4, 5, 8, 12])
def test_backends_agree_with_each_other(n_dist):
    numpy_b, jax_b = _backends()["numpy"], _backends()["jax"]
    rng = np.random.default_rng(60 + n_dist)
    rvecs = rng.normal(size=(5, 3)) * np.array([[1e-9], [1e-3], [0.5], [2.0], [3.1]])
    np.testing.assert_allclose(
        numpy_b["rvec_to_rmat"](rvecs), np.asarray(jax_b["rvec_to_rmat"](rvecs)), atol=2e-16
    )
    intrs = np.array([[900.0, 880.0, 330.0, 250.0], [500.0, 500.0, 3.0, 4.0]])
    np.testing.assert_array_equal(numpy_b["kmat"](intrs), np.asarray(jax_b["kmat"](intrs)))
    cams = [_random_camera(rng, n_dist) for _ in range(3)]
    rv, tv, iv, dv = (np.stack(a) for a in zip(*cams))
    pts = rng.normal(size=(40, 3))
    np.testing.assert_allclose(
        numpy_b["project"](pts, rv, tv, iv, dv),
        np.asarray(jax_b["project"](pts, rv, tv, iv, dv)),
        rtol=1e-12,
        atol=1e-10,
    )
    # the one-point JAX kernel bundle adjustment differentiates is the same model
    one = np.asarray(
        jax.vmap(g.project_full_one, in_axes=(0, None, None, None, None))(
            pts, rv[1], tv[1], iv[1], dv[1]
        )
    )
    np.testing.assert_allclose(
        one, numpy_b["project"](pts, rv, tv, iv, dv)[1], rtol=1e-12, atol=1e-10
    )
    # undistortion: NumPy iterates to convergence, JAX runs a fixed schedule + Newton
    xy = rng.uniform(-0.3, 0.3, size=(30, 2))
    distorted = np.stack(
        g.distort_normalized(xy[:, 0], xy[:, 1], g.pad_dist_numpy(dv[0])[:, None]), axis=-1
    )
    np.testing.assert_allclose(
        numpy_b["undistort"](distorted, dv[0]),
        np.asarray(jax_b["undistort"](distorted, dv[0])),
        atol=1e-13,
    )
    np.testing.assert_allclose(numpy_b["undistort"](distorted, dv[0]), xy, atol=1e-13)


def test_generic_formulas_stay_jittable_and_differentiable_in_float64():
    import jax.numpy as jnp

    from flylib.camera import model as cm

    def loss(rvec, pts, tvec, intr, dist):
        return jnp.sum(
            cm.project_generic(
                jnp,
                pts,
                cm.rvec_to_rmat_generic(jnp, rvec[None]),
                tvec[None],
                intr[None],
                dist[None],
            )
            ** 2
        )

    rng = np.random.default_rng(70)
    rvec, tvec, intr, dist = _random_camera(rng, 5)
    pts = rng.normal(size=(6, 3))
    grad = jax.jit(jax.grad(loss))(rvec, pts, tvec, intr, dist)
    assert grad.dtype == jnp.float64 and np.all(np.isfinite(np.asarray(grad)))
    eps = 1e-6
    num = [
        (loss(rvec + eps * e, pts, tvec, intr, dist) - loss(rvec - eps * e, pts, tvec, intr, dist))
        / (2 * eps)
        for e in np.eye(3)
    ]
    np.testing.assert_allclose(np.asarray(grad), num, rtol=1e-6)
    # at rvec = 0 the Taylor branch is taken and the gradient is still finite
    assert np.all(np.isfinite(np.asarray(jax.grad(loss)(np.zeros(3), pts, tvec, intr, dist))))
