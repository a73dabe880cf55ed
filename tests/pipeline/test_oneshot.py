"""run_from_points2d: synthetic truth recovery and the real DeepFly3D sample."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from flylib.alignment import similarity_aligned
from flylib.errors import ConfigError
from flylib.pipeline import run_from_points2d
from flylib.skeleton import Skeleton

from synthetic import default_rig, observe, perturb_rig, synthetic_fly


def _similarity_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-point distance after a trimmed least-squares similarity (Umeyama) alignment.

    The alignment is refitted on the 90 % best-agreeing points, so that the few gross
    errors no triangulation can catch (an outlier along the epipolar line of a point
    seen by two views only) do not tilt it.
    """
    aligned = similarity_aligned(estimate, truth, keep=0.9, refits=2)
    return np.linalg.norm(aligned - truth, axis=-1)


@pytest.mark.slow
def test_synthetic_fly_truth_is_recovered():
    """Perturbed rig (3 deg, 3 %), 1 px noise, 5 % outliers, real visibility pattern."""
    from flylib.triangulation import reconstruct

    rig, skeleton = default_rig(), Skeleton.fly()
    truth = synthetic_fly(200, seed=0)
    pts2d, conf = observe(truth, rig, noise_px=1.0, outlier_frac=0.05, seed=0)
    start = perturb_rig(rig, rot_deg=3.0, dist_frac=0.03, seed=1)

    result = run_from_points2d(
        start, skeleton, pts2d, conf, bundle_adjust_kwargs={"max_frames": 60}
    )
    i, j = skeleton.bone_index_pairs()
    bone = np.median(np.linalg.norm(truth[:, i] - truth[:, j], axis=-1))
    err = _similarity_error(result.pts3d, truth)
    floor_err = _similarity_error(reconstruct(rig, pts2d)[0], truth)
    before = _similarity_error(reconstruct(start, pts2d)[0], truth)
    assert np.nanmedian(err) < 0.02 * bone
    assert np.nanmedian(err) < 0.5 * np.nanmedian(before)
    # reprojection error within 20 % of what the true rig gives
    floor = np.nanmedian(reconstruct(rig, pts2d)[2])
    assert np.nanmedian(result.reproj_error) < 1.2 * floor
    assert np.isfinite(result.pts3d).all(-1).mean() > 0.95
    assert result.meta["bundle_adjustment"]["final_median_px"] < 1.0
    assert np.nanmedian(floor_err) < 0.02 * bone


def test_bad_arguments_are_clear_errors():
    rig, skeleton = default_rig(), Skeleton.fly()
    pts2d = np.full((7, 2, 38, 2), np.nan)
    with pytest.raises(ConfigError, match="unknown method 'svd'"):
        run_from_points2d(rig, skeleton, pts2d, triangulation="svd")
    with pytest.raises(ConfigError, match="candidates"):
        run_from_points2d(rig, skeleton, pts2d, do_pictorial=True, do_bundle_adjust=False)


def test_pictorial_path_agrees_with_plain_triangulation():
    from flylib.pictorial import Candidates

    rig, skeleton = default_rig(), Skeleton.fly()
    truth = synthetic_fly(6, seed=9)
    pts2d, conf = observe(truth, rig, noise_px=0.5, seed=9)
    plain = run_from_points2d(rig, skeleton, pts2d, conf, do_bundle_adjust=False)
    pictorial = run_from_points2d(
        rig,
        skeleton,
        pts2d,
        conf,
        do_bundle_adjust=False,
        do_pictorial=True,
        candidates=Candidates.from_points(pts2d, conf),
    )
    np.testing.assert_allclose(pictorial.pts3d, plain.pts3d, atol=1e-9)
    assert pictorial.meta["pictorial"] and not plain.meta["pictorial"]
    assert np.nanmax(np.linalg.norm(plain.pts3d - truth, axis=-1)) < 0.05


def test_one_argument_order_and_no_aliases():
    rig, skeleton = default_rig(), Skeleton.fly()
    pts2d = np.full((7, 2, 38, 2), np.nan)
    with pytest.raises(TypeError, match="do_bundle_adjustment"):
        run_from_points2d(rig, skeleton, pts2d, do_bundle_adjustment=False)
    with pytest.raises(TypeError):  # (pts2d, cameras, skeleton) is not the seed's order
        run_from_points2d(pts2d, rig, skeleton, do_bundle_adjust=False)


