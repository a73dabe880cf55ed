"""Pictorial structures: heatmap peaks, chains, hypotheses and peak recovery."""

from __future__ import annotations

import numpy as np
import pytest

from flylib import pictorial as ps
from flylib.errors import ConfigError
from flylib.skeleton import Skeleton

from synthetic import POINT_NAMES, default_rig, observe, project_opencv, synthetic_fly

# -- peaks -----------------------------------------------------------------------------


def _gaussian(h, w, x, y, sigma=1.5, amp=1.0):
    yy, xx = np.mgrid[0:h, 0:w]
    return amp * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2))


def test_peaks_are_ordered_padded_and_subpixel_exact_for_gaussians():
    hm = _gaussian(32, 48, 10.3, 7.6) + _gaussian(32, 48, 30.8, 20.2, amp=0.6)
    xy, score = ps.peak_candidates(hm[None], k=3, method="taylor", threshold=0.1)
    assert xy.shape == (1, 3, 2) and score.shape == (1, 3)
    np.testing.assert_allclose(xy[0, 0], [10.3, 7.6], atol=1e-6)
    np.testing.assert_allclose(xy[0, 1], [30.8, 20.2], atol=1e-6)
    assert score[0, 0] > score[0, 1] > 0 and score[0, 2] == 0 and np.isnan(xy[0, 2]).all()


def test_subpixel_methods():
    hm = _gaussian(20, 20, 8.25, 11.0)
    argmax, _ = ps.peak_candidates(hm, k=1, method="argmax")
    weighted, _ = ps.peak_candidates(hm, k=1, method="weighted")
    np.testing.assert_array_equal(argmax[0], [8.0, 11.0])
    assert 8.0 < weighted[0, 0] < 8.3 and abs(weighted[0, 1] - 11.0) < 1e-9
    with pytest.raises(ConfigError, match="sub-pixel"):
        ps.peak_candidates(hm, method="quadratic")


def test_peaks_keep_leading_axes():
    hm = np.zeros((2, 3, 16, 16))
    hm[1, 2, 4, 5] = 1.0
    xy, score = ps.peak_candidates(hm, k=2)
    assert xy.shape == (2, 3, 2, 2)
    np.testing.assert_array_equal(xy[1, 2, 0], [5.0, 4.0])
    assert np.isnan(xy[0, 0]).all() and (score[0, 0] == 0).all()


# -- skeleton helpers ------------------------------------------------------------------


def test_chains_walk_each_limb_end_to_end():
    skeleton = Skeleton.fly()
    chains = ps.skeleton_chains(skeleton)
    assert sorted(p for c in chains for p in c) == list(range(38))
    by_start = {skeleton.point_names[c[0]]: c for c in chains}
    leg = [skeleton.point_names[p] for p in by_start.get("lf_thorax_coxa", by_start.get("lf_claw"))]
    assert leg in (list(skeleton.limbs["lf_leg"]), list(skeleton.limbs["lf_leg"])[::-1])
    assert [skeleton.point_names[c[0]] for c in chains if len(c) == 1] == ["l_antenna", "r_antenna"]


def test_bone_targets_are_true_lengths_despite_outliers():
    rig, skeleton = default_rig(), Skeleton.fly()
    pts3d = synthetic_fly(30, seed=2)
    pts2d, _ = observe(pts3d, rig, noise_px=0.3, outlier_frac=0.1, seed=3)
    i, j, targets = ps.bone_length_targets(rig, pts2d, skeleton)
    truth = np.median(np.linalg.norm(pts3d[:, i] - pts3d[:, j], axis=-1), axis=0)
    legs = np.array([skeleton.point_names[a][1] != "_" for a in i])  # lf_..., rh_...
    np.testing.assert_allclose(targets[legs], truth[legs], rtol=0.005)
    # abdomen points: two views only, so outliers along the epipolar line slip through
    np.testing.assert_allclose(targets, truth, rtol=0.03)


# -- peak recovery -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene():
    """A fly seen with 1 px noise; candidates: truth (arg-max), the mirror joint, junk."""
    rig, skeleton = default_rig(), Skeleton.fly()
    pts3d = synthetic_fly(24, seed=0)
    pts2d, conf = observe(pts3d, rig, noise_px=1.0, outlier_frac=0.0, seed=1)
    mirror = [(i + 19) % 38 for i in range(38)]
    mirrored = np.where(np.isfinite(pts2d), project_opencv(rig, pts3d[:, mirror]), np.nan)
    junk = np.where(
        np.isfinite(pts2d), np.random.default_rng(2).random(pts2d.shape) * [960, 480], np.nan
    )
    xy = np.stack([pts2d, mirrored, junk], axis=3)
    score = np.stack([conf, 0.5 * conf, 0.3 * conf], axis=3)
    return rig, skeleton, pts3d, pts2d, ps.Candidates(xy, score)


