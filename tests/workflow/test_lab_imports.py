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
        "calibration": {"file": "calib.pkl", "format": "deepfly3d"},
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
