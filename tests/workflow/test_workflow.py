"""The Snakemake workflow, driven through its CLI on tiny synthetic recordings.

One real run of two 6-frame recordings (2D imported from DeepLabCut CSVs), then dry
runs after config edits: each edit must schedule exactly the stages it affects, for
exactly the recordings it affects.
"""

from __future__ import annotations

import copy
import json
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from rig_constants import FOCAL
from workflow_run import SNAKEMAKE, snakemake_command

REPO = Path(__file__).resolve().parents[2]

FRAMES = 6

pytestmark = pytest.mark.slow


def base_config() -> dict:
    return yaml.safe_load((REPO / "config" / "config.yaml").read_text())


def snakemake(
    workdir: Path, *args: str, config: dict | None = None, check: bool = True, timeout: float = 600
) -> subprocess.CompletedProcess:
    """Run the repo's workflow in ``workdir`` (with ``config`` written to config.yaml)."""
    if config is not None:
        (workdir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    cmd = snakemake_command(workdir, *args)
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=workdir)
    if check and proc.returncode != 0:
        raise AssertionError(
            f"snakemake failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}"
        )
    return proc


# A job's block, its lines indented past its `rule` line; a cluster job group's members
# (workflow/rules/common.smk) are printed indented within the group's block.
_JOB_PATTERN = r"^( *)(?:local)?rule (\w+):\n((?:\1    .*\n?)*)"


def _jobs(text: str) -> list[tuple[str, str]]:
    """``(rule, body)`` of every job a dry run prints."""
    return [(rule, body) for _, rule, body in re.findall(_JOB_PATTERN, text, re.MULTILINE)]


def planned(workdir: Path, config: dict) -> set[tuple[str, str]]:
    """``(rule, recording directory name)`` of every job a dry run schedules."""
    proc = snakemake(workdir, "--dry-run", config=config)
    jobs = set()
    for rule, body in _jobs(proc.stdout + proc.stderr):
        if rule == "all":
            continue
        match = re.search(r"wildcards: outdir=(\S+)", body)
        jobs.add((rule, Path(match.group(1)).parent.name if match else ""))
    return jobs


def make_recording(config: dict, directory: Path, seed: int) -> dict:
    """A tiny synthetic recording (footage + DLC CSVs); returns its recordings entry."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    cfg = Config.from_dict(config)
    make_demo(cfg, directory, frames=FRAMES, seed=seed)
    return {"path": str(directory), "import": demo_import_spec(cfg)}


def jobs(rules, recordings) -> set[tuple[str, str]]:
    return {(r, rec) for r in rules for rec in recordings}


ALL_STAGES = (
    "pose2d",
    "bundle_adjustment",
    "triangulation",
    "refinement",
    "assemble",
    "visualization",
    "kinematics",
)
#: What a change to the triangulation re-runs (everything after it).
AFTER_TRIANGULATION = ("triangulation", "refinement", "assemble", "visualization", "kinematics")


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A work dir with recordings recA, recB (run once to completion) and recC (not yet listed)."""
    root = tmp_path_factory.mktemp("workflow")
    config = base_config()
    config["bundle_adjustment"]["max_nfev"] = 20
    entries = {
        name: make_recording(config, root / name, seed)
        for seed, name in enumerate(("recA", "recB", "recC"))
    }
    config["recordings"] = [entries["recA"], entries["recB"]]
    proc = snakemake(root, config=config)
    return {"root": root, "config": config, "entries": entries, "run": proc}


