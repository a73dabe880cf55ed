"""Session calibration through the workflow (issue 38): three trials of one rig in one
folder, ``bundle_adjustment.session: true``. The session is solved once; every
trial's triangulation, refinement and assembly read that rig; the session's
provenance names its members; the session summary sets the per-trial rigs beside it.
"""

from __future__ import annotations

import json
import re
import tomllib

import numpy as np
import pytest

from tests.workflow.test_workflow import base_config, make_recording, planned, snakemake

pytestmark = pytest.mark.slow

TRIALS = ("trial1", "trial2", "trial3")


@pytest.fixture(scope="module")
def session_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("session")
    config = base_config()
    config["bundle_adjustment"]["max_nfev"] = 20
    config["bundle_adjustment"]["session"] = True
    config["pipeline"]["do_visualization"] = False
    config["pipeline"]["do_kinematics"] = False
    config["recordings"] = [
        make_recording(config, root / "day1" / name, seed) for seed, name in enumerate(TRIALS)
    ]
    proc = snakemake(root, config=config)
    return {"root": root, "config": config, "run": proc}


def _session_dir(root):
    return root / "day1" / "flylib_sessions" / "day1"


def test_the_session_is_solved_once_and_every_trial_reads_its_rig(session_run):
    from flylib.results import PoseResult, read_meta, read_stage

    root, proc = session_run["root"], session_run["run"]
    log = proc.stdout + proc.stderr
    assert len(re.findall(r"^(?:local)?rule session_calibration:", log, re.MULTILINE)) == 1
    assert len(re.findall(r"^(?:local)?rule bundle_adjustment:", log, re.MULTILINE)) == 3
    folder = _session_dir(root)
    session = read_stage(folder / "session_calibration.h5", "bundle_adjustment")
    session_id = read_meta(folder / "session_calibration.h5")["artifact_id"]
    toml = tomllib.loads((folder / "calibration.toml").read_text())
    for name in TRIALS:
        out = root / "day1" / name / "flylib_outputs"
        tri_meta = read_meta(out / "stages" / "triangulation.h5")
        assert tri_meta["upstream_artifact_ids"]["bundle_adjustment"] == session_id
        result = PoseResult.load(out / "results.h5")
        np.testing.assert_array_equal(result.cameras.tvecs, session["cameras"].tvecs)
        np.testing.assert_array_equal(result.cameras.rvecs, session["cameras"].rvecs)
        # the trial's calibration.toml is the session's rig
        own = tomllib.loads((out / "calibration.toml").read_text())
        for cam in (k for k in toml if k.startswith("cam_")):
            np.testing.assert_allclose(own[cam]["translation"], toml[cam]["translation"])
            np.testing.assert_allclose(own[cam]["rotation"], toml[cam]["rotation"])
        # the stored reprojection error is that of the stored 3D through the stored rig
        tri = read_stage(out / "stages" / "triangulation.h5", "triangulation")
        projected = session["cameras"].project(tri["points3d"])
        error = np.linalg.norm(projected - tri["points"], axis=-1)
        np.testing.assert_allclose(error, tri["reproj_error"], atol=1e-6, equal_nan=True)
        # its own solve is kept (for the summary), and differs from the session's
        own_ba = read_stage(out / "stages" / "bundle_adjustment.h5", "bundle_adjustment")
        assert not np.array_equal(own_ba["cameras"].tvecs, session["cameras"].tvecs)


def test_provenance_names_the_session_and_its_members(session_run):
    from flylib.results import read_meta, read_stage

    folder = _session_dir(session_run["root"])
    meta = read_meta(folder / "session_calibration.h5")
    assert meta["session"] == {"name": "day1", "members": list(TRIALS)}
    assert set(meta["upstream_params_sha256"]) == {f"pose2d:{t}" for t in TRIALS}
    attrs = read_stage(folder / "session_calibration.h5", "bundle_adjustment")["attrs"]
    assert json.loads(attrs["summary"])["session"]["members"] == list(TRIALS)
    toml = tomllib.loads((folder / "calibration.toml").read_text())
    assert toml["metadata"]["session"] == "day1"
    assert toml["metadata"]["recordings"] == list(TRIALS)


def test_each_trials_results_are_consistent_with_the_session_rig(session_run):
    """``flylib inspect``'s provenance check of a member's results.h5 against the
    snapshot config beside it: every stage ok (the rig is the session's, not stale)."""
    from flylib.config import Config
    from flylib.pipeline.planning import params_of
    from flylib.provenance import provenance_report

    for name in TRIALS:
        out = session_run["root"] / "day1" / name / "flylib_outputs"
        config = Config.from_file(out / "config.yaml")
        rows = provenance_report(out / "results.h5", params_of(config))
        assert {row.stage: row.status for row in rows} == dict.fromkeys(
            ("pose2d", "bundle_adjustment", "triangulation", "refinement", "assemble"), "ok"
        ), [p for row in rows for p in row.problems]


def test_session_summary_sets_per_trial_and_session_rigs_side_by_side(session_run):
    folder = _session_dir(session_run["root"])
    summary = json.loads((folder / "session_summary.json").read_text())
    assert summary["members"] == list(TRIALS)
    assert set(summary["recordings"]) == set(TRIALS)
    for row in summary["recordings"].values():
        for label in ("per_recording", "session"):
            assert row[label]["n"] > 0 and row[label]["median"] >= 0
    pooled = summary["held_out_error_px"]
    assert pooled["session"]["n"] == sum(r["session"]["n"] for r in summary["recordings"].values())
    assert summary["better"] in ("session", "per_recording")
    assert summary["better"] == min(pooled, key=lambda k: pooled[k]["median"])
    assert sum(summary["frames_per_recording"]) == 3 * 6  # 6-frame trials, max_frames 200
    # the end of the run says it too
    line = next(x for x in session_run["run"].stderr.splitlines() if x.startswith("session day1"))
    assert f"{pooled['session']['median']:.2f} px with the session's" in line
    assert str(folder / "calibration.toml") in line


def test_session_off_and_on_keep_the_per_trial_solves(session_run):
    """The switch re-plans only the stages that read the rig: the per-trial solves
    (their params leave the switch out) and the 2D stay."""
    root, config = session_run["root"], session_run["config"]
    assert planned(root, config) == set()
    off = {**config, "bundle_adjustment": {**config["bundle_adjustment"], "session": False}}
    jobs = planned(root, off)
    assert {rule for rule, _ in jobs} == {"triangulation", "refinement", "assemble"}
    assert {rec for _, rec in jobs} == set(TRIALS)


@pytest.mark.parametrize("script", ["session_calibration", "session_summary"])
def test_session_scripts_have_help(script):
    import subprocess
    import sys

    from workflow_run import REPO

    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / f"{script}.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0 and "--members" in proc.stdout and "--config" in proc.stdout
