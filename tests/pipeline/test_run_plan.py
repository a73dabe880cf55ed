"""The workflow's run plan (flylib.pipeline.planning.RunPlan): what each rule reads and
writes, which recordings a run skips, its sessions, targets and pose2d's resources, from
a small config and recordings in a temporary folder (no Snakemake)."""

from __future__ import annotations

import copy
from pathlib import Path
from types import SimpleNamespace

import pytest

from flylib.config import Config
from flylib.errors import ConfigError
from flylib.pipeline.planning import RECORDING_GROUP, RunPlan
from flylib.recordings import Recording

DEFAULT = Config.default().data
IMPORT = {"format": "deeplabcut", "files": "{stem}DLC_*.h5"}


def _config(pipeline: dict | None = None, **tables) -> Config:
    data = copy.deepcopy(DEFAULT)
    data["pipeline"] = {**data["pipeline"], **(pipeline or {})}
    for key, value in tables.items():
        data[key] = {**data.get(key, {}), **value}
    return Config.from_dict(data)


def _recordings(root: Path, *ids: str, **fields) -> list[Recording]:
    return [
        Recording(id=i, path=root / i, sources={}, outdir=root / i / "out", **fields) for i in ids
    ]


def _plan(root: Path, *ids: str, pipeline: dict | None = None, **tables) -> RunPlan:
    return RunPlan(_config(pipeline, **tables), _recordings(root, *ids), main_process=False)


def _w(outdir) -> SimpleNamespace:
    return SimpleNamespace(outdir=str(outdir))


def test_a_recording_is_looked_up_by_its_output_folder_and_other_folders_are_unplanned(tmp_path):
    plan = _plan(tmp_path, "a", "b")
    outdir = tmp_path / "b" / "out"
    assert plan.recording(_w(outdir)).id == "b"
    assert plan.unplanned(_w(outdir)) == []
    other = tmp_path / "elsewhere"
    assert plan.unplanned(_w(other)) == [
        f"{other} (no recording of this run writes to this folder)"
    ]
    assert plan.calibration_inputs(_w(other)) == plan.unplanned(_w(other))
    with pytest.raises(ConfigError, match="is not the output folder of any recording"):
        plan.recording(_w(other))


def test_the_rig_artifact_is_the_recordings_own_without_sessions_and_the_sessions_with(tmp_path):
    own = _plan(tmp_path, "a", "b")
    outdir = tmp_path / "a" / "out"
    assert own.sessions == []
    assert own.rig_artifact(_w(outdir)) == f"{outdir}/stages/bundle_adjustment.h5"

    shared = _plan(tmp_path, "a", "b", bundle_adjustment={"session": True})
    assert [s.ids for s in shared.sessions] == [["a", "b"]]
    session = shared.sessions[0]
    assert shared.rig_artifact(_w(outdir)) == str(session.artifact)
    assert shared.session(SimpleNamespace(sessiondir=str(session.outdir))) is session
    # a folder no recording writes keeps the pattern (its job is dropped as unplanned)
    other = tmp_path / "x"
    assert shared.rig_artifact(_w(other)) == f"{other}/stages/bundle_adjustment.h5"
    assert shared.session_unplanned(SimpleNamespace(sessiondir=str(outdir)))
    assert str(session.summary) in shared.targets()


def test_session_calibration_without_bundle_adjustment_plans_no_session_and_warns(tmp_path):
    config = _config({"do_bundle_adjustment": False}, bundle_adjustment={"session": True})
    recordings = _recordings(tmp_path, "a", "b")
    assert RunPlan(config, recordings, main_process=False).warnings == []  # a job: no warning
    plan = RunPlan(config, recordings, main_process=True)
    assert plan.sessions == []
    assert any("do_bundle_adjustment is false" in line for line in plan.warnings)


def test_reconstruction_inputs_follow_the_stage_flags(tmp_path):
    outdir = tmp_path / "a" / "out"
    stages = f"{outdir}/stages"
    plan = _plan(tmp_path, "a")
    assert plan.reconstruction_inputs("triangulation")(_w(outdir)) == {
        "pose2d": f"{stages}/pose2d.h5",
        "bundle_adjustment": f"{stages}/bundle_adjustment.h5",
    }
    refinement = plan.refinement_inputs(_w(outdir))
    assert refinement["triangulation"] == f"{stages}/triangulation.h5"
    assert "pictorial_structures" not in refinement

    plan = _plan(tmp_path, "a", pipeline={"do_bundle_adjustment": False})
    # the config rig: an orbit rig reads no file, but the key is there
    assert plan.reconstruction_inputs("triangulation")(_w(outdir)) == {
        "pose2d": f"{stages}/pose2d.h5",
        "calibration": [],
    }

    plan = _plan(tmp_path, "a", pipeline={"do_pictorial_structures": True})
    k = plan.config.pictorial_structures.k
    assert plan.reconstruction_inputs("pictorial_structures")(_w(outdir))["candidates"] == (
        f"{stages}/candidates_k{k}.h5"
    )
    triangulation = plan.reconstruction_inputs("triangulation")(_w(outdir))
    assert triangulation["pictorial_structures"] == f"{stages}/pictorial_structures.h5"
    assert plan.pose2d_outputs() == {
        "out": "{outdir}/stages/pose2d.h5",
        "candidates_out": f"{{outdir}}/stages/candidates_k{k}.h5",
    }


