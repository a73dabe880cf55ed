"""Writing and reading the datasets and attributes of flylib's HDF5 files (the layout:
:mod:`flylib.results`); big arrays' chunks are deflated on threads. Every read goes through
:func:`read_dataset`: a damaged dataset is one ResultsError naming the file and the dataset."""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import h5py
import numpy as np

from ..errors import ResultsError
from ..resources import thread_map
from .checksums import damaged, fletcher32, verify_dataset

# Arrays with at least this many elements are chunked and compressed.
_COMPRESS_MIN_ELEMENTS = 4096
# Target size of one chunk: big enough for fast whole-array reads, within h5py's default 1 MiB
# chunk cache for cheap partial reads of a long recording.
_CHUNK_BYTES = 1024 * 1024
# gzip level 1 without the shuffle filter: smallest and fastest on detector output (NaN runs,
# heatmap-grid coordinates) and on continuous floats alike (benchmarks/results_io.py); any HDF5
# reader (MATLAB, R, h5py) decodes it. LZF would write faster on one core but only h5py reads it.
_COMPRESSION = {"compression": "gzip", "compression_opts": 1}
# chunks deflate on at most this many threads (fewer under a thread budget)
_DEFLATE_THREADS = 8
# Fletcher-32 on every dataset; off only for benchmarks/results_io.py's baseline.
FLETCHER32 = True


def _checksummed(payload: bytes) -> bytes:
    """A filtered chunk as the Fletcher-32 filter stores it: the data, then its checksum."""
    if not FLETCHER32:
        return payload
    return payload + struct.pack("<I", fletcher32(payload))


def read_dataset(dataset: h5py.Dataset) -> np.ndarray:
    """The whole dataset, its checksums verified by HDF5; damage is a ResultsError."""
    if dataset.dtype.kind == "c":  # NumPy would drop the imaginary part with only a warning
        raise ResultsError(
            f"{dataset.file.filename}: dataset {dataset.name} holds complex numbers, which "
            "flylib never writes: the file was not made by flylib or was altered; re-run "
            "the workflow to regenerate it"
        )
    try:
        return dataset[()]
    except OSError as err:
        path = dataset.file.filename
        verify_dataset(path, dataset)  # names the chunk whose checksum fails, if one does
        raise damaged(path, f"dataset {dataset.name}", err) from None


def write_array(group: h5py.Group, name: str, data: Any, dtype: Any = np.float64) -> h5py.Dataset:
    """Write ``data``; big arrays are chunked along their longest axis and compressed."""
    arr = np.asarray(data, dtype=dtype)
    if name in group:
        del group[name]
    if arr.size == 0 or arr.ndim == 0:  # no chunk to checksum (the header holds a scalar)
        return group.create_dataset(name, data=arr)
    if arr.size < _COMPRESS_MIN_ELEMENTS:
        if not FLETCHER32:
            return group.create_dataset(name, data=arr)
        return group.create_dataset(name, data=arr, chunks=arr.shape, fletcher32=True)
    axis = int(np.argmax(arr.shape))
    per_step = arr.itemsize * arr.size // arr.shape[axis]
    step = int(max(1, min(arr.shape[axis], _CHUNK_BYTES // max(per_step, 1))))
    chunks = list(arr.shape)
    chunks[axis] = step
    dataset = group.create_dataset(
        name,
        shape=arr.shape,
        dtype=arr.dtype,
        chunks=tuple(chunks),
        fletcher32=FLETCHER32,
        **_COMPRESSION,
    )
    _write_deflated_chunks(dataset, arr, axis, step)
    return dataset


def _write_deflated_chunks(dataset: h5py.Dataset, arr: np.ndarray, axis: int, step: int) -> None:
    """Fill a gzip-filtered dataset chunked in slabs of ``step`` along ``axis``.

    HDF5 compresses chunk by chunk on one core (most of the write time of a long recording's
    arrays); here zlib compresses the slabs on threads (it releases the GIL) and HDF5 stores the
    finished chunks as they are. The file is the one ``create_dataset(data=...,
    compression="gzip", fletcher32=True)`` writes: the same zlib stream followed by the
    Fletcher-32 checksum of the deflated bytes, readable and verified by any HDF5 reader.
    """
    starts = range(0, arr.shape[axis], step)

    def deflate(start: int) -> bytes:
        slab = arr[(slice(None),) * axis + (slice(start, start + step),)]
        if slab.shape[axis] < step:  # an edge chunk is stored whole, padded with zeros
            pad = [(0, 0)] * arr.ndim
            pad[axis] = (0, step - slab.shape[axis])
            slab = np.pad(slab, pad)
        return _checksummed(
            zlib.compress(np.ascontiguousarray(slab).tobytes(), _COMPRESSION["compression_opts"])
        )

    for start, payload in zip(starts, thread_map(deflate, starts, _DEFLATE_THREADS)):
        offset = tuple(start if i == axis else 0 for i in range(arr.ndim))
        dataset.id.write_direct_chunk(offset, payload)


def write_strings(group: h5py.Group, name: str, values: Sequence[str]) -> None:
    if name in group:
        del group[name]
    encoded = [str(v).encode("utf-8") for v in values]
    width = max([1, *map(len, encoded)])
    data = np.array(encoded, dtype=h5py.string_dtype("utf-8", width))
    kwargs = {"chunks": data.shape, "fletcher32": True} if data.size and FLETCHER32 else {}
    group.create_dataset(name, data=data, **kwargs)


def read_strings(dataset: h5py.Dataset) -> list[str]:
    values = read_dataset(dataset)
    return [
        v.decode("utf-8") if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel()
    ]


def json_attrs(group: h5py.Group, attrs: Mapping | None) -> None:
    for key, value in (attrs or {}).items():
        group.attrs[key] = json.dumps(value)


def read_json_attrs(group: h5py.Group) -> dict:
    out = {}
    for key, value in group.attrs.items():
        text = value.decode() if isinstance(value, bytes) else value
        try:
            out[key] = json.loads(text) if isinstance(text, str) else text
        except json.JSONDecodeError:
            out[key] = text
    return out
