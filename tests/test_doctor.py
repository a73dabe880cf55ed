"""`flylib doctor`: one screen on the installation; exit 1 only for what blocks a run."""

from __future__ import annotations

import subprocess
import sys

from flylib import doctor
from flylib.cli import main


def test_doctor_reports_this_installation(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    status = main(["doctor"])
    out = capsys.readouterr().out
    assert status == 0, out
    for what in (
        "python",
        "packages",
        "torch device",
        "weights deepfly2d",
        "cache",
        "slurm",
        "chromium",
    ):
        assert f"  {what}" in out
    assert "torch" in out and "jax" in out and "snakemake" in out
    assert out.rstrip().endswith("ready to run (notes above are not problems)")
    assert str(tmp_path / "cache") in out  # FLYLIB_CACHE is the cache shown


def test_an_unwritable_cache_blocks_a_run(capsys, tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("FLYLIB_CACHE", str(blocker / "cache"))  # under a file: never writable
    assert main(["doctor"]) == 1
    out = capsys.readouterr().out
    assert "FAIL  cache" in out and "set FLYLIB_CACHE to a writable folder" in out
    assert "1 problem(s) block a run: cache" in out


def test_a_missing_package_blocks_a_run(monkeypatch):
    monkeypatch.setattr(doctor, "REQUIRED", (*doctor.REQUIRED, ("no-such-dist", "no_such_module")))
    lines = doctor.check_packages()
    failed = [c for c in lines if c.status == doctor.FAIL]
    assert len(failed) == 1 and "no-such-dist (not installed)" in failed[0].detail


def test_local_weights_from_the_users_config(tmp_path, monkeypatch):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    weights = tmp_path / "sh8_deepfly.tar"
    weights.write_bytes(b"not checked here: the detector job verifies and loads it")
    config = tmp_path / "my.yaml"
    config.write_text(f"pose2d:\n  weights: {{deepfly2d: {weights}}}\n")
    (line,) = doctor.check_weights([config])
    assert (line.status, line.what, line.detail) == (doctor.OK, "weights deepfly2d", str(weights))


def test_missing_weights_are_a_note_naming_where_they_go(tmp_path, monkeypatch):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    config = tmp_path / "my.yaml"
    config.write_text(f"pose2d:\n  weights: {{deepfly2d: {tmp_path / 'absent.tar'}}}\n")
    (line,) = doctor.check_weights([config])
    assert line.status == doctor.NOTE
    assert (
        "needed only to run the detector" in line.detail
        and "absent.tar does not exist" in line.detail
    )


def test_doctor_console_script():
    done = subprocess.run(
        [sys.executable, "-m", "flylib.cli", "doctor", "--help"], capture_output=True, text=True
    )
    assert done.returncode == 0 and "installation in one screen" in done.stdout
