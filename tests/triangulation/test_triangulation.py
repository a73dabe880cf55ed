"""flylib.triangulation: DLT, RANSAC, greedy, dispatch, config and the DeepFly3D sample."""

from __future__ import annotations

import dataclasses
import pickle
from itertools import combinations

import numpy as np
import pytest

from flylib import triangulation as tri
from flylib.camera import jax_model, model as camera_model
from flylib.camera.rig import CameraGroup, orbit_extrinsics
from flylib.config import Config
from flylib.config.params import TriangulationParams
from flylib.errors import ConfigError

from rig_constants import AZIMUTHS, DISTANCE, FOCAL, IMAGE_SIZE

METHODS = ("ransac", "greedy", "dlt")


@pytest.fixture(scope="module")
def rig() -> CameraGroup:
    defaults = {"focal_length_px": FOCAL, "distance": DISTANCE, "look_at": [0, 0, 0]}
    cams = {name: {"azimuth_deg": az} for name, az in AZIMUTHS.items()}
    config = Config.from_dict({"cameras": {"defaults": defaults, **cams}})
    return CameraGroup.from_config(config, image_sizes={n: IMAGE_SIZE for n in AZIMUTHS})


@pytest.fixture(scope="module")
def scene(rig):
    pts3d = np.random.default_rng(0).uniform(-1.5, 1.5, size=(6, 5, 3))
    return pts3d, rig.project(pts3d)  # (T, P, 3), (V, T, P, 2)


def _lstsq_point(obs, pmats, weights=None):
    """Independent per-point reference: normalized rows, numpy lstsq."""
    rows, rhs = [], []
    weights = np.ones(len(obs)) if weights is None else weights
    for (u, v), p, w in zip(obs, pmats, weights):
        for r in (u * p[2] - p[0], v * p[2] - p[1]):
            n = np.linalg.norm(r[:3])
            rows.append(np.sqrt(w) * r[:3] / n)
            rhs.append(-np.sqrt(w) * r[3] / n)
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]


# -- DLT --------------------------------------------------------------------------------------


def test_dlt_recovers_points_exactly(rig, scene):
    pts3d, pts2d = scene
    got = tri.triangulate(rig, pts2d)
    assert got.shape == pts3d.shape
    np.testing.assert_allclose(got, pts3d, rtol=1e-9, atol=1e-9 * np.abs(pts3d).max())


def test_dlt_chunking_and_jax_path_agree(rig, scene):
    pts3d, pts2d = scene
    noisy = pts2d + np.random.default_rng(1).normal(scale=4.0, size=pts2d.shape)
    noisy[2, 1, 3] = np.nan
    whole = tri.triangulate(rig, noisy)
    np.testing.assert_allclose(tri.triangulate(rig, noisy, chunk_points=7), whole, rtol=1e-12)
    np.testing.assert_allclose(
        np.asarray(jax_model.triangulate_dlt(noisy, rig.pmats)), whole, rtol=1e-10
    )
    np.testing.assert_array_equal(rig.triangulate(noisy), whole)  # one path behind both
    # the unchunked NumPy DLT (the seed API's path before) agrees to float64 precision
    np.testing.assert_allclose(camera_model.dlt_solve(np, noisy, rig.pmats), whole, rtol=1e-10)
    for t, p in [(0, 0), (1, 3), (5, 4)]:
        obs = noisy[:, t, p]
        ok = np.isfinite(obs).all(axis=1)
        np.testing.assert_allclose(whole[t, p], _lstsq_point(obs[ok], rig.pmats[ok]), rtol=1e-9)


