"""HDF5's Fletcher-32 checksum (:func:`fletcher32`, for the threaded deflate of
:mod:`flylib.results.datasets` and for checking raw chunks) and the integrity checks built on it:
:func:`verify_file` (a whole file), :func:`verify_dataset` and :func:`check_group` (the loaders)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import ResultsError, one_line
from .guard import guard_file

# Word weights n, n-1, ..., 1 (mod 65535), grown on demand: the tail of this array is the weight
# vector of any shorter buffer. Integer dot products (no BLAS threads competing with the deflate
# threads) stay exact in int64.
_WEIGHTS = np.zeros(0, np.int64)


def fletcher32(data: bytes) -> int:
    """HDF5's Fletcher-32 checksum of ``data`` (``H5_checksum_fletcher32``).

    Sums big-endian 16-bit words (an odd last byte is the high byte of a last word) in
    ones'-complement arithmetic modulo 65535, a non-zero sum represented in ``1..65535``; returns
    ``(sum2 << 16) | sum1``. The filter appends it to each chunk as 4 little-endian bytes.
    """
    global _WEIGHTS
    raw = np.frombuffer(data, np.uint8)
    if raw.size % 2:
        raw = np.concatenate([raw, np.zeros(1, np.uint8)])
    n = raw.size // 2
    words = raw.view(">u2").astype(np.int64)
    table = _WEIGHTS
    if table.size < n:
        table = _WEIGHTS = np.arange(max(n, 1 << 19), 0, -1, dtype=np.int64) % 65535
    # word i is in the running sum of every later position: weight n - i
    total, weighted = int(words.sum()), int(np.dot(words, table[table.size - n :]))
    if total == 0:
        return 0

    def fold(value: int) -> int:
        return (value - 1) % 65535 + 1  # value > 0 here

    return (fold(weighted) << 16) | fold(total)


def damaged(path: str | Path, what: str, err: BaseException) -> ResultsError:
    return ResultsError(
        f"{path}: {what} is damaged (HDF5: {one_line(err)}); the file is corrupt: delete it "
        "and re-run the workflow to regenerate it"
    )


def verify_file(path: str | Path, *, unchecked: list[str] | None = None) -> list[str]:
    """Check every dataset and attribute of an HDF5 file against its checksums: one line per
    damaged object (file and dataset or group named).

    Reads each dataset chunk by chunk (HDF5 verifies the Fletcher-32 checksum of every chunk and
    the checksum of every object header it loads). ``unchecked``, when given, receives the names
    of non-empty datasets that carry no checksum (readable, but not verifiable).
    """
    problems: list[str] = []
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        return [str(damaged(path, "its HDF5 structure", err))]
    try:  # nothing is read from a file that reaches beyond itself
        guard_file(f, path, "pass the results.h5 a run wrote, or re-run the workflow")
    except ResultsError as refused:
        f.close()
        return [str(refused)]
    except (OSError, KeyError, RuntimeError, ValueError) as err:
        f.close()
        return [str(damaged(path, "its HDF5 structure", err))]

    def visit(group: h5py.Group) -> None:
        try:
            names = list(group.keys())
            dict(group.attrs.items())
        except (OSError, KeyError, RuntimeError) as err:
            problems.append(str(damaged(path, f"group {group.name}", err)))
            return
        for name in names:
            try:
                item = group[name]
            except (OSError, KeyError, RuntimeError) as err:
                problems.append(str(damaged(path, f"object {group.name.rstrip('/')}/{name}", err)))
                continue
            if isinstance(item, h5py.Group):
                visit(item)
                continue
            try:
                dict(item.attrs.items())
                if item.size and item.chunks is not None:
                    for chunk in item.iter_chunks():
                        item[chunk]
                else:
                    item[()]
            except (OSError, RuntimeError) as err:
                try:
                    verify_dataset(path, item)  # the chunk whose checksum fails, if one does
                except ResultsError as precise:
                    problems.append(str(precise))
                else:
                    problems.append(str(damaged(path, f"dataset {item.name}", err)))
                continue
            if unchecked is not None and item.size and not item.fletcher32:
                unchecked.append(item.name)

    with f:
        visit(f)
    return problems


def verify_dataset(path: str | Path, dataset: h5py.Dataset) -> None:
    """Check a dataset against its stored checksums without decompressing it: its chunks are
    read raw and their checksums recomputed (a fraction of the cost of decoding them). A
    mismatch is a ResultsError naming the file and the dataset."""
    if not (dataset.size and dataset.chunks is not None and dataset.fletcher32):
        return  # no checksum to check (an empty array, or a file of an older flylib)
    try:
        dsid = dataset.id
        for i in range(dsid.get_num_chunks()):
            info = dsid.get_chunk_info(i)
            _, raw = dsid.read_direct_chunk(info.chunk_offset)
            if len(raw) < 4 or int.from_bytes(raw[-4:], "little") != fletcher32(raw[:-4]):
                raise OSError(
                    f"Fletcher-32 checksum mismatch in the chunk at {tuple(info.chunk_offset)}"
                )
    except (OSError, RuntimeError, ValueError) as err:
        raise damaged(path, f"dataset {dataset.name}", err) from None


def check_group(path: str | Path, group: h5py.Group, skip: Sequence[str] = ()) -> None:
    """Verify every dataset under ``group`` (but those named in ``skip``, already read)."""
    datasets: list[h5py.Dataset] = []

    def collect(name: str, item: Any) -> None:
        if isinstance(item, h5py.Dataset) and item.name not in skip:
            datasets.append(item)

    try:
        group.visititems(collect)
    except (OSError, KeyError, RuntimeError) as err:
        raise damaged(path, f"group {group.name}", err) from None
    for dataset in datasets:
        verify_dataset(path, dataset)
