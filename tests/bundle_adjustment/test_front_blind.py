"""Bundle adjustment where the images leave directions open.

The real DeepFly3D sample (front camera blind, the two sides share no view), the
front-blind scene made of DeepFly3D's own 3D and calibration (``tests/front_blind.py``),
a synthetic front-blind rig built the hard way (``tests/rough_rig.py``: focal ~16,000 px
at ~116 units, each side camera sees its own side, the start off in position and aim),
and swapped cameras. On each, the refined rig's held-out-view error (truth-free) is
never worse than the starting rig's.
"""

from __future__ import annotations

import warnings

import front_blind
import numpy as np
import pytest

from flylib.bundle_adjustment.parts import (
    align_parts,
    camera_parts,
    crossing_bones,
    point_parts,
)
from flylib.config import Config
from flylib.pipeline.bundle_adjustment import compute_bundle_adjustment
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.pose2d import import_target
from flylib.triangulation import reconstruct

from rough_rig import fit_with_default_config, make_case

needs_deepfly3d = pytest.mark.skipif(
    not front_blind.available(),
    reason=f"{front_blind.PACKAGE_EXAMPLE} or the DeepFly3D sample is absent "
    "(real-data tests need ../shared/data beside the repo)",
)


def _fit(config, rig, pts2d, conf):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        adjusted = compute_bundle_adjustment(
            stage_inputs(config, "bundle_adjustment"), rig, pts2d, conf
        )
    result, refined = adjusted.solution, adjusted.cameras
    pts3d, _, _ = reconstruct(refined, pts2d, config.triangulation, conf)
    return result, refined, pts3d, [str(w.message) for w in caught]


def test_cameras_sharing_no_point_form_groups_and_constraints_stay_inside():
    # 3 views, 6 columns: views 0 and 1 share columns 0-2; view 2 sees columns 3-5
    usable = np.zeros((3, 6), bool)
    usable[:2, :3] = usable[2, 3:] = True
    ids = np.arange(6)
    part = camera_parts(usable, ids, 6)
    assert part.tolist() == [0, 0, 1]
    # a stray shared column does not join two groups (fewer than MIN_SHARED_POINTS)
    usable[2, 0] = True
    assert camera_parts(usable, ids, 6).tolist() == [0, 0, 1]
    assert camera_parts(np.zeros((2, 6), bool), ids, 6).tolist() == [-1, -1]
    pt_part = point_parts(usable, ids, 6, part)
    assert pt_part.tolist() == [0, 0, 0, 1, 1, 1]  # column 0: two votes against one
    # bones 0-1 and 3-4 stay inside a group, 0-3 joins the two
    assert crossing_bones(np.array([0, 3, 0]), np.array([1, 4, 3]), pt_part) == 1


def test_each_group_is_put_back_where_the_start_had_it():
    from flylib.bundle_adjustment.adjust import camera_table
    from flylib.bundle_adjustment.gauge import similarity_table

    case = make_case(5, blind_front=True)
    table0 = camera_table(case.start)
    pts0 = case.truth[0, :12]
    cam_part = np.array([0, 0, 0, -1, 1, 1, 1])
    pt_part = np.array([0] * 6 + [1] * 6)
    # move group 1 by a similarity: nothing in its images changes
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    table = table0.copy()
    table[4:] = similarity_table(table0[4:], 1.3, rot, np.array([1.0, 2.0, 3.0]))
    pts = pts0.copy()
    pts[6:] = 1.3 * pts0[6:] @ rot.T + [1.0, 2.0, 3.0]
    back, back_pts = align_parts(table0, table, pts, pts0, cam_part, pt_part, np.ones(7, bool))
    np.testing.assert_allclose(back_pts, pts0, atol=1e-9)
    np.testing.assert_allclose(back[4:, :6], table0[4:, :6], atol=1e-9)


