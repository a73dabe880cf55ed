"""Imported 2D through the workflow: the import files are inputs of pose2d (an edit
re-runs it and everything after), rows land on the frame their index names, and a
likelihood that is no probability stops the job naming the file (issue 37, 9-11)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml

from workflow_run import snakemake_command

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow

#: The view whose CSV the tests edit, and its position on the V axis.
VIEW, V = "lm", 5


@pytest.fixture(scope="module")
def demo_recording(tmp_path_factory) -> tuple[Path, dict]:
    """A 4-frame synthetic recording with one DeepLabCut CSV per view, and the import
    spec that reads them."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    root = tmp_path_factory.mktemp("imports") / "rec"
    config = Config.from_file(REPO / "config" / "config.yaml")
    make_demo(config, root, frames=4, seed=0)
    return root, demo_import_spec(config)


@pytest.fixture
def work(demo_recording, tmp_path) -> tuple[Path, Path]:
    """A fresh copy of the recording and a workdir whose config imports its 2D."""
    source, spec = demo_recording
    recording = tmp_path / "rec"
    shutil.copytree(source, recording)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["recordings"] = [str(recording)]
    config["outdir"] = str(tmp_path / "out")
    config["pose2d"]["import"] = spec
    config["pipeline"].update(do_visualization=False, do_kinematics=False, do_refinement=False)
    workdir = tmp_path / "work"
    workdir.mkdir()
    (workdir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return recording / spec["files"][VIEW], workdir


def snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        snakemake_command(workdir, *args),
        capture_output=True,
        text=True,
        timeout=600,
        cwd=workdir,
        check=False,
    )


def run(workdir: Path, *args: str) -> str:
    proc = snakemake(workdir, *args)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    return out


def results_2d(workdir: Path) -> np.ndarray:
    """``(V, T, P, 2)`` 2D points in the run's results.h5."""
    config = yaml.safe_load((workdir / "config.yaml").read_text())
    with h5py.File(Path(config["outdir"]) / "results.h5", "r") as f:
        return f["pose2d/points"][()]


def read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path, header=[0, 1, 2], index_col=0)


def test_editing_an_import_file_re_runs_pose2d_and_what_follows(work):
    csv, workdir = work
    run(workdir)
    before = results_2d(workdir)
    assert "Nothing to be done" in run(workdir, "--dry-run")

    frame = read_csv(csv)
    x = [c for c in frame.columns if c[2] == "x"]
    frame[x] += 40.0  # the camera's points moved 40 px
    frame.to_csv(csv)

    planned = run(workdir, "--dry-run")
    assert f"reason: Updated input files: {csv}" in planned
    assert {"pose2d", "triangulation", "assemble"} <= {
        line.split()[-1].rstrip(":") for line in planned.splitlines() if "rule " in line
    }
    run(workdir)
    after = results_2d(workdir)
    seen = np.isfinite(before[V, ..., 0])
    np.testing.assert_allclose(after[V, ..., 0][seen], before[V, ..., 0][seen] + 40.0)
    np.testing.assert_array_equal(np.delete(after, V, axis=0), np.delete(before, V, axis=0))


def test_rows_out_of_frame_order_land_on_the_frame_their_index_names(work):
    csv, workdir = work
    run(workdir)
    ordered = results_2d(workdir)
    shutil.rmtree(workdir.parent / "out")  # a fresh run: nothing of the first one kept
    frame = read_csv(csv)
    frame.iloc[::-1].to_csv(csv)  # rows 3, 2, 1, 0
    run(workdir)
    np.testing.assert_array_equal(results_2d(workdir), ordered)


def test_a_frame_given_twice_stops_pose2d_naming_the_file_and_rows(work):
    csv, workdir = work
    frame = read_csv(csv)
    frame.index = [0, 1, 1, 3]
    frame.to_csv(csv)
    proc = snakemake(workdir)
    assert proc.returncode != 0
    log = (workdir.parent / "out" / "logs" / "pose2d.log").read_text()
    assert f"{csv}: frame 1 is given twice (data rows 2 and 3, index 1 and 1)" in log


def test_a_likelihood_that_is_no_probability_stops_pose2d_naming_the_file(work):
    csv, workdir = work
    frame = read_csv(csv)
    likelihood = [c for c in frame.columns if c[2] == "likelihood"]
    frame.loc[2, likelihood[0]] = 1000.0
    frame.to_csv(csv)
    proc = snakemake(workdir)
    assert proc.returncode != 0
    log = (workdir.parent / "out" / "logs" / "pose2d.log").read_text()
    assert (
        f"{csv}: 1 score outside [0, 1], from 1000 to 1000 (first at frame 2, keypoint "
        f"{likelihood[0][1]!r}); a DeepLabCut / Lightning Pose likelihood is a probability"
    ) in log
