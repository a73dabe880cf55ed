"""Folder names a filesystem allows, through the real workflow: each one works, or is
refused before the DAG in one line naming the path and the fix (issue 37, case 12)."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

import pytest
import yaml

from workflow_run import snakemake_command

REPO = Path(__file__).resolve().parents[2]


def _env() -> dict:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]),
    }
    env.pop("FLYLIB_RUN_ID", None)
    return env


def _workdir(root: Path, names: list[str], **config) -> Path:
    """``root`` with a tiny imported-2D recording per name and a config listing them."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    root.mkdir(parents=True, exist_ok=True)
    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    data["bundle_adjustment"]["max_nfev"] = 20
    cfg = Config.from_dict(data)
    data["recordings"] = []
    for seed, name in enumerate(names):
        make_demo(cfg, root / name, frames=6, seed=seed)
        data["recordings"].append({"path": str(root / name), "import": demo_import_spec(cfg)})
    data.update(config)
    (root / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return root


def _run(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        snakemake_command(workdir, *args),
        cwd=workdir,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )


def _refused(proc: subprocess.CompletedProcess) -> str:
    """The one line a run refused before its DAG ends with (and nothing else of note)."""
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "Building DAG" not in proc.stdout + proc.stderr
    for noise in ("Traceback", "WildcardError", "OSError", 'File "'):
        assert noise not in proc.stderr, proc.stderr[-3000:]
    return proc.stderr.strip().splitlines()[-1]


@pytest.mark.slow  # runs Snakemake
def test_a_folder_name_with_a_brace_group_is_refused_in_one_line(tmp_path):
    root = _workdir(tmp_path, ["fly{1}"])
    line = _refused(_run(root, "-n"))
    assert line == (
        f"invalid config: config.yaml: recordings[0]: {root / 'fly{1}'}: the recording "
        "folder's path holds {1}, which Snakemake reads as a wildcard in a file path "
        "(there is no escape for it); rename it without braces, e.g. ( ) or _"
    )


@pytest.mark.slow  # runs Snakemake
def test_a_leading_dash_and_literal_brackets_in_folder_names_run_to_the_end(tmp_path):
    # "fly[1]" exists, so it is that folder, not a pattern matching "fly1"; "-fly" is
    # never an argv token that an option could swallow.
    root = _workdir(tmp_path, ["-fly", "fly[1]"])
    proc = _run(root)
    assert proc.returncode == 0, proc.stderr[-4000:]
    for name in ("-fly", "fly[1]"):
        assert (root / name / "flylib_outputs" / "results.h5").is_file()
    assert "is not a valid recording" not in proc.stderr


def test_a_listed_path_that_exists_is_a_path_and_a_missing_one_a_pattern(tmp_path):
    from flylib.recordings.lookup import is_pattern

    (tmp_path / "fly[1]").mkdir()
    assert not is_pattern(tmp_path / "fly[1]")
    assert is_pattern(tmp_path / "fly[2]") and is_pattern(tmp_path / "fly*")
    assert not is_pattern(tmp_path / "fly2")


@pytest.mark.slow  # runs Snakemake
def test_an_outdir_name_longer_than_the_filesystem_allows_is_refused_in_one_line(tmp_path):
    name = "f" * 250
    root = _workdir(tmp_path, [name], outdir="{recording}_flylib_outputs")
    line = _refused(_run(root, "-n"))
    outdir = root / f"{name}_flylib_outputs"
    assert line == (
        f"invalid config: config.yaml: outdir: {outdir}: the folder name {name[:40]}... is "
        "265 bytes, longer than its filesystem allows (255); choose a shorter outdir "
        "(e.g. outdir: results/{id})"
    )


def _unwritable(tmp_path: Path) -> Path:
    """A folder this process cannot write: mode 0555, or (as root, who may write it
    anyway) the read-only /proc/sys."""
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP)
    if not os.access(locked, os.W_OK):
        return locked
    if Path("/proc/sys").is_dir() and not os.access("/proc/sys", os.W_OK):
        return Path("/proc/sys")
    pytest.skip("no folder here that this process cannot write")


@pytest.mark.slow  # runs Snakemake
def test_a_fresh_outdir_in_a_folder_that_cannot_be_written_is_refused_in_one_line(tmp_path):
    parent = _unwritable(tmp_path)
    root = _workdir(tmp_path / "work", ["fly"], outdir=f"{parent}/flylib/{{id}}")
    try:
        line = _refused(_run(root, "-n"))
    finally:
        (tmp_path / "locked").chmod(0o755)
    assert line.startswith(
        f"invalid config: config.yaml: outdir: {parent}/flylib/fly: cannot create the "
        f"output folder in {parent}: it is "
    )
    assert line.endswith("; set outdir to a writable folder")
    assert not (parent / "flylib").exists()


@pytest.mark.slow  # runs Snakemake
def test_folders_named_in_other_scripts_keep_their_names_as_recording_ids(tmp_path):
    root = _workdir(tmp_path, ["日本", "中国"], outdir=f"{tmp_path}/results/{{id}}")
    proc = _run(root, "-n")
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("日本", "中国"):
        assert f"wildcards: outdir={tmp_path / 'results' / name}\n" in proc.stdout