def test_run_writes_every_artifact_and_a_byte_for_byte_config_snapshot(workspace):
    from flylib.results import PoseResult

    root = workspace["root"]
    for name in ("recA", "recB"):
        out = root / name / "flylib_outputs"
        result = PoseResult.load(out / "results.h5")
        assert result.pts3d.shape == (FRAMES, 38, 3)
        assert np.isfinite(result.pts3d).mean() > 0.9
        for f in (
            "summary.png",
            "summary.json",
            "calibration.toml",
            "pose2d.mp4",
            "pose3d.mp4",
            "stages/pose2d.h5",
            "stages/bundle_adjustment.h5",
            "stages/triangulation.h5",
            "stages/refinement.h5",
            "kinematics.h5",
            "angles.csv",
            "angles.png",
        ):
            assert (out / f).stat().st_size > 0, f
        assert (out / "config.yaml").read_bytes() == (root / "config.yaml").read_bytes()
        assert (out / "benchmarks" / "triangulation.tsv").is_file()
        assert (out / "logs" / "pose2d.log").is_file()
        summary = json.loads((out / "summary.json").read_text())
        assert summary["frames"] == FRAMES and summary["views"][0] == "rh"
        with h5py.File(out / "results.h5") as f:
            assert {
                "pose2d",
                "bundle_adjustment",
                "triangulation",
                "refinement",
                "skeleton",
            } <= set(f)
    assert not list(root.rglob("*.tmp*")), "a temporary file was left behind"


def test_unchanged_config_plans_nothing(workspace):
    assert planned(workspace["root"], workspace["config"]) == set()


@pytest.mark.parametrize(
    "section,key,value",
    [
        ("pose2d", "batch_size", 3),
        ("pose2d", "decode_buffer", 9),
        ("io", "image", {"workers": 3}),
    ],
)
def test_performance_knobs_plan_nothing(workspace, section, key, value):
    config = copy.deepcopy(workspace["config"])
    config[section][key] = value
    assert planned(workspace["root"], config) == set()


def test_triangulation_threshold_reruns_triangulation_and_downstream_only(workspace):
    config = copy.deepcopy(workspace["config"])
    config["triangulation"]["ransac_threshold"] = 9.5
    expected = jobs(AFTER_TRIANGULATION, ("recA", "recB"))
    assert planned(workspace["root"], config) == expected


def test_refinement_weight_reruns_refinement_and_downstream_only(workspace):
    config = copy.deepcopy(workspace["config"])
    config["refinement"]["smooth_weight"] = 0.5
    expected = jobs(("refinement", "assemble", "visualization", "kinematics"), ("recA", "recB"))
    assert planned(workspace["root"], config) == expected


def test_angle_table_edit_reruns_kinematics_only(workspace):
    config = copy.deepcopy(workspace["config"])
    config["kinematics"]["angles"] = {
        "lf_knee": ["lf_coxa_trochanter", "lf_femur_tibia", "lf_tibia_tarsus"]
    }
    assert planned(workspace["root"], config) == jobs(("kinematics",), ("recA", "recB"))


def test_rig_edit_reruns_bundle_adjustment_and_after_but_not_pose2d(workspace):
    config = copy.deepcopy(workspace["config"])
    config["cameras"]["defaults"]["distance"] = 107.0
    expected = jobs(("bundle_adjustment", *AFTER_TRIANGULATION), ("recA", "recB"))
    assert planned(workspace["root"], config) == expected


def test_skeleton_edit_reruns_bundle_adjustment_and_after(workspace):
    config = copy.deepcopy(workspace["config"])
    limbs = config["skeleton"]["limb_points"]
    limbs["l_abdomen"] = limbs["l_abdomen"][:2]
    limbs["l_abdomen_tip"] = ["l_abdomen2"]
    planned_jobs = planned(workspace["root"], config)
    assert ("pose2d", "recA") not in planned_jobs
    assert (
        jobs(("bundle_adjustment", "triangulation", "assemble"), ("recA", "recB")) <= planned_jobs
    )


def test_new_recording_plans_only_its_own_jobs(workspace):
    config = copy.deepcopy(workspace["config"])
    config["recordings"].append(workspace["entries"]["recC"])
    assert planned(workspace["root"], config) == jobs(ALL_STAGES, ("recC",))


