"""What a new user trips over, caught at validation (before the DAG) with one line
that names the key and the fix: detector weights neither present nor
downloadable, an import spec whose files do not exist, misspelled keys."""

from __future__ import annotations

import copy
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml
from conftest import checkpoint_layout

from flylib.config import Config, validate_config
from flylib.pipeline.preflight import preflight_problems
from flylib.pose2d import published
from flylib.recordings import Recording

REPO = Path(__file__).resolve().parents[2]
CLOSED_PORT_URL = "http://127.0.0.1:9/sh8.tar"  # the discard port: refused at once


@pytest.fixture(scope="module")
def default_data() -> dict:
    return Config.default().data


def detector_recording(path: Path, spec: dict | None = None) -> Recording:
    """A planned recording (the detector's when ``spec`` is None, else its own import)."""
    return Recording(
        id="rec",
        path=path,
        sources={"vid_rh": [path]},
        outdir=path / "out",
        import_spec=spec,
        extra={"where": "recordings[0]", "own_import": spec is not None},
    )


def with_model_url(data: dict, url: str) -> Config:
    data = copy.deepcopy(data)
    data["pose2d"]["models"][0]["url"] = url
    return Config.from_dict(data)


# -- 1. the detector's checkpoint -----------------------------------------------------


def test_a_checkpoint_neither_cached_nor_downloadable_is_one_line_naming_model_and_place(
    default_data, tmp_path, monkeypatch
):
    cache = tmp_path / "cache"
    monkeypatch.setenv("FLYLIB_CACHE", str(cache))
    config = with_model_url(default_data, CLOSED_PORT_URL)
    problems = preflight_problems(config, [detector_recording(tmp_path)], config.stage_flags())
    assert len(problems) == 1, problems
    line = problems[0]
    assert line.startswith(
        "pose2d.models.deepfly2d.weights: model 'deepfly2d' needs its checkpoint"
    )
    assert f"put it at {cache / 'sh8_deepfly.tar'}" in line
    assert CLOSED_PORT_URL in line and "pose2d.weights: {deepfly2d:" in line
    # the same file in the cache, or a local path in pose2d.weights: valid
    cache.mkdir()
    checkpoint_layout(cache / "sh8_deepfly.tar")
    assert preflight_problems(config, [detector_recording(tmp_path)], config.stage_flags()) == []


def test_a_cluster_job_rereading_the_config_does_not_probe_again(
    default_data, tmp_path, monkeypatch
):
    """The main process checked the checkpoints; a compute node may have no network."""
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    config = with_model_url(default_data, CLOSED_PORT_URL)
    flags = config.stage_flags()
    rec = detector_recording(tmp_path)
    assert preflight_problems(config, [rec], flags, check_weights=False) == []
    assert preflight_problems(config, [rec], flags) != []


def test_a_reachable_weights_host_counts_as_downloadable(default_data, tmp_path, monkeypatch):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        url = f"http://127.0.0.1:{server.getsockname()[1]}/sh8.tar"
        config = with_model_url(default_data, url)
        flags = config.stage_flags()
        assert preflight_problems(config, [detector_recording(tmp_path)], flags) == []


def test_a_silent_network_is_given_up_on_after_the_timeout(monkeypatch):
    never = threading.Event()

    def black_hole(address, timeout=None):  # a name lookup or SYN that is never answered
        never.wait()

    monkeypatch.setattr(published.socket, "create_connection", black_hole)
    reachable, why = published.host_reachable("https://weights.example.org/x.tar", timeout=0.2)
    assert not reachable and why == "no answer from weights.example.org within 0.2 s"


def test_imported_2d_needs_no_checkpoint(default_data, tmp_path, monkeypatch):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    config = with_model_url(default_data, CLOSED_PORT_URL)
    (tmp_path / "df3d_result_2d.pkl").write_bytes(b"x")
    rec = detector_recording(tmp_path, {"format": "deepfly3d", "image_size": [480, 960]})
    assert preflight_problems(config, [rec], config.stage_flags()) == []


