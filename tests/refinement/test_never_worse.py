"""Refinement never makes a recording worse: through the stage
functions with the workflow's defaults, the held-out-view error of the output the
results hold is never above the plain triangulation's, on the real DeepFly3D sample,
a front-blind synthetic scene with a rough rig, and the demo; the points where
refinement lost keep the triangulation and say so in refinement.h5 and summary.json."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from flylib.config import Config
from flylib.pipeline.assemble import run_assemble
from flylib.pipeline.bundle_adjustment import run_bundle_adjustment
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.pose2d import run_pose2d
from flylib.pipeline.refinement import run_refinement
from flylib.pipeline.stage_helpers import run_inputs
from flylib.pipeline.triangulation import run_triangulation
from flylib.refinement import FLAG_BITS
from flylib.results import Pose2dData

from rough_rig import make_case

KEPT = FLAG_BITS["kept_triangulation"][0]


def _check_never_worse(out, with_ba=True):
    """Triangulation + refinement + assemble on ``out/stages``; the shared assertions."""
    config = Config.default()
    s = out / "stages"
    ba = s / "bundle_adjustment.h5" if with_ba else None
    run_triangulation(
        run_inputs(config, "triangulation", ba),
        s / "pose2d.h5",
        s / "triangulation.h5",
        ba_path=ba,
    )
    run_refinement(
        run_inputs(config, "refinement", ba),
        s / "pose2d.h5",
        s / "triangulation.h5",
        s / "refinement.h5",
        ba_path=ba,
    )
    files = {"pose2d": s / "pose2d.h5", "triangulation": s / "triangulation.h5"}
    files["refinement"] = s / "refinement.h5"
    if ba is not None:
        files["bundle_adjustment"] = ba
    summary = run_assemble(stage_inputs(config, "assemble"), files, out)
    acc = summary["accuracy"]
    assert acc["output_stage"] == "refinement"
    tri, output = acc["triangulation"]["held_out_px"], acc["output"]["held_out_px"]
    assert tri["n"] == output["n"] > 0
    assert output["median"] <= tri["median"] and output["p95"] <= tri["p95"]
    names = list(config.skeleton().point_names)
    kept = [names.index(n) for n in acc["kept_triangulation"]]
    with h5py.File(s / "refinement.h5") as f, h5py.File(s / "triangulation.h5") as g:
        flags = f["refinement/flags"][()]
        refined = f["refinement/points3d"][()]
        triangulated = g["triangulation/points3d"][()]
        stored = json.loads(f["refinement"].attrs["accuracy"])
    assert stored["kept_triangulation"] == acc["kept_triangulation"]
    flagged = np.flatnonzero((flags & KEPT).any(0))
    assert sorted(flagged.tolist()) == sorted(kept)
    np.testing.assert_array_equal(refined[:, kept], triangulated[:, kept])
    assert json.loads((out / "summary.json").read_text())["accuracy"] == json.loads(json.dumps(acc))
    return acc


def test_real_sample_with_the_workflow_defaults(df3d_sample_dir, tmp_path):
    """The issue's case: DeepFly3D's 2D of the sample, default bundle adjustment,
    ransac, refinement (before: reprojection 2.53 -> 3.71 px median, 6.28 -> 11.7 p95)."""
    config = Config.default()
    s = tmp_path / "stages"
    run_pose2d(
        stage_inputs(config, "pose2d"),
        df3d_sample_dir,
        s / "pose2d.h5",
        import_spec={"format": "deepfly3d"},
    )
    ba_inputs = stage_inputs(config, "bundle_adjustment")
    run_bundle_adjustment(ba_inputs, s / "pose2d.h5", s / "bundle_adjustment.h5")
    acc = _check_never_worse(tmp_path)
    assert acc["frames_evaluated"] == acc["frames_total"] == 15
    # the smoothness is the candidate of lowest held-out error: here a multiple of the
    # recording's own motion, not the 0.03 default (which held this fly too still)
    smooth = acc["smoothness"]
    tried = {float(k): (v["median"], v["p95"]) for k, v in smooth["tried"].items()}
    assert len(tried) == 4 and min(tried, key=tried.get) == pytest.approx(smooth["scale"], rel=1e-5)
    assert smooth["scale"] > 0.03 and tried[0.03][0] > acc["triangulation"]["held_out_px"]["median"]
    with h5py.File(s / "refinement.h5") as f:
        info = json.loads(f["refinement"].attrs["summary"])
    assert info["smooth_scale"] == smooth["scale"]


def test_front_blind_scene_through_bundle_adjustment(tmp_path):
    """The rough rig's hard case: a DeepFly3D-like rig (f ~16,000 px at ~116 units), the
    front camera blind, 1 px noise and 5 % outliers; the workflow's default bundle
    adjustment starts from the config rig (off in aim and position)."""
    case = make_case(120, hard=True, seed=2)
    config = Config.default()
    s = tmp_path / "stages"
    s.mkdir(parents=True)
    sizes = {v: (480, 960) for v in case.rig.names}
    conf = np.where(np.isfinite(case.pts2d).all(-1), case.conf, np.nan)
    Pose2dData(case.pts2d, conf, list(case.rig.names), sizes).save(
        s / "pose2d.h5", config.skeleton()
    )
    ba_inputs = stage_inputs(config, "bundle_adjustment")
    run_bundle_adjustment(ba_inputs, s / "pose2d.h5", s / "bundle_adjustment.h5")
    acc = _check_never_worse(tmp_path)
    assert acc["triangulation"]["held_out_px"]["median"] < 10  # a usable rig to judge on


def test_the_demo(tmp_path, capsys):
    from flylib.pipeline.demo import demo_import_spec, make_demo

    config = Config.default()
    make_demo(config, tmp_path / "demo")
    s = tmp_path / "demo" / "flylib_outputs" / "stages"
    run_pose2d(
        stage_inputs(config, "pose2d"),
        tmp_path / "demo",
        s / "pose2d.h5",
        import_spec=demo_import_spec(config),
    )
    out = tmp_path / "demo" / "flylib_outputs"
    acc = _check_never_worse(out, with_ba=False)
    assert acc["frames_evaluated"] == 60
    # flylib inspect: the held-out figures per stage and per point, and the sentence
    from flylib.cli import main
    from flylib.results import summarize_results

    summary = summarize_results(out / "results.h5")
    rows = {r["stage"]: r for r in summary["stages"]}
    assert rows["triangulation"]["held_median"] == acc["triangulation"]["held_out_px"]["median"]
    assert rows["refinement"]["held_median"] == acc["output"]["held_out_px"]["median"]
    first = summary["points"][0]
    assert first["held_median"] == acc["output"]["per_point"][first["point"]]["median"]
    capsys.readouterr()
    assert main(["inspect", str(out / "results.h5")]) in (0, 2)
    text = capsys.readouterr().out
    assert "held-out median px" in text and "accuracy: held-out px = " in text
    assert "refinement is better than triangulation" in text or "keep" in text