def test_stage_toggles_shape_the_dag(workspace):
    root, base = workspace["root"], workspace["config"]
    config = copy.deepcopy(base)
    config["pipeline"]["do_bundle_adjustment"] = False
    plan = planned(root, config)
    assert not any(rule == "bundle_adjustment" for rule, _ in plan)
    assert jobs(AFTER_TRIANGULATION, ("recA", "recB")) == plan

    config = copy.deepcopy(base)
    config["pipeline"]["do_pose2d"] = False  # reconstruct from the existing 2D artifact
    assert planned(root, config) == set()

    config = copy.deepcopy(base)
    config["pipeline"]["do_visualization"] = False
    assert planned(root, config) == set()

    config = copy.deepcopy(base)
    config["pipeline"]["do_pictorial_structures"] = True  # pose2d re-runs once, for candidates
    plan = planned(root, config)
    assert jobs(("pose2d", "pictorial_structures", "triangulation"), ("recA", "recB")) <= plan


def test_calibration_file_edit_reruns_the_stages_that_read_it(tmp_path):
    from flylib.config import Config
    from flylib.interop.anipose import write_anipose_toml
    from flylib.pipeline.planning import config_rig

    config = base_config()
    config["bundle_adjustment"]["max_nfev"] = 5
    config["pipeline"]["do_visualization"] = False
    config["recordings"] = [make_recording(config, tmp_path / "recA", seed=0)]
    rig_file = tmp_path / "rig.toml"
    cfg = Config.from_dict(config)
    write_anipose_toml(config_rig(cfg, {v: (480, 960) for v in cfg.view_names()}), rig_file)
    config["calibration"] = {"file": str(rig_file), "format": "anipose"}
    snakemake(tmp_path, config=config)
    assert planned(tmp_path, config) == set()

    rig_file.write_text(rig_file.read_text().replace(str(FOCAL), "22400.0", 1))  # re-calibrated
    assert planned(tmp_path, config) == jobs(
        ("bundle_adjustment", "triangulation", "refinement", "assemble", "kinematics"), ("recA",)
    )
    config["pipeline"]["do_bundle_adjustment"] = False  # triangulation reads the file itself
    assert ("triangulation", "recA") in planned(tmp_path, config)
    assert ("pose2d", "recA") not in planned(tmp_path, config)


def test_pictorial_structures_toggle_reruns_detection_only_to_get_candidates(tmp_path):
    """The detector (a random tiny network on the synthetic footage) runs once with PS
    on; turning PS off, and on again, re-runs triangulation and assembly but never the
    detector."""
    import torch

    from flylib.pose2d.model import HourglassNet
    from flylib.pose2d.weights import save_checkpoint
    from flylib.results import load_candidates

    torch.manual_seed(0)
    checkpoint = save_checkpoint(
        HourglassNet(num_stacks=1, num_feats=8, inplanes=8), tmp_path / "sh1_random.tar"
    )
    config = base_config()
    config["pose2d"]["models"][0].update(weights=str(checkpoint), input_size=[64, 128])
    config["pose2d"]["device"] = "cpu"
    config["bundle_adjustment"]["max_nfev"] = 5
    config["pipeline"].update(do_pictorial_structures=True, do_visualization=False)
    entry = make_recording(config, tmp_path / "recA", seed=0)
    config["recordings"] = [{"path": entry["path"]}]  # footage only: the detector runs
    snakemake(tmp_path, config=config)
    stages = tmp_path / "recA" / "flylib_outputs" / "stages"
    assert load_candidates(stages / "candidates_k5.h5").xy.shape == (7, FRAMES, 38, 5, 2)
    assert (stages / "pictorial_structures.h5").is_file()

    off = copy.deepcopy(config)
    off["pipeline"]["do_pictorial_structures"] = False
    assert planned(tmp_path, off) == jobs(
        ("triangulation", "refinement", "assemble", "kinematics"), ("recA",)
    )
    snakemake(tmp_path, config=off)
    # back on: the earlier pictorial-structures artifact is still valid, only its users re-run
    assert planned(tmp_path, config) == jobs(
        ("triangulation", "refinement", "assemble", "kinematics"), ("recA",)
    )
    # k: no detection while PS is off; while on, the detector must find k peaks again
    off["pictorial_structures"]["k"] = 3
    assert planned(tmp_path, off) == set()
    config["pictorial_structures"]["k"] = 3
    assert {("pose2d", "recA"), ("pictorial_structures", "recA")} <= planned(tmp_path, config)


