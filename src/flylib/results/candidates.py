"""The detector's top-K peaks per (view, frame, point), kept for pictorial structures: stored as
``candidates/{xy, score}``, in their own artifact (``stages/candidates_k<k>.h5``) or inside the
pose2d group."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py

from ..errors import ResultsError
from ..paths import atomic_path
from .datasets import read_dataset, write_array
from .hdf5 import create_file, new_meta, read_checked


def read_candidates(group: h5py.Group) -> Any:
    """The :class:`flylib.pictorial.Candidates` in ``group``'s ``candidates/``."""
    from ..pictorial import Candidates

    return Candidates(
        xy=read_dataset(group["candidates/xy"]), score=read_dataset(group["candidates/score"])
    )


def write_candidates(group: h5py.Group, candidates: Any) -> None:
    write_array(group, "xy", candidates.xy)
    write_array(group, "score", candidates.score)


def save_candidates(
    path: str | Path, candidates: Any, meta: Mapping[str, Any] | None = None
) -> None:
    """Write the detector's top-K peaks (a :class:`flylib.pictorial.Candidates`) atomically to
    their own artifact; ``meta``: extra entries for its meta JSON (e.g. its params hash)."""
    with atomic_path(path) as tmp, create_file(tmp) as f:
        f.attrs["meta"] = json.dumps(new_meta("candidates", meta))
        write_candidates(f.create_group("candidates"), candidates)


def load_candidates(path: str | Path) -> Any:
    """Read what :func:`save_candidates` wrote; a missing, stale or empty file is a ResultsError."""
    rerun = "re-run the pose2d stage with pictorial structures on"
    with read_checked(path, rerun) as f:
        if "candidates/xy" not in f:
            raise ResultsError(f"{path}: holds no candidate peaks; {rerun}")
        return read_candidates(f)
