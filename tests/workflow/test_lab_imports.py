"""A lab's own files through the workflow as a user runs it: ``snakemake --configfile
my.yaml`` merged over the checkout's config (issue 36: 1, 2, 3, 8, 9).

- DeepFly3D 1.x's package example (2D for all 38 points in every camera, its
  ``calib.pkl``, no footage): the front camera's 24 points that DeepFly3D's own
  detection plan never gives it are left missing, so no camera looks mis-calibrated.
- A camera's footage missing: named before the DAG, with the fix.
- A relative recording path: looked up from the working directory, the message says
  where it looked.
- A typo inside ``pose2d.import``, a junk weights file, a glob matching nothing: one line
  each, before the DAG.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from workflow_run import REPO, SNAKEMAKE

pytestmark = pytest.mark.slow

FLYLIB = Path(sys.executable).parent / "flylib"


def snakemake(workdir: Path, mine: dict, *args: str) -> subprocess.CompletedProcess:
    """``snakemake --configfile my.yaml`` in ``workdir``: the user's file over the
    checkout's config/config.yaml (the Snakefile's ``configfile:``)."""
    (workdir / "my.yaml").write_text(yaml.safe_dump(mine, sort_keys=False))
    command = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--configfile", "my.yaml"]
    return subprocess.run(
        [*command, "--cores", "2", *args],
        capture_output=True,
        text=True,
        timeout=900,
        cwd=workdir,
        check=False,
    )


def check_config(workdir: Path) -> subprocess.CompletedProcess:
    """``flylib check-config my.yaml`` in ``workdir`` (the file :func:`snakemake` wrote)."""
    return subprocess.run(
        [str(FLYLIB), "check-config", "my.yaml"],
        capture_output=True,
        text=True,
        cwd=workdir,
        check=False,
    )


def refused(proc: subprocess.CompletedProcess) -> str:
    """The one line a run refused before its DAG printed (stderr's last line)."""
    assert proc.returncode != 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    for noise in ("Traceback", "WildcardError", 'File "', "Building DAG"):
        assert noise not in proc.stderr, proc.stderr[-3000:]
    return proc.stderr.strip().splitlines()[-1]


# -- 2. DeepFly3D 1.x: the detection plan's points per view -----------------------------


def package_example_config(example: Path, outdir: Path, **spec) -> dict:
    return {
        "recordings": [str(example)],
        "outdir": str(outdir),
        "pose2d": {"import": {"format": "deepfly3d", "image_size": [480, 960], **spec}},
        # its world is the fly's mirror image: run as it is (what these tests measure)
        "calibration": {"file": "calib.pkl", "format": "deepfly3d", "mirror": False},
        "pipeline": {"do_visualization": False, "do_kinematics": False},
    }


def front_held_out(outdir: Path) -> tuple[dict, int]:
    """The front camera's triangulation held-out error and the suspect count."""
    summary = json.loads((outdir / "summary.json").read_text())
    with open(outdir / "suspects.csv", newline="") as f:
        n_suspects = len(list(csv.reader(f))) - 1
    return summary["accuracy"]["triangulation"]["per_view"]["f"], n_suspects


def test_deepfly3d_package_example_front_camera_keeps_only_its_planned_points(
    df3d_package_example_dir, tmp_path
):
    """DeepFly3D's own 3D reprojects 3.1 px from the front camera's 14 planned points and
    156 px from the other 24: imported as they are, the front camera looked
    mis-calibrated (held-out median 64 px, 319 of 570 pairs suspect)."""
    outdir = tmp_path / "out"
    proc = snakemake(tmp_path, package_example_config(df3d_package_example_dir, outdir))
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    front, n_suspects = front_held_out(outdir)
    assert front["median"] < 10 and front["p95"] < 40, front
    assert front["n"] == 14 * 15  # 14 planned points x 15 frames
    assert n_suspects < 100
    assert "mis-calibrated or mislabeled" not in log
    assert (
        f"{df3d_package_example_dir / 'df3d_result.pkl'}: holds 2D for points the detection "
        "plan does not give their view: view 'rf' 3 (r_abdomen0, r_abdomen1, r_abdomen2); "
        "view 'f' 24 (lf_thorax_coxa, lf_coxa_trochanter, lm_thorax_coxa, lm_coxa_trochanter "
        "and 20 more); view 'lf' 3 (l_abdomen0, l_abdomen1, l_abdomen2); they are left "
        "missing, as the detector would leave them (set pose2d.import.view_points: all to "
        "keep them)"
    ) in log

    # the documented switch keeps every point the file holds: the junk comes back
    outdir = tmp_path / "all"
    mine = package_example_config(df3d_package_example_dir, outdir, view_points="all")
    proc = snakemake(tmp_path, mine)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    front, n_suspects = front_held_out(outdir)
    assert front["median"] > 30 and front["n"] == 38 * 15
    assert "Cameras f" in log and "mis-calibrated or mislabeled" in log
    assert "detection plan does not give" not in log


# -- 1. every documented placeholder of a top-level import pattern -------------------------


@pytest.fixture(scope="module")
def dlc_recording(tmp_path_factory) -> Path:
    """A 4-frame synthetic recording with each view's DeepLabCut CSV under the names each
    placeholder gives: ``camera_{index}DLC_x.csv`` (= ``{stem}DLC_x.csv``),
    ``{view}_view.csv`` and ``{source}_source.csv``."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    root = tmp_path_factory.mktemp("dlc") / "rec"
    config = Config.default()
    make_demo(config, root, frames=4, seed=0)
    for index, (view, name) in enumerate(demo_import_spec(config)["files"].items()):
        for copy in (f"camera_{index}DLC_x.csv", f"{view}_view.csv", f"vid_{view}_source.csv"):
            shutil.copy(root / name, root / copy)
        (root / name).unlink()
    return root


@pytest.mark.parametrize(
    "files",
    ["camera_{index}DLC_x.csv", "{stem}DLC_x.csv", "{view}_view.csv", "{source}_source.csv"],
)
def test_a_top_level_import_pattern_plans_the_run_and_check_config_agrees(
    dlc_recording, tmp_path, files
):
    mine = {
        "recordings": [str(dlc_recording)],
        "outdir": str(tmp_path / "out"),
        "pose2d": {"import": {"format": "dlc_csv", "files": files}},
    }
    proc = snakemake(tmp_path, mine, "--dry-run")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "WildcardError" not in proc.stdout + proc.stderr
    assert "rule pose2d:" in proc.stdout
    check = check_config(tmp_path)
    assert check.returncode == 0, check.stderr
    assert check.stdout.startswith("my.yaml over the default config: valid; 1 recording(s)")


# -- 3. a camera's footage missing; imported 2D without footage ------------------------------


def test_a_missing_camera_file_is_named_before_the_dag_and_check_config_says_the_same(
    df3d_sample_dir, tmp_path
):
    recording = tmp_path / "rec"
    recording.mkdir()
    for path in [*df3d_sample_dir.glob("camera_?.mp4"), df3d_sample_dir / "df3d_result_2d.pkl"]:
        if path.name != "camera_6.mp4":
            os.symlink(path, recording / path.name)
    mine = {
        "recordings": [str(recording)],
        "outdir": str(tmp_path / "out"),
        "pose2d": {"import": {"format": "deepfly3d"}},
    }
    line = refused(snakemake(tmp_path, mine, "--dry-run"))
    assert line == (
        f"invalid config: my.yaml: pose2d.import: no footage for view 'lh': no file matches "
        f"{recording / 'camera_6.mp4'}; put the camera's file there (or fix its source's "
        "filename in sources), or, to import its 2D without footage, set "
        "pose2d.import.image_size: [height, width]"
    )
    assert not (tmp_path / "out").exists()
    check = check_config(tmp_path)
    assert check.returncode == 1
    assert check.stderr.strip() == f"flylib check-config: {line}"


def test_imported_2d_without_any_footage_says_how_to_set_image_size(
    df3d_package_example_dir, tmp_path
):
    mine = package_example_config(df3d_package_example_dir, tmp_path / "out")
    del mine["pose2d"]["import"]["image_size"]
    line = refused(snakemake(tmp_path, mine, "--dry-run"))
    assert line == (
        f"invalid config: my.yaml: pose2d.import: no footage for any view in "
        f"{df3d_package_example_dir} to read the frame size from; imported 2D without "
        "footage needs the frames' size in pixels: set pose2d.import.image_size: "
        "[height, width] (e.g. [480, 960])"
    )


# -- 9. a junk weights file --------------------------------------------------------------------


def test_a_junk_weights_file_is_refused_before_the_dag_naming_it(df3d_sample_dir, tmp_path):
    junk = tmp_path / "sh8.tar"
    junk.write_text("<html>Dropbox: this file is no longer available</html>\n")
    mine = {
        "recordings": [str(df3d_sample_dir)],
        "outdir": str(tmp_path / "out"),
        "pose2d": {"weights": {"deepfly2d": str(junk)}},
    }
    line = refused(snakemake(tmp_path, mine, "--dry-run"))
    assert line == (
        f"invalid config: my.yaml: pose2d.weights.deepfly2d: {junk} is not a PyTorch "
        "checkpoint (neither a torch.save zip archive nor torch's legacy format); point it at "
        "the model's checkpoint (a torch.save file holding {'state_dict': ...}, such as "
        "DeepFly2D's sh8 .tar)"
    )
    assert "weights_only" not in line


# -- 8. a recording path relative to the config file's folder ----------------------------------


def test_a_relative_recording_path_is_read_from_the_working_directory_and_says_so(
    dlc_recording, tmp_path
):
    lab = tmp_path / "lab"
    shutil.copytree(dlc_recording, lab / "data" / "fly1")
    mine = {
        "recordings": ["data/fly1"],
        "outdir": "results/{name}",
        "pose2d": {"import": {"format": "dlc_csv", "files": "{stem}DLC_x.csv"}},
        "pipeline": {"do_visualization": False, "do_kinematics": False, "do_refinement": False},
    }
    (lab / "my.yaml").write_text(yaml.safe_dump(mine, sort_keys=False))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    command = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--cores", "2"]
    proc = subprocess.run(
        [*command, "--configfile", str(lab / "my.yaml"), "--dry-run"],
        capture_output=True,
        text=True,
        cwd=elsewhere,
        timeout=600,
        check=False,
    )
    assert refused(proc) == (
        f"invalid config: {lab / 'my.yaml'}: recordings[0]: data/fly1 does not exist in the "
        f"working directory {elsewhere} (relative paths in a config are read from the working "
        "directory, snakemake --directory or where snakemake runs, as Snakemake reads them; "
        "never from the config file's folder); it is in the config file's folder "
        f"({lab / 'data' / 'fly1'}): list it as {lab / 'data' / 'fly1'}, or run from {lab} "
        f"(snakemake --directory {lab})"
    )
    # the fix it names: run from the config file's folder; the result records both paths
    proc = subprocess.run(
        [*command, "--configfile", str(lab / "my.yaml"), "--directory", str(lab)],
        capture_output=True,
        text=True,
        cwd=elsewhere,
        timeout=900,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    from flylib.results import PoseResult

    meta = PoseResult.load(lab / "results" / "fly1" / "results.h5").meta
    assert meta["recording"] == "data/fly1"
    assert meta["recording_abspath"] == str(lab / "data" / "fly1")
    summary = json.loads((lab / "results" / "fly1" / "summary.json").read_text())
    assert summary["recording_abspath"] == str(lab / "data" / "fly1")


# -- 9. a glob matching nothing ----------------------------------------------------------------


def test_a_recordings_pattern_matching_nothing_is_said_once(tmp_path):
    mine = {"recordings": [str(tmp_path / "no_such_fly*")]}
    proc = snakemake(tmp_path, mine, "--dry-run")
    line = refused(proc)
    assert line == (
        f"invalid config: my.yaml: recordings[0]: the pattern '{tmp_path / 'no_such_fly*'}' "
        "matches no path; fix the pattern"
    )
    assert (proc.stdout + proc.stderr).count("no_such_fly*") == 1


def test_a_typo_inside_pose2d_import_gets_did_you_mean(dlc_recording, tmp_path):
    mine = {
        "recordings": [str(dlc_recording)],
        "pose2d": {"import": {"fromat": "dlc_csv", "files": "{stem}DLC_x.csv"}},
    }
    assert refused(snakemake(tmp_path, mine, "--dry-run")) == (
        "invalid config: my.yaml: pose2d.import.fromat: unknown key; did you mean 'format'? "
        "(known: files, format, image_size, individual, keypoint_map, likelihood_threshold, "
        "track, view_points, views)"
    )
