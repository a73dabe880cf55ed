"""A path a ``flylib`` command cannot write is one line naming it and why (issue 45).

Every subcommand that writes a file is run as the real console script onto a folder it cannot
write: a regular file where a folder is expected, a read-only folder (a read-only mount as
root, who ignores permissions; a folder without write permission otherwise) and, for the
commands that write one new file, a folder that does not exist. Each stops with exit status 1
and one line on stderr naming the path and the reason, no traceback, and leaves nothing behind.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from gui_fixtures import make_corrected_outputs

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A corrected demo run (its outputs folder) and a TOML config beside it."""
    root = tmp_path_factory.mktemp("unwritable")
    out, _, _ = make_corrected_outputs(root / "rec", frames=12)
    (root / "my.toml").write_text('outdir = "res/{id}"\n')
    return out


# name -> (the arguments given the folder it writes into, the path named, the working folder)
COMMANDS = {
    "init": lambda out, d: (["init", str(out.parent), "-o", str(d / "my.yaml")], d / "my.yaml"),
    "check-config --to-yaml": lambda out, d: (
        ["check-config", str(out.parents[1] / "my.toml"), "--to-yaml", str(d / "my.yaml")],
        d / "my.yaml",
    ),
    "export --csv3d": lambda out, d: (
        ["export", str(out / "results.h5"), "--csv3d", str(d / "x.csv")],
        d / "x.csv",
    ),
    "export --dlc-dir": lambda out, d: (
        ["export", str(out / "results.h5"), "--dlc-dir", str(d / "dlc")],
        d / "dlc" / "rh.csv",
    ),
    "export --nwb": lambda out, d: (
        ["export", str(out / "results.h5"), "--nwb", str(d / "x.nwb")],
        d / "x.nwb",
    ),
    "export --training-data": lambda out, d: (
        ["export", str(out / "results.h5"), "--training-data", str(d / "dlc")],
        d / "dlc" / "labeled-data" / "camera_0" / "img0004.png",
    ),
    "calibration -o": lambda out, d: (
        ["calibration", str(out / "results.h5"), "-o", str(d / "rig.toml")],
        d / "rig.toml",
    ),
    # flylib run keeps its checked copies in .flylib/ under the folder it is run from
    "run": lambda out, d: (["run", str(out.parents[1] / "my.toml"), "-n"], d / "run-configs"),
}


def _blocked(kind: str, path: Path, request) -> str:
    """Make ``path`` a folder of ``kind`` that cannot be written into; the reason flylib gives."""
    if kind == "a file":
        path.write_text("not a folder\n")
        return f"{path} is a file, not a folder"
    if kind == "missing":
        return f"its folder {path} does not exist"
    path.mkdir()
    if os.geteuid() != 0:
        path.chmod(0o555)
        request.addfinalizer(lambda: path.chmod(0o755))
        return "permission denied"
    mount = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro", "tmpfs", str(path)], check=False)
    if mount.returncode:
        pytest.skip("root, and no read-only mount can be made here")
    request.addfinalizer(lambda: subprocess.run(["umount", str(path)], check=True))
    return "read-only file system"


@pytest.mark.parametrize(
    "command,kind",
    [(c, k) for c in COMMANDS for k in ("a file", "read-only")]
    + [("init", "missing"), ("check-config --to-yaml", "missing")],
)
def test_a_path_a_command_cannot_write_is_one_line_naming_it(run, tmp_path, command, kind, request):
    cwd = tmp_path / "work"
    cwd.mkdir()
    folder = cwd / ".flylib" if command == "run" else tmp_path / "out"
    reason = _blocked(kind, folder, request)
    args, named = COMMANDS[command](run, folder)
    proc = subprocess.run(
        [str(Path(sys.executable).with_name("flylib")), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO / "src")),
        timeout=300,
    )
    assert proc.returncode == 1
    (line,) = proc.stderr.splitlines()
    subcommand = command.split()[0]
    assert line.startswith(f"flylib {subcommand}: {named}"), line
    assert line.endswith(f": cannot be written ({reason}); nothing was written"), line
    left = [p for p in tmp_path.rglob("*") if p not in (cwd, folder)]
    assert left == [], left


def test_an_export_checks_every_output_before_writing_any(run, tmp_path, capsys):
    from flylib.cli import main

    (tmp_path / "notes").write_text("a file\n")
    results = str(run / "results.h5")
    args = ["--training-data", str(tmp_path / "dlc"), "--csv3d", str(tmp_path / "x.csv")]
    assert main(["export", results, *args, "--nwb", str(tmp_path / "notes" / "x.nwb")]) == 1
    assert capsys.readouterr().err == (
        f"flylib export: {tmp_path}/notes/x.nwb: cannot be written ({tmp_path}/notes is a file, "
        "not a folder); nothing was written\n"
    )
    assert [p.name for p in tmp_path.iterdir()] == ["notes"]