def test_dlt_missing_views_and_confidence(rig, scene):
    pts3d, pts2d = scene
    rng = np.random.default_rng(2)
    noisy = pts2d + rng.normal(scale=4.0, size=pts2d.shape)
    one_view = np.full_like(noisy, np.nan)
    one_view[3] = noisy[3]
    assert np.isnan(tri.triangulate(rig, one_view)).all()
    conf = rng.uniform(0.2, 1.0, size=noisy.shape[:-1])
    plain = tri.triangulate(rig, noisy)
    weighted = tri.triangulate(rig, noisy, conf)
    np.testing.assert_array_equal(rig.triangulate(noisy, conf), weighted)
    assert np.abs(weighted - plain).max() > 1e-6
    obs, w = noisy[:, 2, 1], conf[:, 2, 1]
    np.testing.assert_allclose(weighted[2, 1], _lstsq_point(obs, rig.pmats, w), rtol=1e-9)
    conf[4] = 0.0  # zero confidence == missing view
    dropped = noisy.copy()
    dropped[4] = np.nan
    np.testing.assert_allclose(
        tri.triangulate(rig, noisy, conf), tri.triangulate(rig, dropped, conf), rtol=1e-12
    )


def test_reprojection_error(rig, scene):
    pts3d, pts2d = scene
    shifted = pts2d.copy()
    shifted[1, ..., 0] += 3.0
    shifted[4, ..., 1] -= 4.0
    shifted[0, 0, 0] = np.nan
    err = tri.reprojection_error(rig, pts3d, shifted)
    assert err.shape == pts2d.shape[:-1]
    np.testing.assert_allclose(err[1], 3.0, rtol=1e-6)
    np.testing.assert_allclose(err[4], 4.0, rtol=1e-6)
    np.testing.assert_allclose(err[2], 0.0, atol=1e-6)
    assert np.isnan(err[0, 0, 0])


def test_input_validation(rig, scene):
    _, pts2d = scene
    with pytest.raises(ValueError, match="7 cameras"):
        tri.triangulate(rig, pts2d[:5])
    with pytest.raises(ValueError, match="min_inliers"):
        tri.triangulate_ransac(rig, pts2d, min_inliers=1)
    with pytest.raises(ValueError, match="weights must have shape"):
        tri.triangulate(rig, pts2d, np.ones((7, 2)))
    with pytest.raises(ValueError, match="weights must have shape"):
        rig.triangulate(pts2d, np.ones((7, 2)))


def test_one_argument_order(rig, scene):
    # The seed API's order, rig first; the swapped order is refused, not guessed.
    pts3d, pts2d = scene
    calls = [
        (tri.triangulate, (pts2d,)),
        (tri.triangulate_ransac, (pts2d,)),
        *[(tri.reconstruct, (pts2d, TriangulationParams(method=m))) for m in METHODS],
    ]
    for func, args in calls:
        out = func(rig, *args)
        np.testing.assert_allclose(out if isinstance(out, np.ndarray) else out[0], pts3d, atol=1e-9)
        with pytest.raises(
            TypeError, match=r"\(cameras, pts2d, \.\.\.\) takes the camera rig first"
        ):
            func(args[0], rig, *args[1:])
    np.testing.assert_allclose(tri.reprojection_error(rig, pts3d, pts2d), 0.0, atol=1e-6)
    with pytest.raises(TypeError, match="camera rig first"):
        tri.reprojection_error(pts3d, pts2d, rig)
    # the old aliases are gone: conf / weigh_by_confidence / ransac_threshold
    with pytest.raises(TypeError):
        tri.triangulate(rig, pts2d, conf=np.ones(pts2d.shape[:-1]))
    with pytest.raises(TypeError):
        tri.reconstruct(rig, pts2d, ransac_threshold=3.0)
    with pytest.raises(TypeError):
        tri.reconstruct(rig, pts2d, method="dlt")  # the method is the params'
    with pytest.raises(TypeError):
        tri.triangulate_ransac(rig, pts2d, 15.0)  # knobs are keywords


