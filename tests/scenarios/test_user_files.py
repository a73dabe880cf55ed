"""The user's own files are never overwritten or deleted (issue 37, cases 1-3).

``flylib export`` and ``flylib calibration`` refuse an output that is one of their
inputs (the same path, a link to it, another name of it) and, without ``--force``, a
file flylib did not write; the workflow refuses an ``outdir`` whose planned outputs
would land on the run's inputs or on files flylib did not write, before any job, and
still replaces its own files on a re-run.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path

import pytest
import yaml

from flylib.cli import main

from gui_fixtures import make_demo_outputs
from workflow_run import snakemake_command

REPO = Path(__file__).resolve().parents[2]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def outputs(tmp_path_factory) -> Path:
    return make_demo_outputs(tmp_path_factory.mktemp("export") / "rec", frames=6)


# -- case 1: an export onto its own input -----------------------------------------------


@pytest.mark.parametrize("option", ["--csv3d", "--nwb"])
def test_an_export_onto_its_results_file_is_refused_and_the_file_kept(outputs, option, capsys):
    results = outputs / "results.h5"
    before = _digest(results)
    assert main(["export", str(results), option, str(results)]) == 1
    err = capsys.readouterr().err
    assert err == (
        f"flylib export: {results} is the input RESULTS_H5 and would be overwritten by "
        f"flylib export {option}; write to another file\n"
    )
    assert _digest(results) == before


def test_a_link_to_the_input_and_the_calibration_command_are_refused(outputs, tmp_path, capsys):
    results = outputs / "results.h5"
    before = _digest(results)
    link = tmp_path / "link.csv"
    link.symlink_to(results)
    assert main(["export", str(results), "--csv3d", str(link), "--force"]) == 1
    assert "is the input RESULTS_H5 and would be overwritten" in capsys.readouterr().err
    hard = tmp_path / "other_name.h5"
    os.link(results, hard)
    assert main(["calibration", str(results), "-o", str(hard), "--force"]) == 1
    assert "is the input RESULTS_H5 and would be overwritten by flylib calibration -o" in (
        capsys.readouterr().err
    )
    snapshot = outputs / "config.yaml"
    snap = _digest(snapshot)
    assert main(["export", str(results), "--csv3d", str(snapshot)]) == 1
    assert "is the config snapshot beside RESULTS_H5" in capsys.readouterr().err
    assert _digest(results) == before and _digest(snapshot) == snap


def test_an_existing_file_flylib_did_not_write_needs_force_its_own_export_does_not(
    outputs, tmp_path, capsys
):
    results = outputs / "results.h5"
    mine = tmp_path / "analysis.csv"
    mine.write_text("the lab's own table\n")
    assert main(["export", str(results), "--csv3d", str(mine)]) == 1
    assert capsys.readouterr().err == (
        f"flylib export: {mine} exists and was not written by flylib; flylib export --csv3d "
        "would replace it: choose another file, or pass --force to replace it\n"
    )
    assert mine.read_text() == "the lab's own table\n"
    # a view's CSV of --dlc-dir: checked before anything is written
    from flylib.results import PoseResult

    view = PoseResult.load(results).cameras.names[3]
    (tmp_path / "dlc").mkdir()
    (tmp_path / "dlc" / f"{view}.csv").write_text("hand labels\n")
    assert main(["export", str(results), "--dlc-dir", str(tmp_path / "dlc")]) == 1
    assert f"{view}.csv exists and was not written by flylib" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "dlc").iterdir()) == [f"{view}.csv"]
    # flylib's own export is replaced by the next export, and --force replaces the user's
    fresh = tmp_path / "points3d.csv"
    assert main(["export", str(results), "--csv3d", str(fresh)]) == 0
    assert main(["export", str(results), "--csv3d", str(fresh)]) == 0
    assert main(["export", str(results), "--csv3d", str(mine), "--force"]) == 0
    assert "center_0" in mine.read_text().splitlines()[0]  # the Anipose table
