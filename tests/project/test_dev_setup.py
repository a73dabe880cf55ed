"""The developer set-up: system packages come from the documented set-up
(``install.sh --test-system-packages``, run by ``.ci/run``), never from inside a test."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _install_function() -> str:
    text = (REPO / "install.sh").read_text()
    start = text.index("install_system_packages() {")
    return text[start : text.index("\n}\n", start) + 3]


def test_no_test_runs_a_package_manager():
    offenders = []
    for path in sorted((REPO / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.List) and node.elts:
                first = node.elts[0]
                if isinstance(first, ast.Constant) and first.value in ("apt-get", "apt", "dnf"):
                    offenders.append(f"{path.name}:{node.lineno}")
    assert offenders == [], offenders


def test_ci_installs_the_system_packages_first():
    run = (REPO / ".ci" / "run").read_text()
    assert "bash install.sh --test-system-packages && bash .ci/lint" in run


def test_system_packages_step_is_one_quiet_line_and_never_fails_without_apt(tmp_path):
    """Where apt-get is not there (or not root) it says so once and succeeds."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("id", "env", "timeout"):  # everything but apt-get, slurm and chromium
        os.symlink(shutil.which(tool), bin_dir / tool)
    proc = subprocess.run(
        [shutil.which("bash"), "-c", _install_function() + "install_system_packages"],
        env={"PATH": str(bin_dir)},
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [
        "install.sh: not installing slurm-wlm munge chromium chromium-driver (needs root and "
        "apt-get); the tests that use them skip"
    ]
    assert proc.stderr == ""
