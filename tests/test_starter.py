"""`flylib init DIR`: a starter config from a lab's folder, checked by the workflow itself."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
import yaml

from flylib.cli import main
from flylib.config import Config
from flylib.pipeline.demo import make_demo

from workflow_run import REPO, SNAKEMAKE


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A lab's folder: two trials of the demo's footage and DeepLabCut files (as the demo
    names them: camera_<i>DLC_<scorer>.csv), one folder per trial."""
    root = tmp_path_factory.mktemp("lab")
    demo = make_demo(Config.default(), root / "fly1" / "trial1", frames=4)
    shutil.copytree(demo.directory, root / "fly1" / "trial2")
    return root


def _init(tmp_path, folder, capsys, *extra):
    out = tmp_path / "my.yaml"
    status = main(["init", str(folder), "-o", str(out), *extra])
    return status, out, capsys.readouterr().out


def test_init_writes_a_config_the_workflow_runs(lab, tmp_path, capsys):
    status, out, printed = _init(tmp_path, lab, capsys)
    assert status == 0, printed
    assert "2 recording(s)" in printed and "is valid" in printed
    data = yaml.safe_load(out.read_text())
    assert data["recordings"] == [str(lab / "fly1" / "trial1"), str(lab / "fly1" / "trial2")]
    # one pattern for every view, found from the files' names
    assert data["pose2d"]["import"] == {
        "format": "dlc_csv",
        "files": "camera_{index}DLC_flylibdemo.csv",
    }
    assert "sources" not in data  # the default camera_N.mp4 names matched
    dry = subprocess.run(
        [
            str(SNAKEMAKE),
            "--snakefile",
            str(REPO / "Snakefile"),
            "--directory",
            str(tmp_path),
            "--configfile",
            str(out),
            "-n",
            "--cores",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert dry.returncode == 0, dry.stderr[-3000:]
    assert dry.stdout.count("rule pose2d:") == 2


def test_init_maps_renamed_videos_and_says_to_check_the_order(lab, tmp_path, capsys):
    folder = tmp_path / "renamed"
    folder.mkdir()
    for i in range(7):
        shutil.copy(lab / "fly1" / "trial1" / f"camera_{i}.mp4", folder / f"cam{i}.avi")
    status, out, printed = _init(tmp_path, folder, capsys)
    data = yaml.safe_load(out.read_text())
    names = [s["name"] for s in Config.default().data["sources"]]
    assert data["sources"] == [{"name": n, "filename": f"cam{i}.avi"} for i, n in enumerate(names)]
    assert "check the order" in printed
    assert status == 0, printed  # valid: the detector's weights are checked by the run itself


def test_init_never_replaces_a_file(lab, tmp_path, capsys):
    (tmp_path / "my.yaml").write_text("mine\n")
    status = main(["init", str(lab), "-o", str(tmp_path / "my.yaml")])
    assert status == 1
    assert "already exists" in capsys.readouterr().err
    assert (tmp_path / "my.yaml").read_text() == "mine\n"


def test_init_says_when_it_finds_nothing(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    status, out, printed = _init(tmp_path, tmp_path / "empty", capsys)
    assert "no recording found" in printed
    assert status == 1  # an empty recordings list is no runnable config
    assert yaml.safe_load(out.read_text())["recordings"] == []


def test_init_on_the_deepfly3d_sample(df3d_sample_dir, tmp_path, capsys):
    status, out, printed = _init(tmp_path, df3d_sample_dir, capsys, "--outdir", "df3d/{id}")
    assert status == 0, printed
    data = yaml.safe_load(out.read_text())
    assert data["recordings"] == [str(df3d_sample_dir)]
    assert data["outdir"] == "df3d/{id}"
    assert data["pose2d"]["import"] == {"format": "deepfly3d", "files": "df3d_result_2d.pkl"}


def test_init_on_the_package_example_names_its_calibration_and_the_missing_frame_size(
    df3d_package_example_dir, tmp_path, capsys
):
    folder = df3d_package_example_dir
    _, out, printed = _init(tmp_path, folder, capsys)
    data = yaml.safe_load(out.read_text())
    # its world is the fly's mirror image, decided from its cameras, and mirrored back
    assert data["calibration"] == {
        "file": str(folder / "calib.pkl"),
        "format": "deepfly3d",
        "mirror": True,
    }
    assert data["pose2d"]["import"]["format"] == "deepfly3d"
    assert "image_size: [height, width]" in printed  # undecided: no footage


def test_init_mirrors_a_deepfly3d_calibration_beside_footage_for_the_detector(
    lab, df3d_package_example_dir, tmp_path, capsys
):
    """Issue 46: no 2D to triangulate (flylib's detector runs): the calibration's cameras
    against the default rig decide, and the starter says why."""
    folder = shutil.copytree(lab / "fly1" / "trial1", tmp_path / "fly1")
    for csv in folder.glob("*.csv"):
        csv.unlink()
    shutil.copy(df3d_package_example_dir / "calib.pkl", folder / "calib.pkl")
    _, out, _ = _init(tmp_path, folder, capsys)
    data = yaml.safe_load(out.read_text())
    assert "import" not in data.get("pose2d", {})
    assert data["calibration"] == {
        "file": str(folder / "calib.pkl"),
        "format": "deepfly3d",
        "mirror": True,
    }
    assert (
        "# mirror: its world is the fly's mirror image (the centres and image-up directions of its "
        "7 cameras fit the cameras table's only mirrored (residual 0.02, 0.81 unmirrored)); "
        "mirrored back" in out.read_text()
    )


def test_init_cli_entry_point(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "flylib.cli", "init", "--help"], capture_output=True, text=True
    )
    assert done.returncode == 0 and "starter config" in done.stdout
