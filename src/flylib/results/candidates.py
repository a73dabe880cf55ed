"""The detector's top-K peaks per (view, frame, point), kept for pictorial structures.

Stored as ``candidates/{xy, score}``, in their own artifact
(``stages/candidates_k<k>.h5``, :func:`save_candidates`) or inside the pose2d group.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import ResultsError
from ..paths import atomic_path
from .datasets import read_dataset, write_array
from .hdf5 import create_file, new_meta, read_checked


def make_candidates(xy: np.ndarray, score: np.ndarray) -> Any:
    from ..pictorial import Candidates

    return Candidates(xy=xy, score=score)


def write_candidates(group: h5py.Group, candidates: Any) -> None:
    write_array(group, "xy", candidates.xy)
    write_array(group, "score", candidates.score)


def save_candidates(
    path: str | Path, candidates: Any, meta: Mapping[str, Any] | None = None
) -> None:
    """Write the detector's top-K peaks to their own artifact (``candidates/{xy, score}``).

    Parameters
    ----------
    path
        Destination, e.g. ``<out>/stages/candidates.h5``; written atomically.
    candidates
        A :class:`flylib.pictorial.Candidates` (``xy (V, T, P, K, 2)``, ``score (V, T, P, K)``).
    meta
        Extra entries for the file's meta JSON (e.g. its params hash).
    """
    with atomic_path(path) as tmp, create_file(tmp) as f:
        f.attrs["meta"] = json.dumps(new_meta("candidates", meta))
        write_candidates(f.create_group("candidates"), candidates)


def load_candidates(path: str | Path) -> Any:
    """Read what :func:`save_candidates` wrote.

    Raises
    ------
    ResultsError
        If the file is missing, of another version, or holds no candidates.
    """
    rerun = "re-run the pose2d stage with pictorial structures on"
    with read_checked(path, rerun) as f:
        if "candidates/xy" not in f:
            raise ResultsError(f"{path}: holds no candidate peaks; {rerun}")
        return make_candidates(
            read_dataset(f["candidates/xy"]), read_dataset(f["candidates/score"])
        )