# -- RANSAC -------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad_views", [[2], [0, 5]])
def test_ransac_rejects_gross_outliers(rig, scene, bad_views):
    pts3d, pts2d = scene
    corrupted = pts2d.copy()
    corrupted[bad_views] += np.array([150.0, -90.0])
    got, inliers = tri.triangulate_ransac(rig, corrupted)
    np.testing.assert_allclose(got, pts3d, rtol=1e-9, atol=1e-9 * np.abs(pts3d).max())
    expected = np.ones(7, dtype=bool)
    expected[bad_views] = False
    assert (inliers == expected[:, None, None]).all()
    _, clean, err = tri.reconstruct(rig, corrupted)
    assert np.isnan(clean[bad_views]).all()
    np.testing.assert_array_equal(
        np.delete(clean, bad_views, axis=0), np.delete(corrupted, bad_views, axis=0)
    )
    assert np.isnan(err[bad_views]).all() and np.nanmax(err) < 1e-6
    # Plain DLT is dragged by the same outliers.
    assert np.abs(tri.triangulate(rig, corrupted) - pts3d).max() > 1e-3


def test_ransac_nan_views_never_count_and_min_inliers(rig, scene):
    pts3d, pts2d = scene
    two = np.full_like(pts2d, np.nan)
    two[[1, 2]] = pts2d[[1, 2]]
    got, inliers = tri.triangulate_ransac(rig, two)
    np.testing.assert_allclose(got, pts3d, atol=1e-9)
    assert inliers[[1, 2]].all() and not inliers[[0, 3, 4, 5, 6]].any()
    got3, inliers3 = tri.triangulate_ransac(rig, two, min_inliers=3)
    assert np.isnan(got3).all() and not inliers3.any()
    _, clean, _ = tri.reconstruct(rig, two, TriangulationParams(min_inliers=3))
    assert np.isnan(clean).all()


def test_ransac_tie_break_prefers_lower_total_error(rig):
    point = np.array([[0.2, -0.3, 0.4]])
    pts2d = np.full((7, 1, 2), np.nan)
    exact = rig.project(point)
    pts2d[[3, 4]] = exact[[3, 4]]  # an exactly consistent pair
    # An earlier-enumerated pair that agrees with itself only up to a few pixels
    # and is far from the exact pair's point.
    other = rig.project(point + np.array([0.0, 0.0, 0.5]))
    pts2d[[0, 1]] = other[[0, 1]] + np.array([[[3.0, 0.0]], [[-3.0, 2.0]]])
    got, inliers = tri.triangulate_ransac(rig, pts2d)
    assert inliers[:, 0].tolist() == [False, False, False, True, True, False, False]
    np.testing.assert_allclose(got, point, atol=1e-9)


def _brute_force_ransac(pts2d, cameras, threshold):
    pmats = cameras.pmats
    n_views = pts2d.shape[0]
    flat = pts2d.reshape(n_views, -1, 2)
    out = np.full((flat.shape[1], 3), np.nan)
    masks = np.zeros((n_views, flat.shape[1]), dtype=bool)
    for n in range(flat.shape[1]):
        obs = flat[:, n]
        ok = np.isfinite(obs).all(axis=1)
        best = (0, np.inf, None)
        for i, j in combinations(np.flatnonzero(ok), 2):
            cand = _lstsq_point(obs[[i, j]], pmats[[i, j]])
            proj = cameras.project(cand)
            err = np.where(ok, np.linalg.norm(proj - np.nan_to_num(obs), axis=1), np.inf)
            inl = err < threshold
            key = (inl.sum(), err[inl].sum())
            if key[0] > best[0] or (key[0] == best[0] and key[1] < best[1]):
                best = (key[0], key[1], inl)
        if best[0] >= 2:
            out[n] = _lstsq_point(obs[best[2]], pmats[best[2]])
            masks[:, n] = best[2]
    return out.reshape(*pts2d.shape[1:-1], 3), masks.reshape(pts2d.shape[:-1])