def test_reconstructing_without_pose2d_skips_recordings_missing_their_2d(workspace):
    config = copy.deepcopy(workspace["config"])
    config["pipeline"].update(do_pose2d=False, do_pictorial_structures=True)
    proc = snakemake(workspace["root"], "--dry-run", config=config)
    text = proc.stdout + proc.stderr
    for name in ("recA", "recB"):  # 2D exists, candidates do not (imported 2D keeps none)
        assert f"{name}/flylib_outputs/stages/candidates_k5.h5 missing; skipping" in text
    assert [rule for rule, _ in _jobs(text) if rule != "all"] == []  # nothing to run


def test_report_holds_every_recordings_figure_and_videos(workspace):
    root = workspace["root"]
    snakemake(root, "--report", str(root / "report.zip"), config=workspace["config"])
    import zipfile

    report = zipfile.ZipFile(root / "report.zip")
    names = report.namelist()
    for f in ("summary.png", "angles.png", "pose2d.mp4", "pose3d.mp4"):
        assert sum(n.endswith(f"/{f}") for n in names) == 2, f  # one per recording
    html = report.read(next(n for n in names if n.endswith(".html"))).decode()
    assert "recA/flylib_outputs" in html and "recB/flylib_outputs" in html


def test_lint_is_clean():
    proc = subprocess.run(
        [str(SNAKEMAKE), "--snakefile", str(REPO / "Snakefile"), "--lint"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Congratulations" in proc.stdout + proc.stderr


def test_failing_job_leaves_no_artifact_and_keep_going_finishes_the_rest(tmp_path):
    config = base_config()
    config["pipeline"].update(do_visualization=False, do_bundle_adjustment=False)
    good = make_recording(config, tmp_path / "good", 0)
    bad = make_recording(config, tmp_path / "bad", 1)
    csv = tmp_path / "bad" / bad["import"]["files"]["rm"]
    original = csv.read_bytes()
    csv.write_text("not,a\ndeeplabcut,file\n")
    config["recordings"] = [good, bad]
    proc = snakemake(tmp_path, "--keep-going", config=config, check=False)
    assert proc.returncode != 0
    assert (tmp_path / "good" / "flylib_outputs" / "results.h5").is_file()
    assert not (tmp_path / "bad" / "flylib_outputs" / "stages" / "pose2d.h5").exists()
    assert csv.name in (tmp_path / "bad" / "flylib_outputs" / "logs" / "pose2d.log").read_text()

    csv.write_bytes(original)
    assert planned(tmp_path, config) == jobs(
        ("pose2d", "triangulation", "refinement", "assemble", "kinematics"), ("bad",)
    )


def test_bad_footage_fails_pose2d_naming_the_file(tmp_path):
    from flylib.pose2d.model import HourglassNet
    from flylib.pose2d.weights import save_checkpoint

    checkpoint = save_checkpoint(
        HourglassNet(num_stacks=1, num_feats=8, inplanes=8), tmp_path / "w.tar"
    )
    config = base_config()
    # a checkpoint, or validation stops the run before the job (no weights, no network)
    config["pose2d"]["models"][0].update(weights=str(checkpoint), input_size=[64, 128])
    config["pipeline"]["do_visualization"] = False
    rec = tmp_path / "broken"
    make_recording(config, rec, 0)
    (rec / "camera_3.mp4").write_bytes(b"this is not a video")
    config["recordings"] = [str(rec)]  # detector path: footage is decoded
    proc = snakemake(tmp_path, config=config, check=False)
    assert proc.returncode != 0
    log = (rec / "flylib_outputs" / "logs" / "pose2d.log").read_text()
    assert "camera_3.mp4" in log.strip().splitlines()[-1]
    assert not (rec / "flylib_outputs" / "stages" / "pose2d.h5").exists()


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda c: c["triangulation"].update(method="magic"), "triangulation.method"),
        # a video panel is checked before any job, not when the visualization job starts
        (
            lambda c: c["visualization"]["videos"][0]["panels"][0].update(view="nope"),
            "panels[0].view: 'nope'",
        ),
    ],
)
def test_invalid_config_is_one_clear_error_before_any_job(tmp_path, edit, message):
    config = base_config()
    edit(config)
    proc = snakemake(tmp_path, "--dry-run", config=config, check=False)
    assert proc.returncode != 0
    assert message in proc.stdout + proc.stderr
    assert not (tmp_path / "demo").exists()


