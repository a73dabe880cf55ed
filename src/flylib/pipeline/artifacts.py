"""The names of the workflow's files: stage artifacts and per-recording summary files.

What the Snakefile imports to name its outputs, and what the stage functions write.
"""

from __future__ import annotations

from pathlib import Path

from ..results import ARTIFACTS

__all__ = ["ARTIFACTS", "SUMMARY_FILES", "artifact_path", "candidates_artifact"]


def candidates_artifact(k: int) -> str:
    """File name of the detector's top-``k`` peaks inside ``<outdir>/stages/``.

    Kept beside ``pose2d.h5`` while pictorial structures is on, as a file of its own
    named by ``k``: turning pictorial structures off (or editing ``k`` while it is off)
    re-runs no detection, and a new ``k`` while it is on asks for a new file.
    """
    return f"candidates_k{int(k)}.h5"


#: The per-recording summary files the assemble stage writes beside ``results.h5``.
SUMMARY_FILES = ("summary.json", "summary.png", "calibration.toml", "suspects.csv")


def artifact_path(outdir: str | Path, stage: str) -> Path:
    """``<outdir>/stages/<stage>.h5``."""
    return Path(outdir) / "stages" / ARTIFACTS[stage]
