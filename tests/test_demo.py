"""The embedded demo recording: motion model, detector-like corruption, files, scoring."""

from __future__ import annotations

import numpy as np
import pytest

from flylib.config import Config
from flylib.demo import (
    DEMO_DEFAULTS,
    FLY38_POINTS,
    demo_error,
    demo_settings,
    load_truth,
    observe,
    synthetic_fly,
    view_visibility,
)
from flylib.errors import ConfigError
from flylib.pipeline.demo import make_demo
from flylib.pipeline.pose2d import import_target


@pytest.fixture(scope="module")
def config():
    return Config.default()


@pytest.fixture(scope="module")
def demo(config, tmp_path_factory):
    return make_demo(config, tmp_path_factory.mktemp("demo"), frames=5)


def test_leg_segments_keep_their_length_and_the_legs_move():
    pts = synthetic_fly(40, seed=3)
    assert pts.shape == (40, 38, 3)
    for side in "lr":
        for leg in "fmh":
            chain = [
                FLY38_POINTS.index(f"{side}{leg}_{j}")
                for j in ("thorax_coxa", "coxa_trochanter", "femur_tibia", "tibia_tarsus", "claw")
            ]
            lengths = np.linalg.norm(np.diff(pts[:, chain], axis=1), axis=-1)  # (T, 4)
            np.testing.assert_allclose(lengths, lengths[:1].repeat(40, 0), atol=1e-12)
            assert np.ptp(pts[:, chain[-1]], axis=0).max() > 0.1  # the claw walks
    np.testing.assert_array_equal(pts, synthetic_fly(40, seed=3))
    assert not np.allclose(pts, synthetic_fly(40, seed=4))


def test_every_bone_keeps_its_length():
    """The refinement's acceptance scene assumes constant bones: abdomen included."""
    from flylib.skeleton import Skeleton

    skeleton = Skeleton.fly()
    pts = synthetic_fly(300, seed=5)
    lengths = np.linalg.norm(pts[:, skeleton.bones[:, 0]] - pts[:, skeleton.bones[:, 1]], axis=-1)
    assert np.ptp(lengths, axis=0).max() < 1e-12
    tip = pts[:, FLY38_POINTS.index("l_abdomen2"), 2]
    assert np.ptp(tip) > 0.05  # the abdomen still moves


def test_left_legs_are_on_plus_y_and_the_head_on_plus_x():
    pts = synthetic_fly(3)
    y = {name: pts[0, i, 1] for i, name in enumerate(FLY38_POINTS)}
    assert all(y[p] > 0 for p in FLY38_POINTS if p.startswith("l"))
    assert all(y[p] < 0 for p in FLY38_POINTS if p.startswith("r"))
    x_antenna = pts[0, FLY38_POINTS.index("l_antenna"), 0]
    x_abdomen = pts[0, FLY38_POINTS.index("l_abdomen2"), 0]
    assert x_antenna > 0.5 > -1.0 > x_abdomen


def test_observe_adds_the_configured_corruption():
    rng = np.random.default_rng(0)
    clean = rng.uniform(100, 400, (3, 400, 10, 2))
    visible = np.ones((3, 10), bool)
    visible[1, :5] = False
    settings = {**DEMO_DEFAULTS, "noise_px": 2.0, "dropout": 0.1, "outliers": 0.05}
    pts, like = observe(clean, visible, settings, (480, 960))
    assert np.isnan(pts[1, :, :5]).all() and np.isnan(like[1, :, :5]).all()
    seen = np.isfinite(pts).all(-1)
    assert abs(1 - seen[visible[:, None, :].repeat(400, 1)].mean() - 0.1) < 0.02
    offset = np.linalg.norm(pts - clean, axis=-1)[seen]
    outliers = offset > 30
    assert abs(outliers.mean() - 0.05) < 0.015
    assert offset[outliers].max() <= 120 * 1.001
    inlier_residual = (pts - clean)[seen][~outliers]
    assert inlier_residual.std() == pytest.approx(2.0, rel=0.05)
    again, _ = observe(clean, visible, settings, (480, 960))
    np.testing.assert_array_equal(np.isnan(again), np.isnan(pts))
    np.testing.assert_array_equal(again[seen], pts[seen])


def test_visibility_follows_output_points(config):
    views, points = config.view_names(), list(config.skeleton().point_names)
    vis = view_visibility((config.data.get("pose2d") or {}).get("output_points"), views, points)
    front = views.index("f")
    assert vis[front].sum() == len(config.data["pose2d"]["output_points"]["f"])
    assert not vis[views.index("rh"), points.index("lf_claw")]
    assert vis[views.index("rh"), points.index("rf_claw")]


