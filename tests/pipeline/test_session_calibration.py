"""The session solve (flylib.pipeline.session_calibration, issue 38): frames shared
between the trials, one rig from all of them, the switch outside the per-trial params."""

from __future__ import annotations

import numpy as np
import pytest

from flylib.bundle_adjustment import select_session_frames
from flylib.config import Config
from flylib.errors import ConfigError
from flylib.pipeline.inputs import stage_params
from flylib.pipeline.session_calibration import (
    SessionCalibrationInputs,
    compute_session_calibration,
)

import rough_rig as rr
from rig_constants import VIEWS
from synthetic import POINT_NAMES, rig_visibility


def _trials(counts, views=2, points=3):
    rng = np.random.default_rng(0)
    return [rng.normal(size=(views, n, points, 2)) for n in counts]


def test_max_frames_is_shared_between_the_trials():
    trials = _trials([50, 40, 30])
    chosen = select_session_frames(trials, [None] * 3, 20, "even")
    assert [c.size for c in chosen] == [7, 7, 6]
    assert all(np.all(np.diff(c) > 0) and c.max() < t.shape[1] for c, t in zip(chosen, trials))
    # null keeps every frame; fewer frames than trials still samples each trial once
    assert [c.size for c in select_session_frames(trials, [None] * 3, None)] == [50, 40, 30]
    assert [c.size for c in select_session_frames(trials, [None] * 3, 2)] == [1, 1, 1]
    # a short trial gives what it has
    assert [c.size for c in select_session_frames(_trials([3, 40]), [None] * 2, 20)] == [3, 10]
    with pytest.raises(ConfigError, match="max_frames must be >= 1"):
        select_session_frames(trials, [None] * 3, 0)


def test_the_session_switch_leaves_the_per_trial_solve_unchanged():
    off = Config.default()
    data = dict(off.data)
    data["bundle_adjustment"] = {**data["bundle_adjustment"], "session": True}
    on = Config.from_dict(data)
    assert stage_params(on, "bundle_adjustment") == stage_params(off, "bundle_adjustment")
    session = SessionCalibrationInputs.from_config(on).canonical_params()
    assert session["bundle_adjustment"]["session"] is True
    assert "session" not in stage_params(on, "bundle_adjustment")["bundle_adjustment"]


def test_one_solve_over_three_trials_refines_the_rough_rig():
    """Three short trials of one rig (the front camera sees both sides): the session's
    rig is far closer to the truth than the rough start, from max_frames frames in all."""
    rig = rr.true_rig(seed=0)
    start = rr.rough_start(rig, seed=1)
    vis = rig_visibility(list(VIEWS), POINT_NAMES)
    trials, confs, truths = [], [], []
    for k in range(3):
        truth = rr.tethered_fly(40, seed=k)
        pts2d, conf, _ = rr.detections(rig, truth, vis, np.random.default_rng(k), 1.0, 0.05, 80.0)
        trials.append(pts2d)
        confs.append(conf)
        truths.append(truth)
    data = dict(Config.default().data)
    data["bundle_adjustment"] = {**data["bundle_adjustment"], "max_frames": 60}
    inputs = SessionCalibrationInputs.from_config(Config.from_dict(data))
    result, frames = compute_session_calibration(inputs, start, trials, confs)
    assert [f.size for f in frames] == [20, 20, 20]
    assert result.summary["frames_per_recording"] == [20, 20, 20]
    assert result.points3d.shape == (60, len(POINT_NAMES), 3)

    def centre_error(cameras):
        import cv2

        from flylib.alignment import similarity_aligned

        def centres(g):
            return np.array(
                [-cv2.Rodrigues(np.asarray(r, float))[0].T @ t for r, t in zip(g.rvecs, g.tvecs)]
            )

        truth = centres(rig)
        return np.linalg.norm(similarity_aligned(centres(cameras), truth) - truth, axis=1).max()

    assert centre_error(result.cameras) < 0.1 * centre_error(start)


def test_a_member_with_other_cameras_is_one_line_naming_it(tmp_path):
    from flylib.errors import ResultsError
    from flylib.pipeline.session_calibration import run_session_calibration
    from flylib.results import Pose2dData

    config = Config.default()
    skeleton = config.skeleton()
    views = config.view_names()
    paths = []
    for name, sizes in (("t1", (480, 960)), ("t2", (512, 960))):
        n_points = len(skeleton.point_names)
        data = Pose2dData(
            pts2d=np.zeros((len(views), 2, n_points, 2)),
            conf=np.ones((len(views), 2, n_points)),
            view_names=list(views),
            image_sizes={v: sizes for v in views},
        )
        data.save(tmp_path / f"{name}.h5", skeleton)
        paths.append(tmp_path / f"{name}.h5")
    inputs = SessionCalibrationInputs.from_config(config)
    with pytest.raises(
        ResultsError, match=r"t2\.h5: recording 't2' has views .* one session is one rig"
    ):
        run_session_calibration(
            inputs, paths, tmp_path / "s.h5", tmp_path / "c.toml", name="day1", members=["t1", "t2"]
        )
    assert not (tmp_path / "s.h5").exists() and not (tmp_path / "c.toml").exists()
