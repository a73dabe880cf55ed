"""What this process may use of the machine.

A workflow job is given a number of threads (the rule's ``threads``, Snakemake's ``--cores``);
:func:`thread_budget` makes that number what every thread pool in flylib sizes itself from.
Outside a budget (library use) the pools size themselves from the CPU affinity mask.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

_budget: int | None = None


def usable_cpus() -> int:
    """CPUs this process may use: the :func:`thread_budget` in force, else its affinity mask
    where the OS has one (a SLURM job bound to 2 cores of a 64-core node gets 2), else the
    CPU count."""
    if _budget is not None:
        return _budget
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS and Windows have no affinity mask
        return max(1, os.cpu_count() or 1)


@contextmanager
def thread_budget(threads: int | None) -> Iterator[int]:
    """Size every flylib thread pool (and BLAS's) from ``threads`` while in the block.

    Under ``threads=1`` flylib starts no thread: pools run their work inline, the detector
    decodes in the calling thread, FFmpeg decodes with one thread and torch's CPU pool has one.

    Not covered: what native libraries start on their own. JAX's CPU backend starts its C++
    thread pools on the first JAX operation, sized from the machine; ``XLA_FLAGS`` does not
    shrink them (jax 0.10), and nothing can once the backend is up. They idle outside JAX
    calls. Likewise OpenBLAS starts its pool on import; ``threadpool_limits`` keeps all but
    one of its threads idle.

    ``threads=None`` sets no budget (the affinity mask). Yields the budget in force.
    """
    global _budget
    if threads is None:
        yield usable_cpus()
        return
    from threadpoolctl import threadpool_limits

    previous, _budget = _budget, max(1, int(threads))
    try:
        with threadpool_limits(_budget):
            yield _budget
    finally:
        _budget = previous


def thread_map(fn: Callable[[T], R], items: Sequence[T], workers: int) -> Iterator[R]:
    """``map(fn, items)`` in order on at most ``workers`` threads (capped by
    :func:`usable_cpus`); in the calling thread when that leaves one.

    At most ``workers`` items run ahead of the one being consumed, so a caller that writes
    each result out (a chunked stage) keeps its memory flat in the number of items.
    """
    workers = max(1, min(int(workers), usable_cpus(), len(items)))
    if workers == 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
