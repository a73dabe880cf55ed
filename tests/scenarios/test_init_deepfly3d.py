"""`flylib init` on a folder laid out as DeepFly3D leaves it (issue 46): its results in the
sibling folder ``<input>_df3d`` (``df3d-cli``'s default output folder) holding
``df3d_result_<input path>.pkl``, sometimes several pickles; then the dry run the user is
told to type, typed as printed, from a shell without the virtual environment on its PATH."""

from __future__ import annotations

import os
import pickle
import re
import subprocess
from pathlib import Path

import pytest
import yaml

from .lab import assert_self_consistent, copy_files, env, finished, flylib_cli, table_line

pytestmark = pytest.mark.shared


def _init(cwd: Path, folder: Path) -> subprocess.CompletedProcess:
    """``flylib init folder -o my.yaml`` from ``cwd``, with a PATH that holds no snakemake."""
    return flylib_cli(cwd, "init", str(folder), "-o", "my.yaml", PATH="/usr/bin:/bin")


def _as_printed(cwd: Path, printed: str, run: bool = False) -> subprocess.CompletedProcess:
    """The 'Next:' dry run ``flylib init`` printed (or, with ``run``, the run after it), run by
    a shell as the user would; ``proc.out`` holds stdout then stderr."""
    pattern = r", then (.+ --cores 2)\n" if run else r"Next: (.+?) \(a dry run\)"
    command = re.search(pattern, printed)
    assert command, printed
    proc = subprocess.run(
        command[1],
        shell=True,
        cwd=cwd,
        env={**env(), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    proc.out = proc.stdout + proc.stderr
    return proc


def _df3d_lab(root: Path, sample: Path) -> tuple[Path, Path]:
    """``root/lab/fly1`` (the sample's videos) and ``root/lab/fly1_df3d``, DeepFly3D's output
    folder for it, holding its 2D under the name DeepFly3D gives it."""
    fly = copy_files(sample, root / "lab" / "fly1", ["camera_*.mp4"])
    out = root / "lab" / "fly1_df3d"
    out.mkdir()
    name = "df3d_result_{}.pkl".format(str(fly).replace("/", "_"))
    (out / name).write_bytes((sample / "df3d_result_2d.pkl").read_bytes())
    return fly, out / name


def test_init_finds_deepfly3ds_results_folder_and_the_dry_run_it_prints_runs(
    df3d_sample_dir, tmp_path
):
    fly, pkl = _df3d_lab(tmp_path, df3d_sample_dir)
    init = _init(tmp_path, tmp_path / "lab")
    assert init.returncode == 0, init.out
    assert "1 recording(s)" in init.out and "undecided" not in init.out, init.out
    data = yaml.safe_load((tmp_path / "my.yaml").read_text())
    assert data["recordings"] == [str(fly)]
    assert data["pose2d"]["import"] == {"format": "deepfly3d", "files": f"../fly1_df3d/{pkl.name}"}
    dry = _as_printed(tmp_path, init.stdout)
    assert dry.returncode == 0, dry.stdout[-2000:] + dry.stderr[-3000:]
    assert "rule pose2d:" in dry.stdout and "weights" not in dry.stderr


def test_init_among_several_deepfly3d_pickles_takes_the_newest_2d_and_says_why(
    df3d_sample_dir, df3d_package_example_dir, tmp_path
):
    fly, _ = _df3d_lab(tmp_path, df3d_sample_dir)
    out = fly.parent / "fly1_df3d"
    for p in out.iterdir():
        p.unlink()
    # DeepFly3D 1.x's full result (2D, 3D and its calibration), an older 0.x 2D-only result,
    # and a pickle of 3D alone
    full = out / "df3d_result.pkl"
    full.write_bytes((df3d_package_example_dir / "df3d_result.pkl").read_bytes())
    old = out / "df3d_result_2d.pkl"
    old.write_bytes((df3d_sample_dir / "df3d_result_2d.pkl").read_bytes())
    with open(df3d_package_example_dir / "df3d_result.pkl", "rb") as f:
        points3d = pickle.load(f)["points3d"]
    with open(out / "df3d_result_3d.pkl", "wb") as f:
        pickle.dump({"points3d": points3d}, f)
    os.utime(old, (1_600_000_000, 1_600_000_000))
    init = _init(tmp_path, tmp_path / "lab")
    assert "several tools" not in init.out and "df3d_result_3d.pkl" not in init.out, init.out
    assert (
        f"  undecided: {fly}: 2 DeepFly3D pickles with 2D (../fly1_df3d/df3d_result.pkl, "
        "../fly1_df3d/df3d_result_2d.pkl); using the newest, ../fly1_df3d/df3d_result.pkl; "
        "set pose2d.import.files to take another"
    ) in init.out, init.out
    text = (tmp_path / "my.yaml").read_text()
    assert (
        "# mirror: its world is the fly's mirror image (the centres and image-up directions of "
        "its 7 cameras fit the cameras table's only mirrored (residual 0.02, 0.81 unmirrored)); "
        "mirrored back\n"
        "calibration: {file: ../fly1_df3d/df3d_result.pkl, format: deepfly3d, mirror: true}\n"
    ) in text, text
    data = yaml.safe_load(text)
    assert data["pose2d"]["import"] == {
        "format": "deepfly3d",
        "files": "../fly1_df3d/df3d_result.pkl",
    }


@pytest.mark.slow
def test_init_on_deepfly3ds_image_sequences_runs_as_printed(df3d_sample_dir, tmp_path):
    """DeepFly3D reads a recording as images ``camera_<N>_img_<M>.jpg`` (camera N = 0..6 in its
    rig order) and writes its results to ``<name>_df3d``: init maps the sequences to the
    default rig's cameras by their numbers, and the two commands it prints run to the end."""
    fly = copy_files(df3d_sample_dir, tmp_path / "lab" / "fly1", ["camera_*_img_*.jpg"])
    (tmp_path / "lab" / "fly1_df3d").mkdir()
    pkl = tmp_path / "lab" / "fly1_df3d" / "df3d_result_{}.pkl".format(str(fly).replace("/", "_"))
    pkl.write_bytes((df3d_sample_dir / "df3d_result_2d.pkl").read_bytes())
    init = _init(tmp_path, tmp_path / "lab")
    assert init.returncode == 0 and "1 recording(s)" in init.out, init.out
    data = yaml.safe_load((tmp_path / "my.yaml").read_text())
    views = ("rh", "rm", "rf", "f", "lf", "lm", "lh")
    assert data["sources"] == [
        {"name": f"vid_{v}", "filename": f"camera_{i}_img_*.jpg"} for i, v in enumerate(views)
    ]
    assert data["pose2d"]["import"] == {"format": "deepfly3d", "files": f"../fly1_df3d/{pkl.name}"}
    dry = _as_printed(tmp_path, init.stdout)
    assert dry.returncode == 0, dry.stdout[-2000:] + dry.stderr[-3000:]
    out = finished(_as_printed(tmp_path, init.stdout, run=True))
    cells = table_line(out, "fly1")
    assert cells[1] == "15" and float(cells[2].rstrip("%")) > 95, cells
    result = assert_self_consistent(fly / "flylib_outputs" / "results.h5")
    assert result.pts3d.shape == (15, 38, 3) and result.cameras.names == list(views)
    assert (fly / "flylib_outputs" / "pose2d.mp4").stat().st_size > 0  # drawn on the images