@needs_deepfly3d
def test_real_sample_meets_the_seed_and_beats_no_bundle_adjustment(df3d_sample_dir):
    """DeepFly3D's sample, default config: the seed system's 0.084 median bones against
    DeepFly3D's own 3D (the same recording: its 1.x file's 2D matches the sample's to
    the heatmap grid); measured 0.078 (no bundle adjustment 0.219, before 0.263)."""
    from flylib.interop.importer import import_points2d
    from flylib.pipeline.planning import config_rig

    config = Config.default()
    spec = {"format": "deepfly3d", "files": "df3d_result_2d.pkl"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the blind front camera is warned about
        pose2d = import_points2d(import_target(config), df3d_sample_dir, spec)
    rig = config_rig(config, pose2d.image_sizes)
    truth = front_blind.recorded_poses()
    bone = front_blind.median_bone(truth)
    plain, _, _ = reconstruct(rig, pose2d.pts2d, config.triangulation, pose2d.conf)
    result, refined, pts3d, caught = _fit(config, rig, pose2d.pts2d, pose2d.conf)

    error = np.nanmedian(front_blind.mirror_free_error(pts3d, truth)) / bone
    before = np.nanmedian(front_blind.mirror_free_error(plain, truth)) / bone
    assert error <= 0.084 and error < 0.5 * before
    held_out = np.nanmedian(front_blind.held_out_error(refined, pose2d.pts2d))
    assert held_out <= np.nanmedian(front_blind.held_out_error(rig, pose2d.pts2d))
    # what was decided from the data, in the report and the warning
    assert result.report["camera_groups"] == [["rh", "rm", "rf"], ["lf", "lm", "lh"]]
    assert result.report["constraints_across_groups_dropped"] > 0
    assert result.report["rigid"]["used"] is False  # its thorax moves 5 px
    message = next(w for w in caught if "poorly determined" in w)
    assert "{rh, rm, rf} and {lf, lm, lh}" in message and "f sees no point" in message
    assert "calibration" in message and "Hessian" not in message
    assert not [w for w in caught if "degrees away" in w]


@needs_deepfly3d
def test_deepfly3d_front_blind_scene():
    """Real DeepFly3D poses and rig, the sample's visibility, 5 % outliers, the default
    rig as the start. Measured 0.066 median bones at 1,000 frames (the seed system:
    0.061, no bundle adjustment 0.196, before 0.170 with inlier rounds that never
    settled)."""
    case = front_blind.make_case(300)
    plain, _, _ = reconstruct(case.start, case.pts2d, Config.default().triangulation, case.conf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result, refined, pts3d, _ = fit_with_default_config(case, max_frames=100)
    error = np.nanmedian(front_blind.mirror_free_error(pts3d, case.truth)) / case.bone
    before = np.nanmedian(front_blind.mirror_free_error(plain, case.truth)) / case.bone
    assert error <= 0.075 and error < 0.5 * before
    assert result.report["inliers_stable"]
    assert np.nanmedian(front_blind.held_out_error(refined, case.pts2d)) <= np.nanmedian(
        front_blind.held_out_error(case.start, case.pts2d)
    )


def test_synthetic_front_blind_rig_keeps_the_sides_where_the_start_had_them():
    """Built the hard way (no ../shared needed): each side camera sees its own side, the
    front camera nothing, the start 4 degrees off on the orbit and 4 % in distance.
    Measured 0.126 median bones (no bundle adjustment 0.172; before, with the mirror
    constraints placing one side against the other: 0.450)."""
    case = make_case(120, blind_front=True)
    plain, _, _ = reconstruct(case.start, case.pts2d, Config.default().triangulation, case.conf)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result, refined, pts3d, err = fit_with_default_config(case, max_frames=60)
    before = np.nanmedian(front_blind.mirror_free_error(plain, case.truth)) / case.bone
    assert np.nanmedian(err) < 0.8 * before
    assert result.report["camera_groups"] == [["rh", "rm", "rf"], ["lf", "lm", "lh"]]
    assert result.report["inliers_stable"]
    assert any("poorly determined" in str(w.message) for w in caught)
    assert np.nanmedian(front_blind.held_out_error(refined, case.pts2d)) <= np.nanmedian(
        front_blind.held_out_error(case.start, case.pts2d)
    )


@pytest.mark.parametrize("swap", [("rh", "rm"), ("lf", "lm")])
def test_swapped_cameras_are_named(swap):
    """Two same-side cameras' 2D swapped (as when their videos are): the warning names
    both (measured 21-47 degrees moved; unswapped rigs move at most ~8)."""
    case = make_case(80)
    names = list(case.rig.names)
    i, j = (names.index(n) for n in swap)
    case.pts2d[[i, j]] = case.pts2d[[j, i]]
    case.conf[[i, j]] = case.conf[[j, i]]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result, _, _, _ = fit_with_default_config(case, max_frames=40)
    message = next(str(w.message) for w in caught if "degrees away" in str(w.message))
    assert f"cameras {swap[0]} and {swap[1]} ended" in message
    assert "swapped" in message
    assert min(result.report["moved_deg"][n] for n in swap) > 15


def test_an_unswapped_rig_is_not_named():
    case = make_case(80)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result, _, _, _ = fit_with_default_config(case, max_frames=40)
    assert not [w for w in caught if "degrees away" in str(w.message)]
    assert max(result.report["moved_deg"].values()) < 15
