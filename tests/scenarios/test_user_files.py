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


# -- cases 2 and 3: an outdir holding the user's files ------------------------------------


def _env() -> dict:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]),
    }
    env.pop("FLYLIB_RUN_ID", None)
    return env


def _snakemake(workdir: Path, *args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    return subprocess.run(
        snakemake_command(workdir, *args),
        cwd=workdir,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _recording_run(root: Path, **settings) -> tuple[Path, dict]:
    """A tiny imported-2D recording in ``root/fly1`` and the work directory's config."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    data["bundle_adjustment"]["max_nfev"] = 20
    data["pipeline"].update(do_visualization=False, do_refinement=False)
    cfg = Config.from_dict(data)
    rec = root / "fly1"
    make_demo(cfg, rec, frames=6, seed=0)
    data["recordings"] = [{"path": str(rec), "import": demo_import_spec(cfg)}]
    data.update(settings)
    (root / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return rec, data


def _user_files(rec: Path) -> dict[Path, bytes]:
    files = {
        rec / "config.yaml": b"# the lab's own notes\nfly: 1\n",
        rec / "summary.png": b"\x89PNG lab figure",
    }
    for path, data in files.items():
        path.write_bytes(data)
    return files


def test_an_outdir_over_the_users_files_stops_before_any_job(tmp_path):
    rec, _ = _recording_run(tmp_path, outdir="{recording}")
    files = _user_files(rec)
    listing = sorted(p.name for p in rec.iterdir())
    for args in ((), ("-n",)):
        proc = _snakemake(tmp_path, *args)
        assert proc.returncode == 1, proc.stderr[-3000:]
        for name in ("config.yaml", "summary.png"):
            assert (
                f"outdir: {rec / name} exists and was not written by flylib (not in "
                f".flylib-outputs) and would be overwritten by assemble's {name}; move it away "
                "or set outdir to another folder, e.g. '{recording}/flylib_outputs'"
            ) in proc.stderr, proc.stderr[-3000:]
    check = subprocess.run(
        [
            str(Path(os.sys.executable).parent / "flylib"),
            "check-config",
            str(tmp_path / "config.yaml"),
        ],
        cwd=tmp_path,
        env=_env(),
        capture_output=True,
        text=True,
    )
    assert (
        check.returncode == 1
        and f"{rec / 'summary.png'} exists and was not written" in check.stderr
    )
    assert {p: p.read_bytes() for p in files} == files
    assert sorted(p.name for p in rec.iterdir()) == listing  # nothing created or removed


def test_the_runs_calibration_file_in_the_outdir_is_never_deleted(tmp_path):
    from flylib.config import Config
    from flylib.interop.anipose import write_anipose_toml
    from flylib.pipeline.planning import config_rig

    rec, data = _recording_run(tmp_path, outdir="{recording}")
    calibration = rec / "calibration.toml"
    cfg = Config.from_dict(data)
    sizes = {v: (480, 960) for v in cfg.view_names()}
    write_anipose_toml(config_rig(cfg, sizes), calibration, sizes)
    data["calibration"] = {"file": "calibration.toml", "format": "anipose"}
    data["pipeline"]["do_bundle_adjustment"] = False
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    before = calibration.read_bytes()
    proc = _snakemake(tmp_path)
    assert proc.returncode == 1
    assert (
        f"outdir: {calibration} is the run's calibration file (calibration.file) and would be "
        "overwritten by assemble's calibration.toml; set outdir to another folder, e.g. "
        "'{recording}/flylib_outputs'"
    ) in proc.stderr, proc.stderr[-3000:]
    assert "CyclicGraphException" not in proc.stderr and "Missing files" not in proc.stderr
    assert calibration.read_bytes() == before
    assert not (rec / "stages").exists() and not (rec / "results.h5").exists()


@pytest.mark.slow
def test_files_flylib_wrote_are_replaced_by_the_next_run(tmp_path):
    rec, data = _recording_run(tmp_path)  # the default outdir: <recording>/flylib_outputs
    files = _user_files(rec)  # the user's files beside the outputs stay untouched
    first = _snakemake(tmp_path)
    assert first.returncode == 0, first.stderr[-4000:]
    out = rec / "flylib_outputs"
    assert "config.yaml" in (out / ".flylib-outputs").read_text().split()
    snapshot = (out / "config.yaml").stat().st_mtime_ns
    again = _snakemake(tmp_path, "--forcerun", "assemble")
    assert again.returncode == 0, again.stderr[-4000:]
    assert (out / "config.yaml").stat().st_mtime_ns != snapshot
    assert {p: p.read_bytes() for p in files} == files


def test_the_outdir_check_resolves_paths_as_the_file_system_does(tmp_path, monkeypatch):
    """The folder-at-a-time resolution the outdir check uses (flylib.paths.real_paths)
    is os.path.realpath: through a linked folder, a linked file, '..' after a link."""
    from flylib.paths import real_paths

    monkeypatch.chdir(tmp_path)
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "b" / "f").write_text("")
    os.symlink("a/b", "d")
    os.symlink("a/b/f", "lf")
    os.symlink("../nothing", "a/dangling")
    real = real_paths()
    for path in ("d/f", "lf", "a/dangling", "d/../x", "d/..", "d/", ".", "./a//b/f", "/"):
        assert real(path) == os.path.realpath(path), path
        assert real(tmp_path / path) == os.path.realpath(tmp_path / path), path
