"""Opening another tool's HDF5 file so that it cannot reach beyond itself.

A foreign HDF5 file (a SLEAP analysis file, a DeepLabCut ``.h5``) is untrusted input. HDF5 lets a
file borrow bytes from elsewhere: a dataset's raw data may live in other files (external storage,
``Dataset.external``), a link may name an object in another file (``ExternalLink``, which HDF5 opens
when the link is followed -- a FIFO there blocks forever), a virtual dataset maps other files'
datasets, and a soft link may route through any of these. And a dataset declares its shape: a sparse
or compressed dataset of a few hundred bytes on disk can declare terabytes, which a read allocates.

So members are looked up one path component at a time from the link table (:func:`foreign_member`),
never through h5py's ``in`` / ``[]`` on a full path (which resolves, and so opens, external links),
and a dataset is read only once :func:`checked_dataset` passes it. What makes a link or a dataset
unsafe is :mod:`flylib.results.guard`'s, which checks flylib's own files whole."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np

from ..errors import FlylibError, ImportFormatError, one_line
from ..results.guard import dataset_refusal, gib, link_refusal
from ..results.hdf5 import H5_READ_ERRORS, open_hdf5

__all__ = [
    "DEFAULT_READ_BUDGET",
    "H5_READ_ERRORS",
    "checked_dataset",
    "foreign_member",
    "read_budget",
    "read_checked",
    "reading_foreign_h5",
]

#: Bytes one dataset of a foreign file may hold when the recording's frame count is unknown (no
#: footage to count): 2 GiB, a 100,000-frame recording of 1,300 points.
DEFAULT_READ_BUDGET = 2 << 30
#: The smallest budget, whatever the recording: short recordings still get room.
_BUDGET_FLOOR = 64 << 20
#: Values one frame of one view may hold: (x, y, score) of up to 64 tracks or individuals of the
#: skeleton's points (at least 64 points, as a file may carry body parts the import maps away).
_TRACKS_PER_FRAME = 64
#: Soft links followed in one lookup before the chain is refused (a cycle, or a maze).
_MAX_SOFT_LINK_HOPS = 16


def read_budget(frames: int | None, points: int) -> int:
    """Bytes one dataset of a per-view foreign file may hold for this recording:
    ``frames x 3 values x 64 tracks x max(points, 64) x 8 bytes``, at least 64 MiB and at most
    :data:`DEFAULT_READ_BUDGET`; the latter when ``frames`` (the view's frame count, from its
    footage) is unknown. ``points``: the skeleton's point count."""
    if frames is None:
        return DEFAULT_READ_BUDGET
    per_frame = 3 * _TRACKS_PER_FRAME * max(int(points), 64) * 8
    return int(min(DEFAULT_READ_BUDGET, max(_BUDGET_FLOOR, int(frames) * per_frame)))


@contextmanager
def reading_foreign_h5(path: str | Path, what: str, hint: str) -> Iterator[h5py.File]:
    """Open ``path`` read-only (:func:`~flylib.results.hdf5.open_hdf5`: a missing or unreadable file
    is one :class:`ImportFormatError` naming ``what`` and ``hint``); h5py read errors
    (:data:`H5_READ_ERRORS`) inside the block are re-raised as one-line :class:`ImportFormatError`
    naming ``path``, flylib's own errors pass unchanged."""
    with open_hdf5(path, hint, what, error=ImportFormatError, guard=False) as fh:
        try:
            yield fh
        except FlylibError:
            raise
        except H5_READ_ERRORS as exc:
            raise ImportFormatError(
                f"{path}: damaged or not a {what} ({type(exc).__name__}: {one_line(exc)}); {hint}"
            ) from None


def _refuse(path, where: str, reason: str, what: str, hint: str) -> ImportFormatError:
    return ImportFormatError(
        f"{path}: {where!r} {reason}; flylib reads a {what} only from the file's own bytes "
        f"and never follows a link out of it; {hint}"
    )


def foreign_member(
    fh: h5py.File, name: str, path: str | Path, what: str, hint: str, *, _hops: int = 0
) -> h5py.Group | h5py.Dataset | h5py.Datatype | None:
    """The object at ``name`` (``"df_with_missing/table"``) inside ``fh``, reached without leaving
    the file; ``None`` when no link of that path exists. ``path``, ``what`` and ``hint`` (the file,
    what it should be, the fix) are for messages. A path component that is an external or
    user-defined link (not followed), or a chain of more than 16 soft links, is an
    :class:`ImportFormatError`."""
    from h5py import h5l

    if _hops > _MAX_SOFT_LINK_HOPS:
        raise _refuse(path, name, "is a chain of more than 16 soft links", what, hint)
    node: h5py.Group | h5py.Dataset | h5py.Datatype = fh
    parts = [p for p in name.split("/") if p and p != "."]
    for i, part in enumerate(parts):
        if not isinstance(node, h5py.Group):
            return None
        key = part.encode("utf-8")
        where = "/".join(parts[: i + 1])
        links = node.id.links
        if not links.exists(key):
            return None
        refusal = link_refusal(node, key)
        if refusal is not None:
            raise _refuse(path, where, refusal, what, hint)
        if links.get_info(key).type == h5l.TYPE_HARD:
            node = node[part]
        else:  # a soft link: resolved by the same walk
            target = links.get_val(key).decode("utf-8", "replace")
            if not target.startswith("/"):
                target = f"{node.name.rstrip('/')}/{target}"
            resolved = foreign_member(fh, target, path, what, hint, _hops=_hops + 1)
            if resolved is None:
                return None
            node = resolved
    return node


def checked_dataset(
    fh: h5py.File, name: str, path: str | Path, what: str, hint: str, *, max_bytes: int
) -> h5py.Dataset | None:
    """The dataset at ``name`` (as for :func:`foreign_member`), checked to be safe to read whole;
    ``None`` if absent. A member that is no dataset, keeps its data in other files (external
    storage, a virtual dataset), or declares more than ``max_bytes`` (:func:`read_budget`; the
    dataset or any one chunk, decompressed) is an :class:`ImportFormatError`: a sparse or compressed
    "bomb" is refused before anything is allocated."""
    obj = foreign_member(fh, name, path, what, hint)
    if obj is None:
        return None
    if not isinstance(obj, h5py.Dataset):
        raise ImportFormatError(
            f"{path}: {name!r} is a {type(obj).__name__.lower()}, expected a dataset; {hint}"
        )
    refusal = dataset_refusal(obj, max_bytes)
    if refusal is None:
        return obj
    reason, outside = refusal
    if outside:
        raise _refuse(path, name, reason, what, hint)
    raise ImportFormatError(
        f"{path}: {name!r} {reason}, more than the {gib(max_bytes)} a {what} of this "
        f"recording can need (frames x points x tracks); refusing to read it; {hint}"
    )


def read_checked(
    fh: h5py.File, name: str, path: str | Path, what: str, hint: str, *, max_bytes: int
) -> np.ndarray | None:
    """The whole dataset at ``name`` (``None`` if absent), after :func:`checked_dataset`."""
    obj = checked_dataset(fh, name, path, what, hint, max_bytes=max_bytes)
    return None if obj is None else obj[()]