def test_check_config_reports_the_missing_checkpoint(df3d_sample_dir, tmp_path):
    mine = tmp_path / "my.yaml"
    mine.write_text(
        yaml.safe_dump(
            {"recordings": [str(df3d_sample_dir)], "pose2d": {"weights": {"deepfly2d": ""}}}
        )
    )
    env = {"FLYLIB_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    data = copy.deepcopy(Config.default().data)
    data["pose2d"]["models"][0]["url"] = CLOSED_PORT_URL
    base = tmp_path / "base.yaml"
    base.write_text(yaml.safe_dump(data, sort_keys=False))
    proc = subprocess.run(
        [sys.executable, "-m", "flylib.cli", "check-config", str(base), str(mine)],
        capture_output=True,
        text=True,
        env={**env, "PYTHONPATH": str(REPO / "src")},
        timeout=120,
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "pose2d.weights.deepfly2d: model 'deepfly2d' needs its checkpoint" in lines[0]
    assert "sh8_deepfly.tar" in lines[0]


# -- 5. import files and misspelled keys --------------------------------------------


def test_an_import_file_that_does_not_exist_is_caught_with_the_closest_existing_name(
    default_data, tmp_path
):
    """The README's own df3d_result.pkl where DeepFly3D writes df3d_result_2d.pkl."""
    config = Config.from_dict(default_data)
    (tmp_path / "df3d_result_2d.pkl").write_bytes(b"x")
    (tmp_path / "camera_0.mp4").write_bytes(b"x")
    rec = detector_recording(tmp_path, {"format": "deepfly3d", "files": "df3d_result.pkl"})
    problems = preflight_problems(config, [rec], config.stage_flags())
    assert len(problems) == 1, problems
    assert problems[0].startswith("recordings[0].import.files: ")
    assert "no file matches 'df3d_result.pkl'" in problems[0]
    assert "did you mean 'df3d_result_2d.pkl'?" in problems[0]
    rec = detector_recording(tmp_path, {"format": "dlc_csv", "files": "{view}_dlc.csv"})
    (problem,) = preflight_problems(config, [rec], config.stage_flags())
    assert "no file matches 'rh_dlc.csv' for view 'rh'" in problem
    assert "did you mean" not in problem  # nothing there is named like it


def test_the_real_sample_with_the_readme_file_name(df3d_sample_dir, default_data):
    config = Config.from_dict(default_data)
    rec = detector_recording(df3d_sample_dir, {"format": "deepfly3d", "files": "df3d_result.pkl"})
    (problem,) = preflight_problems(config, [rec], config.stage_flags())
    assert "did you mean 'df3d_result_2d.pkl'?" in problem
    rec = detector_recording(
        df3d_sample_dir, {"format": "deepfly3d", "files": "df3d_result_2d.pkl"}
    )
    assert preflight_problems(config, [rec], config.stage_flags()) == []


@pytest.mark.parametrize(
    ("key", "table", "hint"),
    [
        ("triangulaton", {"triangulaton": {}}, "did you mean 'triangulation'?"),
        ("triangulation.methd", {"triangulation": {"methd": "dlt"}}, "did you mean 'method'?"),
        ("pipeline.do_refinment", {"pipeline": {"do_refinment": True}}, "'do_refinement'"),
        (
            "bundle_adjustment.max_frame",
            {"bundle_adjustment": {"max_frame": 3}},
            "did you mean 'max_frames'?",
        ),
        ("kinematics.tetherd", {"kinematics": {"tetherd": True}}, "did you mean 'tethered'?"),
        ("refinement.scale_pix", {"refinement": {"scale_pix": 2}}, "did you mean 'scale_px'?"),
    ],
)
def test_a_misspelled_key_gets_a_did_you_mean(default_data, key, table, hint):
    data = copy.deepcopy(default_data)
    for name, value in table.items():
        data[name] = {**(data.get(name) or {}), **value}
    problems = [p for p in validate_config(data) if p.startswith(key + ":")]
    assert len(problems) == 1 and hint in problems[0], validate_config(data)


def test_a_key_like_no_known_one_gets_no_guess(default_data):
    data = {**copy.deepcopy(default_data), "zzz_qqq": {}}
    (problem,) = validate_config(data)
    assert problem.startswith("zzz_qqq: unknown top-level table; (known:")


# -- 4. the workflow run from another directory -------------------------------------


def _snakemake(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    from workflow_run import SNAKEMAKE

    return subprocess.run(
        [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "-n", "--cores", "1", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env={
            "PYTHONPATH": str(REPO / "src"),
            "PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin",
        },
        timeout=300,
    )


@pytest.mark.slow  # runs Snakemake
def test_snakefile_from_another_directory_finds_its_default_config(tmp_path):
    proc = _snakemake(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "demo" in proc.stdout  # the default config's demo recording, planned under tmp_path
    assert not list(tmp_path.iterdir()) or {p.name for p in tmp_path.iterdir()} <= {".snakemake"}


@pytest.mark.slow  # runs Snakemake
def test_workflow_config_errors_are_the_lines_alone(tmp_path):
    (tmp_path / "my.yaml").write_text("triangulation: {methd: dlt}\n")
    proc = _snakemake(tmp_path, "--configfile", "my.yaml")
    assert proc.returncode == 1
    tail = proc.stderr.strip().splitlines()
    assert tail[-1] == (
        "invalid config: my.yaml: triangulation.methd: unknown parameter; did you mean 'method'? (known: method,"
        " weigh_by_confidence, ransac_threshold, min_inliers, reproj_threshold, max_drops)"
    ), proc.stderr
    assert "WorkflowError" not in proc.stderr and "Traceback" not in proc.stderr
    assert 'File "' not in proc.stderr


@pytest.mark.slow  # runs Snakemake
def test_an_infinite_scale_is_refused_before_the_dag_naming_the_key(tmp_path):
    (tmp_path / "my.yaml").write_text("refinement:\n  scale_px: .inf\n")
    proc = _snakemake(tmp_path, "--configfile", "my.yaml")
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1] == (
        "invalid config: my.yaml: refinement.scale_px: expected a finite number (.inf is "
        "accepted only by refinement.outlier_px), got inf"
    ), proc.stderr
    assert "Traceback" not in proc.stderr
