"""The command line that runs the repository's workflow on a work directory: one place
for the tests and benchmarks that drive Snakemake."""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"


def snakemake_command(workdir: Path, *args: str, cores: int = 2) -> list[str]:
    """``snakemake`` on the repo's Snakefile in ``workdir`` with its ``config.yaml``, a
    whole config that replaces the checkout's (``--replace-workflow-config``), so the
    snapshot is its byte-for-byte copy."""
    return [
        str(SNAKEMAKE),
        "--snakefile",
        str(REPO / "Snakefile"),
        "--directory",
        str(workdir),
        "--configfile",
        str(workdir / "config.yaml"),
        "--replace-workflow-config",
        "--cores",
        str(cores),
        *args,
    ]