def test_ransac_matches_a_brute_force_reference(rig):
    rng = np.random.default_rng(5)
    pts3d = rng.uniform(-1.5, 1.5, size=(4, 10, 3))
    pts2d = rig.project(pts3d) + rng.normal(scale=3.0, size=(7, 4, 10, 2))
    pts2d[rng.random(pts2d.shape[:-1]) < 0.3] = np.nan
    bad = rng.random(pts2d.shape[:-1]) < 0.2
    pts2d[bad] += rng.uniform(-300, 300, size=(int(bad.sum()), 2))
    got, inliers = tri.triangulate_ransac(rig, pts2d, threshold=15.0)
    ref, ref_inliers = _brute_force_ransac(pts2d, rig, 15.0)
    np.testing.assert_array_equal(inliers, ref_inliers)
    np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-10)


def test_ransac_pieces_threads_and_dropped_views(rig):
    # Points are processed in runs of equally seen points, split into pieces that run
    # on threads: tiny pieces give the same answer as the default ones.
    rng = np.random.default_rng(7)
    pts3d = rng.uniform(-1.5, 1.5, size=(40, 6, 3))
    pts2d = rig.project(pts3d) + rng.normal(scale=2.0, size=(7, 40, 6, 2))
    pts2d[rng.random(pts2d.shape[:-1]) < 0.4] = np.nan
    bad = rng.random(pts2d.shape[:-1]) < 0.15
    pts2d[bad] += rng.uniform(-200, 200, size=(int(bad.sum()), 2))
    whole, whole_inliers = tri.triangulate_ransac(rig, pts2d)
    pieces, pieces_inliers = tri.triangulate_ransac(rig, pts2d, chunk_points=5)
    np.testing.assert_array_equal(pieces_inliers, whole_inliers)
    np.testing.assert_allclose(pieces, whole, rtol=1e-12)
    ref, ref_inliers = _brute_force_ransac(pts2d, rig, 15.0)
    np.testing.assert_array_equal(whole_inliers, ref_inliers)
    np.testing.assert_allclose(whole, ref, rtol=1e-8, atol=1e-10)
    # A zero-confidence observation is a missing one, in the vote too.
    conf = rng.uniform(0.5, 1.0, size=pts2d.shape[:-1])
    zero = rng.random(conf.shape) < 0.2
    conf[zero] = 0.0
    got, inliers = tri.triangulate_ransac(rig, pts2d, weights=conf)
    dropped = np.where(zero[..., None], np.nan, pts2d)
    want, want_inliers = tri.triangulate_ransac(rig, dropped, weights=conf)
    assert not inliers[zero].any()
    np.testing.assert_array_equal(inliers, want_inliers)
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_ransac_with_more_views_than_the_run_key_holds(rig):
    # 64 cameras: points are grouped by their first 62 views only, so one run mixes
    # points seen by different later views.
    n_views = 64
    extrinsics = [
        orbit_extrinsics(
            distance=DISTANCE, azimuth_deg=360.0 * k / n_views, elevation_deg=20.0 * (-1) ** k
        )
        for k in range(n_views)
    ]
    big = CameraGroup.from_arrays(
        [f"c{k}" for k in range(n_views)],
        np.array([e[0] for e in extrinsics]),
        np.array([e[1] for e in extrinsics]),
        np.tile(rig.intrs[:1], (n_views, 1)),
        np.zeros((n_views, 5)),
    )
    pts3d = np.array([[0.2, -0.3, 0.4], [-0.5, 0.1, 0.0], [0.3, 0.3, -0.6]])
    pts2d = np.full((n_views, 3, 2), np.nan)
    exact = big.project(pts3d) + np.random.default_rng(3).normal(scale=2.0, size=(n_views, 3, 2))
    seen = np.zeros((n_views, 3), dtype=bool)
    seen[[0, 1, 2]] = True
    seen[62, [0, 2]] = True
    seen[63, [1, 2]] = True
    pts2d[seen] = exact[seen]
    pts2d[63, 2] += 120.0  # an outlier
    got, inliers = tri.triangulate_ransac(big, pts2d)
    ref, ref_inliers = _brute_force_ransac(pts2d, big, 15.0)
    np.testing.assert_array_equal(inliers, ref_inliers)
    assert inliers[62, 0] and inliers[63, 1] and not inliers[63, 2]
    np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-10)