def test_demo_files_round_trip_through_the_dlc_import(config, demo):
    from flylib.interop import import_points2d
    from flylib.pipeline.demo import demo_import_spec

    truth = load_truth(demo.truth)
    np.testing.assert_array_equal(truth["points3d"], demo.points3d)
    assert truth["points3d"].shape == (5, 38, 3) and truth["views"] == config.view_names()
    imported = import_points2d(import_target(config), demo.directory, demo_import_spec(config))
    assert imported.pts2d.shape == (7, 5, 38, 2)
    assert imported.image_sizes["rh"] == (480, 960)
    # imported 2D = truth + noise (+ rare outliers); unobserved points stay NaN
    err = np.linalg.norm(imported.pts2d - truth["points2d"], axis=-1)
    assert np.nanmedian(err) < 3.0
    visible = view_visibility(
        (config.data.get("pose2d") or {}).get("output_points"),
        config.view_names(),
        list(config.skeleton().point_names),
    )
    assert np.isnan(imported.pts2d[~np.broadcast_to(visible[:, None], err.shape)]).all()


def test_demo_is_deterministic(config, demo, tmp_path):
    again = make_demo(config, tmp_path, frames=5)
    for view, path in demo.dlc.items():
        assert again.dlc[view].read_bytes() == path.read_bytes()
    from flylib.io import open_reader

    frames = open_reader(again.footage["vid_rm"])[:]
    assert frames.shape == (5, 480, 960, 3) and frames.max() > 200  # the skeleton is drawn


def test_demo_error_scores_against_the_truth():
    truth = synthetic_fly(8)
    assert demo_error(truth, truth)["median"] == 0.0
    angle = np.deg2rad(10)
    rot = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    moved = 1.1 * truth @ rot.T + [0.3, 0.0, 0.1]
    moved[0, 0] = np.nan
    score = demo_error(moved, truth)
    assert score["median"] > 0.1
    assert score["median_aligned"] < 1e-9
    assert score["reconstructed"] == pytest.approx(1 - 1 / (8 * 38))
    with pytest.raises(ValueError, match="shape"):
        demo_error(truth[:2], truth)


def test_demo_settings_are_checked():
    assert demo_settings({"frames": 10})["frames"] == 10
    with pytest.raises(ConfigError, match="unknown"):
        demo_settings({"frame": 10})
    with pytest.raises(ConfigError, match="demo.dropout"):
        demo_settings({"dropout": 1.5})


def test_the_demo_job_reads_what_its_rule_tracked_before_and_rebuilds_it_from_that():
    """The demo rule's params: its settings, sources, the assemble stage's rig and
    skeleton and the output points, as the rule wrote them before the inputs objects
    (the assemble params from tests/data/stage_params_golden.json); a job rebuilds the
    same inputs from that JSON."""
    import copy
    import json
    import pickle
    from pathlib import Path

    from flylib.pipeline.demo import DemoInputs

    golden = json.loads((Path(__file__).parent / "data" / "stage_params_golden.json").read_text())
    for name in ("default", "ba_off", "calibration_file", "corrupt_missing"):
        data = copy.deepcopy(golden["base"])
        for path, value in golden["variants"][name]["edits"]:
            node = data
            *parents, last = path.split(".")
            for key in parents:
                node = node.setdefault(key, {})
            node[last] = value
        data["demo"] = {"frames": 7, "noise_px": 0.5}
        assemble = golden["variants"][name]["params"]["assemble"]
        before = json.dumps(
            {
                "demo": {**DEMO_DEFAULTS, "frames": 7, "noise_px": 0.5},
                "sources": data.get("sources"),
                "rig": assemble["rig"],
                "skeleton": assemble["skeleton"],
                "output_points": data["pose2d"].get("output_points"),
            },
            sort_keys=True,
        )
        inputs = DemoInputs.from_config(Config.from_dict(data))
        assert inputs.rule_params() == before, name
        rebuilt = DemoInputs.from_params(json.loads(inputs.rule_params()), inputs.runtime)
        assert rebuilt == inputs and pickle.loads(pickle.dumps(inputs)) == inputs, name
    data = copy.deepcopy(golden["base"])
    del data["skeleton"]
    with pytest.raises(ConfigError, match="no 'skeleton' table"):
        DemoInputs.from_config(Config.from_dict(data))
