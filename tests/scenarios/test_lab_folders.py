"""A lab's folders: its config in ``configs/``, its recordings listed in a sheet saved by
a spreadsheet program (``sheets/recordings.csv``, paths relative to the sheet), results
wanted in ``results/``, and the workflow run from the lab's folder with the checkout's
Snakefile elsewhere (``snakemake -s <checkout>/Snakefile --configfile configs/my.yaml``),
so every relative path is relative to where the lab runs it (the README), or to the
sheet for the sheet's rows.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .lab import (
    assert_self_consistent,
    env,
    finished,
    lab_run,
    read_dlc_csv,
    stored_pose2d,
    synthetic_recording,
    table_line,
    write_config,
)
from workflow_run import REPO

pytestmark = pytest.mark.slow

FLYLIB = str(Path(sys.executable).with_name("flylib"))

FRAMES = 4
SHEET = """path,import_format,import_files
../data/fly1,dlc_csv,{stem}DLC_*.csv
../data/fly2,dlc_csv,{stem}DLC_*.csv
"""


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """The lab's folder, after one run from it."""
    root = tmp_path_factory.mktemp("lab") / "lab"
    for seed, name in enumerate(("fly1", "fly2")):
        synthetic_recording(root / "data" / name, FRAMES, seed=seed + 10)
    (root / "sheets").mkdir()
    (root / "sheets" / "recordings.csv").write_text("\ufeff" + SHEET)  # as Excel saves it
    write_config(
        root / "configs" / "my.yaml",
        {
            "recordings": "sheets/recordings.csv",
            "outdir": "results/{name}",
            "pipeline": {"do_visualization": False},
        },
    )
    return root, lab_run(root, "configs/my.yaml")


def test_a_csv_sheet_lists_the_recordings_relative_to_itself(lab):
    root, proc = lab
    out = finished(proc)
    from flylib.config import Config

    points = list(Config.default().data["skeleton"]["point_names"])
    for name in ("fly1", "fly2"):
        assert table_line(out, name)[1] == str(FRAMES)
        assert table_line(out, name)[-1] == f"results/{name}"
        results = root / "results" / name / "results.h5"
        csvs = [root / "data" / name / f"camera_{i}DLC_flylibdemo.csv" for i in range(7)]
        expected = np.stack([read_dlc_csv(path, points) for path in csvs])
        np.testing.assert_allclose(stored_pose2d(results), expected, rtol=0, atol=1e-9)
        assert_self_consistent(results)


def test_relative_paths_are_the_labs_folder_and_nothing_lands_elsewhere(lab):
    root, proc = lab
    finished(proc)
    assert sorted(p.name for p in (root / "results").iterdir()) == ["fly1", "fly2"]
    assert sorted(p.name for p in (root / "configs").iterdir()) == ["my.yaml"]
    assert sorted(p.name for p in (root / "sheets").iterdir()) == ["recordings.csv"]
    for name in ("fly1", "fly2"):
        assert not (root / "data" / name / "flylib_outputs").exists()
    # the same config through `flylib run` (how a config someone else wrote is run)
    again = subprocess.run(
        [FLYLIB, "run", "configs/my.yaml", "-s", str(REPO / "Snakefile"), "-n", "--cores", "2"],
        cwd=root,
        env=env(),
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert again.returncode == 0, (again.stdout + again.stderr)[-4000:]
    assert "Nothing to be done" in again.stdout + again.stderr


def test_a_tab_separated_sheet_plans_the_same_run(lab):
    root, proc = lab
    finished(proc)
    (root / "sheets" / "recordings.tsv").write_text(SHEET.replace(",", "\t"))
    write_config(
        root / "configs" / "tsv.yaml",
        {
            "recordings": "sheets/recordings.tsv",
            "outdir": "results/{name}",
            "pipeline": {"do_visualization": False},
        },
    )
    dry = lab_run(root, "configs/tsv.yaml", "-n")
    assert "Nothing to be done" in finished(dry)


def test_a_recording_relative_to_the_configs_folder_is_found_or_the_message_says_where_it_looked(
    lab,
):
    root, proc = lab
    finished(proc)
    write_config(
        root / "configs" / "near.yaml",
        {"recordings": ["../data/fly1"], "outdir": "results/{name}"},
    )
    dry = lab_run(root, "configs/near.yaml", "-n")
    # Snakemake's rule (relative to the working directory), said with where it looked and
    # where the path does exist
    assert dry.returncode != 0
    assert f"../data/fly1 does not exist in the working directory {root}" in dry.out, dry.out[
        -3000:
    ]
    assert f"list it as {(root / 'configs' / '../data/fly1')}" in dry.out or (
        f"list it as {root / 'data' / 'fly1'}" in dry.out
    ), dry.out[-3000:]