def test_ransac_vote_is_not_weighted(rig, scene):
    pts3d, pts2d = scene
    corrupted = pts2d.copy()
    corrupted[5] += 200.0
    conf = np.full(pts2d.shape[:-1], 0.5)
    conf[5] = 1.0  # a confidently wrong view
    got, inliers = tri.triangulate_ransac(rig, corrupted, weights=conf)
    assert not inliers[5].any()
    np.testing.assert_allclose(got, pts3d, atol=1e-9)


def test_ransac_with_distorted_cameras(rig, scene):
    pts3d, _ = scene
    dists = np.tile([-0.2, 0.05, 0.0, 0.0, 0.0], (7, 1))
    distorted = CameraGroup.from_arrays(rig.names, rig.rvecs, rig.tvecs, rig.intrs, dists)
    pts2d = distorted.project(pts3d)
    assert np.abs(pts2d - rig.project(pts3d)).max() > 1e-3  # the distortion is visible
    pts2d[6] += 80.0
    got, inliers = tri.triangulate_ransac(distorted, pts2d)
    np.testing.assert_allclose(got, pts3d, atol=1e-8)
    assert not inliers[6].any() and inliers[:6].all()
    # the JAX kernels' distorted paths: DLT on undistorted points, greedy's raw-image errors
    clean = distorted.project(pts3d)
    np.testing.assert_allclose(tri.triangulate(distorted, clean), pts3d, atol=1e-8)
    greedy, kept = _greedy(distorted, pts2d, reproj_threshold=20.0)
    np.testing.assert_allclose(greedy, pts3d, atol=1e-8)
    assert not kept[6].any() and kept[:6].all()


# -- greedy ----------------------------------------------------------------------------------------


def _greedy(rig, pts2d, **knobs):
    """Greedy's 3D and the views it kept (the finite 2D it returns)."""
    pts3d, clean, _ = tri.reconstruct(rig, pts2d, TriangulationParams(method="greedy", **knobs))
    return pts3d, np.isfinite(clean).all(-1)


def test_greedy_drops_the_outlier(rig, scene):
    pts3d, pts2d = scene
    corrupted = pts2d.copy()
    corrupted[3, :, :, 0] += 400.0
    got, kept = _greedy(rig, corrupted, reproj_threshold=40.0)
    np.testing.assert_allclose(got, pts3d, atol=1e-9)
    assert not kept[3].any() and kept[[0, 1, 2, 4, 5, 6]].all()
    # max_drops=0 is plain DLT.
    np.testing.assert_allclose(
        _greedy(rig, corrupted, max_drops=0)[0],
        tri.triangulate(rig, corrupted),
        rtol=1e-12,
    )
    # Two inconsistent views (off the epipolar line): one is dropped, and one view
    # cannot make a point.
    pair = np.full_like(pts2d, np.nan)
    pair[[0, 1]] = pts2d[[0, 1]]
    pair[1, ..., 1] += 400.0
    got, kept = _greedy(rig, pair)
    assert np.isnan(got).all() and not kept.any()


# -- dispatch and config ---------------------------------------------------------------------------------


def test_reconstruct_dispatch_shapes(rig, scene):
    pts3d, pts2d = scene
    for method in METHODS:
        out3d, clean, err = tri.reconstruct(rig, pts2d, TriangulationParams(method=method))
        assert (
            out3d.shape == pts3d.shape
            and clean.shape == pts2d.shape
            and err.shape == pts2d.shape[:-1]
        )
        np.testing.assert_allclose(out3d, pts3d, atol=1e-9)
    with pytest.raises(ValueError, match="unknown triangulation method"):
        tri.reconstruct(rig, pts2d, TriangulationParams(method="magic"))