def test_clean_candidates_change_nothing(scene):
    rig, skeleton, truth, pts2d, cand = scene
    pts3d, committed, reproj = ps.reconstruct(rig, skeleton, cand)
    np.testing.assert_array_equal(committed, pts2d)
    assert np.nanmax(reproj) < 5.0
    # 1 px at focal 22,388 px and distance 107 is ~0.005 units: the 3D is the truth
    assert np.nanmedian(np.linalg.norm(pts3d - truth, axis=-1)) < 0.02


@pytest.mark.parametrize("temporal", [False, True])
def test_swapped_peak_in_two_views_is_recovered(scene, temporal):
    from flylib.triangulation import reconstruct

    rig, skeleton, truth, pts2d, cand = scene
    frame, joint = 7, POINT_NAMES.index("rf_tibia_tarsus")
    views = np.flatnonzero(np.isfinite(pts2d[:, frame, joint, 0]))
    assert len(views) == 4
    xy, score = cand.xy.copy(), cand.score.copy()
    for v in views[:2]:  # arg-max on the left leg's (strong) peak, the right one second
        xy[v, frame, joint, [0, 1]] = cand.xy[v, frame, joint, [1, 0]]
        score[v, frame, joint, [0, 1]] = [0.95, 0.8]
    swapped = ps.Candidates(xy, score)

    ransac3d, ransac2d, _ = reconstruct(rig, swapped.argmax())
    ransac_err = np.linalg.norm(ransac3d[frame, joint] - truth[frame, joint])
    assert (
        not np.isfinite(ransac_err)
        or ransac_err > 0.1
        or np.isnan(ransac2d[views[:2], frame, joint]).all()
    )  # ransac can at best drop them

    pts3d, committed, _ = ps.reconstruct(rig, skeleton, swapped, temporal=temporal)
    assert np.linalg.norm(pts3d[frame, joint] - truth[frame, joint]) < 0.02
    np.testing.assert_array_equal(committed[views, frame, joint], pts2d[views, frame, joint])


def test_bone_prior_resolves_a_two_view_ambiguity(scene):
    """With only two views any peak pair triangulates; the wrong, stronger pair is
    kept out by the bone lengths to its neighbours."""
    rig, skeleton, truth, pts2d, cand = scene
    frame, joint = 3, POINT_NAMES.index("r_abdomen2")
    views = np.flatnonzero(np.isfinite(pts2d[:, frame, joint, 0]))
    assert len(views) == 2
    xy, score = cand.xy.copy(), cand.score.copy()
    xy[views, frame, joint, 1] = xy[views, frame, joint, 0] + [[0.0, 150.0], [0.0, 150.0]]
    score[views, frame, joint, 1] = 1.0  # a strong, consistent but anatomically wrong pair
    pts3d, _, _ = ps.reconstruct(rig, skeleton, ps.Candidates(xy, score), lam=5.0)
    assert np.linalg.norm(pts3d[frame, joint] - truth[frame, joint]) < 0.02
    pts3d_free, _, _ = ps.reconstruct(rig, skeleton, ps.Candidates(xy, score), lam=0.0)
    assert np.linalg.norm(pts3d_free[frame, joint] - truth[frame, joint]) > 0.1


def test_candidates_validate_shapes():
    with pytest.raises(ValueError, match="Candidates"):
        ps.Candidates(np.zeros((2, 3, 4, 2)), np.zeros((2, 3, 4)))


def test_the_stage_uses_the_pictorial_structures_table(scene):
    from flylib.config import Config
    from flylib.pipeline.inputs import stage_inputs
    from flylib.pipeline.pictorial_structures import compute_pictorial_structures

    rig, _, _, pts2d, cand = scene
    config = Config.from_dict(
        {**Config.default().data, "pictorial_structures": {"k": 3, "temporal": True, "lam": 2.0}}
    )
    inputs = stage_inputs(config, "pictorial_structures")
    assert inputs.pictorial_structures.solver_kwargs()["lam"] == 2.0
    result = compute_pictorial_structures(inputs, rig, cand)
    np.testing.assert_array_equal(result.points, pts2d)
    assert result.points3d.shape == (24, 38, 3) and result.reproj_error.shape == (7, 24, 38)