def test_a_calibration_file_is_an_input_of_the_config_rig(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text("")
    plan = _plan(
        tmp_path,
        "a",
        pipeline={"do_bundle_adjustment": False},
        calibration={"file": str(rig), "format": "anipose"},
    )
    outdir = tmp_path / "a" / "out"
    assert plan.calibration_inputs(_w(outdir)) == [str(rig)]
    assert plan.recording_calibration(tmp_path / "a") == (str(rig),)


def test_without_pose2d_a_recording_missing_its_2d_is_skipped_and_warned_about(tmp_path):
    recordings = _recordings(tmp_path, "has2d", "none")
    stages = recordings[0].outdir / "stages"
    stages.mkdir(parents=True)
    (stages / "pose2d.h5").write_bytes(b"")
    plan = RunPlan(_config({"do_pose2d": False}), recordings, main_process=False)
    assert plan.skipped == {"none"}
    assert [r.id for r in plan.planned] == ["has2d"]
    assert len(plan.warnings) == 1 and plan.warnings[0].startswith("none: pipeline.do_pose2d")
    assert all("/none/" not in t for t in plan.targets())
    # pictorial structures also needs the detector's candidates, which imported 2D lacks
    plan = RunPlan(
        _config({"do_pose2d": False, "do_pictorial_structures": True}),
        recordings,
        main_process=False,
    )
    assert plan.skipped == {"has2d", "none"}
    assert "candidates_k" in plan.warnings[0] and plan.targets() == []
    # with pose2d on nothing is skipped
    assert RunPlan(_config(), recordings, main_process=False).skipped == set()


def test_targets_follow_the_stage_flags(tmp_path):
    out = tmp_path / "a" / "out"
    plan = _plan(tmp_path, "a")
    targets = plan.targets()
    assert f"{out}/results.h5" in targets and f"{out}/angles.csv" in targets
    assert {f"{out}/{name}.mp4" for name in plan.video_names} <= set(targets)
    assert plan.video_names and f"{out}/joint_angles.csv" not in targets
    plan = _plan(
        tmp_path,
        "a",
        pipeline={"do_visualization": False, "do_kinematics": False, "do_neuromechfly": True},
    )
    targets = plan.targets()
    assert plan.video_names == [] and not any(t.endswith(".mp4") for t in targets)
    assert f"{out}/angles.csv" not in targets and f"{out}/joint_angles.csv" in targets


def test_pose2d_needs_a_gpu_and_its_own_group_only_where_the_detector_runs(tmp_path):
    detector = _plan(tmp_path, "a")
    imported = RunPlan(_config(), _recordings(tmp_path, "a", import_spec=IMPORT))
    from_config = _plan(tmp_path, "a", pose2d={"import": IMPORT})
    w = _w(tmp_path / "a" / "out")
    assert (detector.pose2d_gpus(w), detector.pose2d_group(w)) == (1, None)
    assert (detector.pose2d_mem_mb(w), detector.pose2d_runtime(w)) == (8000, 120)
    for plan in (imported, from_config):
        assert (plan.pose2d_gpus(w), plan.pose2d_group(w)) == (0, RECORDING_GROUP)
        assert (plan.pose2d_mem_mb(w), plan.pose2d_runtime(w)) == (2000, 15)
    assert imported.pose2d_import(w) == '{"files": "{stem}DLC_*.h5", "format": "deeplabcut"}'
    assert detector.pose2d_import(w) == "null"


def test_stage_params_are_canonical_json_and_runtime_is_computed_once(tmp_path):
    plan = _plan(tmp_path, "a")
    text = plan.stage_json("triangulation")
    assert text.startswith("{") and '"method"' in text
    assert plan.runtime("pose2d") is plan.runtime("pose2d")


def test_two_demo_recordings_are_one_error(tmp_path):
    with pytest.raises(ConfigError, match="more than one {demo: true} entry"):
        RunPlan(_config(), _recordings(tmp_path, "a", "b", demo=True), main_process=False)