def test_reconstruct_reads_the_methods_knobs(rig, scene):
    pts3d, pts2d = scene
    corrupted = pts2d.copy()
    corrupted[2] += 60.0
    config = Config.from_dict({"triangulation": {"method": "ransac", "ransac_threshold": 20.0}})
    got, clean, _ = tri.reconstruct(rig, corrupted, config.triangulation)
    np.testing.assert_allclose(got, pts3d, atol=1e-9)
    assert np.isnan(clean[2]).all()
    # With a threshold above the outlier's pull, nothing is rejected.
    loose = Config.from_dict({"triangulation": {"method": "greedy", "reproj_threshold": 1000.0}})
    got, clean, _ = tri.reconstruct(rig, corrupted, loose.triangulation)
    assert np.isfinite(clean).all() and np.abs(got - pts3d).max() > 1e-4
    # the method is checked once, where the config is read
    with pytest.raises(ConfigError, match="triangulation.method"):
        Config.from_dict({"triangulation": {"method": "nonsense"}})


def test_each_methods_knobs_are_params_fields_and_its_functions_keywords(rig, scene):
    from flylib.config.constants import TRIANGULATION_METHODS
    from flylib.config.params import TRIANGULATION_KNOBS

    _, pts2d = scene
    fields = {f.name for f in dataclasses.fields(TriangulationParams)}
    assert set(TRIANGULATION_KNOBS) == set(TRIANGULATION_METHODS) == set(METHODS)
    for method, knobs in TRIANGULATION_KNOBS.items():
        assert set(knobs) <= fields, method
        params = TriangulationParams(method=method, ransac_threshold=7.0, max_drops=1)
        assert set(params.method_params()) == {"method", "weigh_by_confidence", *knobs}
        kwargs = params.method_kwargs()
        assert kwargs == {kw: getattr(params, name) for name, kw in knobs.items()}
        tri.reconstruct(rig, pts2d[:, :1], params)  # a knob its function lacks: TypeError


# -- real data ------------------------------------------------------------------------------------------


def test_ransac_on_the_deepfly3d_sample(df3d_pickle, rig):
    with open(df3d_pickle, "rb") as fh:
        data = pickle.load(fh)
    norm = data["points2d"]  # (7, 15, 38, 2): [row / 480, col / 960]
    missing = (norm == 0).all(axis=-1) | ((norm[..., 0] == 0) & (norm[..., 1] == 1))
    pts2d = np.stack([norm[..., 1] * 960.0, norm[..., 0] * 480.0], axis=-1)
    pts2d[missing] = np.nan
    pts2d = np.roll(pts2d, 19, axis=2)  # DeepFly3D joint j -> fly38 point (j + 19) % 38
    seen = np.isfinite(pts2d).all(axis=-1).sum(axis=0)
    assert (seen >= 2).any()
    # The uncalibrated default rig is ~10 px off on this recording: 30 px keeps every
    # point seen twice (15 px, the default, keeps > 99%).
    pts3d, clean, err = tri.reconstruct(rig, pts2d, TriangulationParams(ransac_threshold=30.0))
    assert np.isfinite(pts3d[seen >= 2]).all()
    assert np.nanmedian(err) < 15.0
    strict, _, _ = tri.reconstruct(rig, pts2d)
    assert np.isfinite(strict[seen >= 2]).all(axis=-1).mean() > 0.95
    # The orbit convention reconstructs a fly facing +x: its right side (r* points,
    # 19..37) at -y, its left at +y, front legs ahead of hind legs.
    right, left = np.nanmean(pts3d[:, 19:34, 1]), np.nanmean(pts3d[:, 0:15, 1])
    assert right < 0 < left
    front_x = np.nanmean(pts3d[:, [19, 0], 0])  # rf / lf thorax-coxa
    hind_x = np.nanmean(pts3d[:, [29, 10], 0])  # rh / lh thorax-coxa
    assert front_x > hind_x
