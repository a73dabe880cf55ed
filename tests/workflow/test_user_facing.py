"""What a new user sees from `snakemake`: the per-recording table last, mistakes in the
config or the recordings list as one line naming the user's file and key before the
DAG is built, and nothing written outside the outputs, `.snakemake/` and `demo/`."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import checkpoint_layout

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"

pytestmark = pytest.mark.slow


def user_dir(tmp_path: Path) -> Path:
    """A work directory laid out like a checkout: config/config.yaml is the default."""
    (tmp_path / "config").mkdir()
    shutil.copy(REPO / "config" / "config.yaml", tmp_path / "config" / "config.yaml")
    return tmp_path


def snakemake(workdir: Path, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    cmd = [str(SNAKEMAKE), "--snakefile", str(REPO / "Snakefile"), "--cores", "2", *args]
    return subprocess.run(
        cmd, capture_output=True, text=True, timeout=timeout, cwd=workdir, check=False
    )


def output(proc: subprocess.CompletedProcess) -> str:
    return proc.stdout + proc.stderr


def files_under(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


def untracked_in_repo() -> set[str]:
    proc = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=all"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        pytest.skip("the checkout is not a git work tree")
    return {line[3:] for line in proc.stdout.splitlines() if line.startswith("??")}


def test_demo_run_ends_with_the_table_and_writes_only_outputs_snakemake_and_demo(tmp_path):
    workdir = user_dir(tmp_path)
    before_repo = untracked_in_repo()
    before = files_under(workdir)
    proc = snakemake(workdir)
    assert proc.returncode == 0, proc.stderr[-4000:]

    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    title = max(
        i for i, line in enumerate(lines) if line.startswith("flylib: per-recording results")
    )
    table = lines[title:]
    assert table[1].split()[:4] == ["recording", "frames", "in", "3D"]
    row = table[2].split()
    assert row[0] == "demo" and row[1] == "60" and row[2].endswith("%")
    assert float(row[3]) < 2 and row[4] == "/" and float(row[5]) < 5
    assert row[-1] == "demo/flylib_outputs"
    assert max(len(line) for line in table[:3]) <= 100  # the table fits a normal terminal
    # the demo fly is a fly, not its mirror image (issue 36): no handedness column, and
    # summary.json says so
    assert "handedness" not in table[1]
    summary = json.loads((workdir / "demo" / "flylib_outputs" / "summary.json").read_text())
    assert summary["handedness"]["verdict"] == "right-handed"
    assert summary["handedness"]["score"] > 0.9
    assert table[-1].startswith("demo: 3D error against the demo truth: median ")
    # title, header, one row, the held-out-view accuracy (the note, then the demo's
    # sentence), the truth last; the one warning is bundle adjustment's, and
    # it is right: each camera sees one side, so the two sides share no point and one
    # side can scale about the front camera without changing an image
    assert table[3].startswith("accuracy: held-out px = ") and table[4].strip().startswith("demo: ")
    assert "refinement is better than triangulation" in table[4]
    warnings = table[5:-1]
    assert warnings in ([], ["warnings:", warnings[-1] if warnings else ""]), warnings
    assert not warnings or "bundle adjustment: the rig is poorly determined" in warnings[-1]
    assert "Shell command" not in proc.stdout + proc.stderr  # printshellcmds is off

    written = files_under(workdir) - before
    outside = {f for f in written if not f.startswith((".snakemake/", "demo/"))}
    assert outside == set()
    assert (workdir / "demo" / "flylib_outputs" / "logs" / "demo.log").is_file()
    assert untracked_in_repo() == before_repo

    # nothing to do: Snakemake says so, then the table of the existing results
    again = snakemake(workdir)
    assert again.returncode == 0, again.stderr[-4000:]
    after = again.stderr[again.stderr.index("Nothing to be done") :].splitlines()
    rest = [line for line in after if line.strip()]
    assert rest[1:3] == ["flylib: nothing to do; the existing results:", lines[title]]
    assert rest[3:] == table[1:]
    dry = snakemake(workdir, "-n")
    assert "per-recording results" not in dry.stdout + dry.stderr  # a dry run prints no table


LATE_FAILING = {
    "import_format": ("pose2d:\n  import: {format: deepfly}\n", "pose2d.import.format"),
    # the README's own df3d_result.pkl, where DeepFly3D writes df3d_result_2d.pkl
    "import_files": (
        "pose2d:\n  import: {format: deepfly3d, files: df3d_result.pkl}\n",
        "pose2d.import.files: ",
    ),
    "models_override": (
        "pose2d:\n  models: [{name: deepfly2d, weights: x.tar}]\n",
        "pose2d.models[0].n_out_channels",
    ),
}


@pytest.mark.parametrize("case", LATE_FAILING)
def test_late_failing_configs_fail_at_dry_run_naming_the_users_file_and_key(tmp_path, case):
    workdir = user_dir(tmp_path)
    recording = workdir / "fly1"
    recording.mkdir()
    for i in range(7):
        (recording / f"camera_{i}.mp4").write_bytes(b"")  # the dry run never decodes
    (recording / "df3d_result_2d.pkl").write_bytes(b"")
    text, key = LATE_FAILING[case]
    (workdir / "mine.yaml").write_text(f"recordings: [{recording}]\n{text}")
    before = files_under(workdir)
    proc = snakemake(workdir, "-n", "--configfile", "mine.yaml")
    assert proc.returncode != 0
    errors = [line for line in output(proc).splitlines() if line.startswith("invalid config")]
    assert len(errors) == 1 and errors[0].startswith(f"invalid config: mine.yaml: {key}"), output(
        proc
    )
    assert files_under(workdir) - before <= {
        f for f in files_under(workdir) if f.startswith(".snakemake/")
    }
    assert not (recording / "flylib_outputs").exists()


def test_the_weights_key_passes_the_dry_run(tmp_path):
    workdir = user_dir(tmp_path)
    recording = workdir / "fly1"
    recording.mkdir()
    for i in range(7):
        (recording / f"camera_{i}.mp4").write_bytes(b"")
    checkpoint_layout(workdir / "sh8.tar")
    (workdir / "mine.yaml").write_text(
        f"recordings: [{recording}]\npose2d:\n  weights: {{deepfly2d: sh8.tar}}\n"
        "bundle_adjustment:\n  ftol: 1e-8\n"
    )
    proc = snakemake(workdir, "-n", "--configfile", "mine.yaml")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "rule pose2d" in proc.stdout + proc.stderr


@pytest.mark.parametrize("entry", ["fyl1", "notes.txt"])
def test_a_mistyped_or_file_recording_is_one_line_and_creates_nothing(tmp_path, entry):
    workdir = user_dir(tmp_path)
    (workdir / "fly1").mkdir()
    (workdir / "notes.txt").write_text("not a recording")
    (workdir / "mine.yaml").write_text(f"recordings: [{workdir / entry}]\n")
    before = files_under(workdir)
    proc = snakemake(workdir, "--configfile", "mine.yaml")  # a real run, not only -n
    assert proc.returncode != 0
    errors = [line for line in output(proc).splitlines() if line.startswith("invalid config")]
    assert len(errors) == 1, output(proc)
    expected = (
        f"does not exist; did you mean {workdir / 'fly1'}?"
        if entry == "fyl1"
        else "is a file, not a directory"
    )
    assert errors[0].startswith(f"invalid config: mine.yaml: recordings[0]: {workdir / entry}")
    assert expected in errors[0]
    assert "Traceback" not in output(proc)
    assert {f for f in files_under(workdir) - before if not f.startswith(".snakemake/")} == set()
    assert sorted(p.name for p in workdir.iterdir() if p.name != ".snakemake") == [
        "config",
        "fly1",
        "mine.yaml",
        "notes.txt",
    ]


def test_a_key_given_twice_in_a_configfile_is_an_error_naming_file_and_lines(tmp_path):
    workdir = user_dir(tmp_path)
    (workdir / "mine.yaml").write_text(
        "triangulation:\n  method: dlt\ntriangulation:\n  method: greedy\n"
    )
    proc = snakemake(workdir, "-n", "--configfile", "mine.yaml")
    assert proc.returncode != 0
    assert "mine.yaml: triangulation: key given twice (lines 1 and 3)" in output(proc)