def test_defaults_are_the_packaged_configs(monkeypatch):
    from flylib.config import Config
    from flylib.pipeline import oneshot

    data = Config.default().data
    data["triangulation"] = {**data["triangulation"], "method": "greedy"}
    monkeypatch.setattr(oneshot, "packaged_defaults", lambda: Config.from_dict(data))
    rig, skeleton = default_rig(), Skeleton.fly()
    pts2d, conf = observe(synthetic_fly(4, seed=3), rig, noise_px=0.5, seed=3)
    assert (
        run_from_points2d(rig, skeleton, pts2d, conf, do_bundle_adjust=False).meta["triangulation"]
        == "greedy"
    )


def test_one_chain_the_stages_compute_steps():
    """The one-shot is the stages' compute steps on the default config's inputs: the
    same rig and 3D as the workflow's bundle adjustment (its legs-and-antennae points_to_use
    included) and triangulation; an override is checked as a config is."""
    from flylib.config import Config
    from flylib.pipeline.bundle_adjustment import compute_bundle_adjustment
    from flylib.pipeline.inputs import stage_inputs
    from flylib.pipeline.triangulation import compute_triangulation

    rig, skeleton = default_rig(), Skeleton.fly()
    pts2d, conf = observe(synthetic_fly(12, seed=4), rig, noise_px=0.5, seed=4)
    start = perturb_rig(rig, rot_deg=1.0, dist_frac=0.01, seed=4)
    result = run_from_points2d(start, skeleton, pts2d, conf)
    config = Config.default()
    adjusted = compute_bundle_adjustment(
        stage_inputs(config, "bundle_adjustment"), start, pts2d, conf
    )
    stage = compute_triangulation(
        stage_inputs(config, "triangulation"), adjusted.cameras, pts2d, conf
    )
    np.testing.assert_array_equal(result.cameras.pmats, adjusted.cameras.pmats)
    np.testing.assert_array_equal(result.pts3d, stage.points3d)
    assert result.meta["bundle_adjustment"]["nfev"] == adjusted.summary["nfev"]
    with pytest.raises(ConfigError, match="bundle_adjustment.max_frames"):
        run_from_points2d(start, skeleton, pts2d, conf, bundle_adjust_kwargs={"max_frames": 0})


# -- real data: DeepFly3D's own 2D for the sample recording ---------------------------------


def load_df3d_points(path) -> tuple[np.ndarray, np.ndarray]:
    """``df3d_result_2d.pkl`` -> fly38 ``pts2d (7, T, 38, 2)`` pixels and ``conf``.

    Normalized ``[row/480, col/960]`` becomes ``(x, y)`` pixels; (0, 0) and, in the
    mirrored cameras 4-6, (0, 1) mean "not detected"; DeepFly3D joint ``j`` is fly38
    point ``(j + 19) % 38``.
    """
    with open(path, "rb") as fh:
        data = pickle.load(fh)
    raw = np.asarray(data["points2d"], float)  # (7, T, 38, 2)
    missing = (raw == 0).all(-1) | ((raw[..., 0] == 0) & (raw[..., 1] == 1))
    xy = np.stack([raw[..., 1] * 960.0, raw[..., 0] * 480.0], axis=-1)
    xy[missing] = np.nan
    order = [(j + 19) % 38 for j in range(38)]
    pts2d = np.full_like(xy, np.nan)
    pts2d[:, :, order] = xy
    hm = np.asarray(data["heatmap_confidence"], float)[..., 0]  # (7, T, 19)
    conf_df3d = np.concatenate([hm, hm], axis=-1)  # channel c serves joints c and c + 19
    conf = np.zeros(pts2d.shape[:3])
    conf[:, :, order] = conf_df3d
    conf[np.isnan(pts2d[..., 0])] = 0.0
    return pts2d, conf


@pytest.mark.shared
def test_real_df3d_sample_reaches_three_pixels(df3d_pickle):
    rig, skeleton = default_rig(), Skeleton.fly()
    pts2d, conf = load_df3d_points(df3d_pickle)
    seen = np.isfinite(pts2d).all(-1)
    assert seen[:2, :, 19:].all() and not seen[:3, :, :19].any() and not seen[3].any()
    assert seen[5:, :, :19].all() and not seen[4:, :, 19:].any()
    result = run_from_points2d(
        rig, skeleton, pts2d, conf, bundle_adjust_kwargs={"max_frames": None}
    )
    assert np.nanmedian(result.reproj_error) <= 3.0
    two_view = np.isfinite(pts2d).all(-1).sum(0) >= 2
    reconstructed = np.isfinite(result.pts3d).all(-1)
    assert reconstructed[two_view].mean() == 1.0
