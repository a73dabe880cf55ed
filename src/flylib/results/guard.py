"""What keeps an HDF5 file, flylib's own or another tool's, from reaching beyond itself.

HDF5 lets a file borrow bytes from elsewhere: a dataset's raw data may live in other files
(external storage, ``Dataset.external``: a FIFO there blocks a read forever, a local file there is
read as if it were the dataset), a link may name an object in another file (``ExternalLink``,
which HDF5 opens when the link is followed), a virtual dataset maps other files' datasets, and a
user-defined link runs a plug-in's code. And a dataset declares its shape: a sparse or compressed
dataset of a few hundred bytes on disk can declare terabytes, which a read allocates.

:func:`link_refusal` and :func:`dataset_refusal` say what is wrong with one link or dataset;
:func:`guard_file` checks a whole file before anything is read from it (flylib's own files,
through :func:`~flylib.results.hdf5.open_hdf5`); :mod:`flylib.interop._h5` walks to single
members of another tool's file with the same checks.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import h5py

from ..errors import FlylibError, ResultsError

__all__ = [
    "BUDGET_FLOOR",
    "MAX_EXPANSION",
    "dataset_refusal",
    "file_budget",
    "gib",
    "guard_file",
    "link_refusal",
]

#: The smallest per-dataset budget, whatever the file: small files still get room.
BUDGET_FLOOR = 64 << 20
#: How many bytes one stored byte of a dataset may declare in flylib's files: deflate expands at
#: most ~1032 times (an all-NaN array compresses ~190 times at flylib's level 1).
MAX_EXPANSION = 1100


def file_budget(path: str | Path) -> int:
    """Bytes a dataset may declare: :data:`MAX_EXPANSION` x file size, >= :data:`BUDGET_FLOOR`."""
    try:
        size = os.stat(path).st_size
    except OSError:
        size = 0
    return max(BUDGET_FLOOR, MAX_EXPANSION * size)


def gib(n: int) -> str:
    """``n`` bytes as ``"3.87 GiB"`` (MiB below one GiB, TiB from one TiB)."""
    if n >= 1 << 40:
        return f"{n / (1 << 40):.3g} TiB"
    return f"{n / (1 << 30):.3g} GiB" if n >= 1 << 30 else f"{n / (1 << 20):.3g} MiB"


def link_refusal(group: h5py.Group, key: bytes) -> str | None:
    """Why the link ``key`` of ``group`` must not be followed (``None``: a hard or soft link,
    which stays inside the file). The link is inspected, never followed."""
    from h5py import h5l

    links = group.id.links
    kind = links.get_info(key).type
    if kind in (h5l.TYPE_HARD, h5l.TYPE_SOFT):
        return None
    if kind == h5l.TYPE_EXTERNAL:
        filename, target = links.get_val(key)
        return (
            f"is an external link to {filename.decode('utf-8', 'replace')}:"
            f"{target.decode('utf-8', 'replace')}"
        )
    return f"is a user-defined link (type {kind})"


def dataset_refusal(dataset: h5py.Dataset, max_bytes: int) -> tuple[str, bool] | None:
    """Why ``dataset`` must not be read, or ``None``: ``(reason, outside)``, ``reason`` completing
    "<file>: '<name>' ..."; ``outside`` true when the data lives outside the file (external
    storage, a virtual dataset), false when the dataset (or one of its chunks, decompressed)
    declares more than ``max_bytes``."""
    external = dataset.external
    if external:
        return f"stores its data in the external file {external[0][0]!r}", True
    if dataset.is_virtual:
        sources = sorted({m.file_name for m in dataset.virtual_sources()})
        return f"is a virtual dataset mapping {', '.join(sources[:3])}", True
    itemsize = max(int(dataset.dtype.itemsize), 1)
    declared = math.prod(int(n) for n in dataset.shape or ()) * itemsize
    chunk = math.prod(int(n) for n in dataset.chunks) * itemsize if dataset.chunks else 0
    if max(declared, chunk) <= max_bytes:
        return None
    size = dataset.shape if declared >= chunk else f"chunks of {dataset.chunks}"
    return f"declares {size} of {dataset.dtype} ({gib(max(declared, chunk))})", False


def guard_file(
    fh: h5py.File,
    path: str | Path,
    fix: str,
    *,
    error: type[FlylibError] = ResultsError,
) -> None:
    """Check a whole open file before anything is read from it: every link is visited without
    being followed (soft links stay inside the file, so only objects checked here are reachable).

    Raises ``error``, one line naming ``path``, the object and ``fix`` (what the user should do),
    for an external or user-defined link, a dataset stored in other files, or one (or one of its
    chunks, decompressed) declaring more than :func:`file_budget`; a damaged link table or object
    header raises what h5py raises (OSError, KeyError, RuntimeError).
    """
    from h5py import h5l

    budget = file_budget(path)
    found: list[tuple[str, str, bool]] = []
    failed: list[BaseException] = []

    def check(name: bytes, info) -> bool:
        where = name.decode("utf-8", "replace")
        if info.type == h5l.TYPE_SOFT:
            return True
        if info.type != h5l.TYPE_HARD:
            parent, _, key = name.rpartition(b"/")
            group = fh[parent.decode("utf-8", "replace")] if parent else fh
            found.append((where, link_refusal(group, key) or "is not a plain link", True))
            return False
        obj = fh[where]
        reason = dataset_refusal(obj, budget) if isinstance(obj, h5py.Dataset) else None
        if reason is not None:
            found.append((where, *reason))
        return reason is None

    def visit(name: bytes, info) -> int | None:
        # an exception must not cross HDF5's C iteration: kept, re-raised after it
        try:
            return None if check(name, info) else 1
        except Exception as exc:
            failed.append(exc)
            return 1

    fh.id.links.visit(visit, info=True)
    if failed:
        raise failed[0]
    if not found:
        return
    where, reason, outside = found[0]
    if outside:
        raise error(
            f"{path}: {where!r} {reason}; flylib never writes such a file and reads one only "
            f"from its own bytes, never following a link out of it; {fix}"
        )
    raise error(
        f"{path}: {where!r} {reason}, more than the {gib(budget)} a file of its size can "
        f"hold (at most {MAX_EXPANSION}x its bytes, gzip's limit); refusing to read it; {fix}"
    )