def test_workflow_accepts_what_flylib_accepts(tmp_path):
    config = base_config()
    config["recordings"] = [{"demo": True}]  # no path: the demo's default folder
    config["visualization"]["background"] = [20, 20, 20]
    config["visualization"]["videos"][0]["name"] = config["visualization"]["videos"][0].pop(
        "video_name"
    )
    snakemake(tmp_path, "--dry-run", config=config)


def test_empty_batch_is_one_clear_error(tmp_path):
    config = base_config()
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    config["recordings"] = [str(tmp_path / "a"), str(tmp_path / "b")]
    proc = snakemake(tmp_path, "--dry-run", config=config, check=False)
    assert proc.returncode != 0
    assert "no valid recording" in (proc.stdout + proc.stderr).lower() or "none of" in (
        proc.stdout + proc.stderr
    )


@pytest.mark.shared
def test_batch_of_the_two_real_recordings(
    tmp_path, df3d_sample_dir, df3d_pickle, deeperfly_example_dir
):
    """deepfly3d-sample with DeepFly3D's own 2D imported; deeperfly-example through the
    detector with a randomly initialised network saved in the published checkpoint
    format (its keypoints are meaningless, but every stage runs on real footage)."""
    import torch

    from flylib.pose2d.model import HourglassNet
    from flylib.pose2d.weights import save_checkpoint
    from flylib.results import PoseResult

    torch.manual_seed(0)
    checkpoint = save_checkpoint(
        HourglassNet(num_stacks=1, num_feats=8, inplanes=8), tmp_path / "sh1_random.tar"
    )
    config = base_config()
    model = config["pose2d"]["models"][0]
    model.update(weights=str(checkpoint), input_size=[64, 128])
    config["pose2d"].update(device="cpu", batch_size=16)
    config["bundle_adjustment"]["max_nfev"] = 10
    config["recordings"] = [
        {
            "path": str(df3d_sample_dir),
            "import": {"format": "deepfly3d", "files": df3d_pickle.name},
        },
        {"path": str(deeperfly_example_dir)},
    ]
    config["outdir"] = str(tmp_path / "out" / "{id}")  # the shared data is read-only
    snakemake(tmp_path, config=config)
    for name, frames in (("deepfly3d-sample", 15), ("deeperfly-example", 64)):
        out = tmp_path / "out" / name
        result = PoseResult.load(out / "results.h5")
        assert result.pts2d.shape == (7, frames, 38, 2)
        assert result.pts3d.shape == (frames, 38, 3)
        assert (out / "pose3d.mp4").stat().st_size > 0 and (out / "summary.png").is_file()
    imported = PoseResult.load(tmp_path / "out" / "deepfly3d-sample" / "results.h5")
    assert np.isfinite(imported.pts3d).mean() > 0.5


@pytest.mark.parametrize(
    "script",
    [
        "demo",
        "pose2d",
        "bundle_adjustment",
        "pictorial_structures",
        "triangulation",
        "refinement",
        "assemble",
        "visualization",
        "kinematics",
    ],
)
def test_stage_scripts_have_help(script):
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / f"{script}.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0 and "--config" in proc.stdout


def test_stage_script_reports_a_missing_artifact_in_one_line(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "scripts" / "triangulation.py"),
            "--config",
            str(REPO / "config" / "config.yaml"),
            "--pose2d",
            str(tmp_path / "missing.h5"),
            "--out",
            str(tmp_path / "t.h5"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and "missing.h5" in last
    assert not (tmp_path / "t.h5").exists()
