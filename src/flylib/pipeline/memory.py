"""How much memory a workflow job declares (its rule's ``mem_mb``), from the recording's size.

A job's peak is a fixed part (Python, NumPy, JAX, its libraries) plus a part growing with its
``frames x points x views`` arrays. Each stage's figures (:attr:`flylib.stages.Stage.memory`)
are the peak MB ``benchmarks/stage_memory.py`` measures as a workflow job runs the stage
(7 views x 38 points, 1,000 and 10,000 frames with the rules' threads; 500 and 5,000 with one;
the larger): the fixed part and the part per million (frame, point, view) elements. With
:data:`MARGIN` on top, a scheduler (SLURM kills a job past its reservation) reserves enough for
a 100,000-frame recording as for the demo. Refinement's chunked solve grows more slowly past
10,000 frames, so its figure over-reserves there. Stages without a figure (the detector,
import, visualization, exports) keep the fixed ``mem_mb`` their rules state.
"""

from __future__ import annotations

import errno
import math
from collections.abc import Callable
from pathlib import Path

from ..stages import by_name

__all__ = ["MARGIN", "job_mem_mb", "recording_shape", "stage_mem_mb"]

#: Head-room over the measured peak (allocator fragmentation, other footage, rounding).
MARGIN = 1.5
#: The least any job declares.
FLOOR_MB = 1000


def stage_mem_mb(stage: str, shape: tuple[int, int, int]) -> int:
    """The ``mem_mb`` (a multiple of 100, at least :data:`FLOOR_MB`) a stage with a measured
    figure declares for a recording whose 2D is ``shape`` ``(V, T, P)``."""
    views, frames, points = (int(n) for n in shape)
    memory = by_name(stage).memory
    if memory is None:
        raise KeyError(f"{stage}: no measured memory figure (its rule states its mem_mb)")
    fixed, per_million = memory
    peak = fixed + per_million * views * frames * points / 1e6
    return max(FLOOR_MB, int(math.ceil(MARGIN * peak / 100.0)) * 100)


def recording_shape(path: str | Path) -> tuple[int, int, int]:
    """``(V, T, P)`` of the 2D in a pose2d artifact or a ``results.h5``; FileNotFoundError
    (naming it) while ``path`` does not exist yet: Snakemake then decides the resource once
    the upstream job has written it."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(errno.ENOENT, "no such file", str(path))
    with h5py.File(path, "r") as f:
        v, t, p, _ = f["pose2d/points"].shape
    return int(v), int(t), int(p)


def job_mem_mb(stage: str, fallback_mb: int = 4000) -> Callable[..., int]:
    """A rule's ``mem_mb``: :func:`stage_mem_mb` of the job's pose2d (or results) input,
    doubled on each retry (``attempt``); ``fallback_mb`` when the input cannot be read (a
    damaged file: the job fails on it with its own message)."""

    def mem_mb(wildcards, input, attempt: int = 1) -> int:
        source = input.get("pose2d") or input.get("results")
        if isinstance(source, list):
            source = source[0] if source else None
        try:
            megabytes = stage_mem_mb(stage, recording_shape(source))
        except FileNotFoundError:
            raise
        except (OSError, KeyError, ValueError, TypeError):
            megabytes = fallback_mb
        return megabytes * 2 ** (max(int(attempt), 1) - 1)

    return mem_mb
