"""HDF5 results (schema version 2) and the per-stage artifacts they are assembled from.

Every file holds ``attrs["meta"]`` (JSON: ``deeperfly_format_version``,
``flylib_version``, ``created_utc``, ``stage``) and the group of each stage that
produced it; ``results.h5`` is the union of the stage files plus ``skeleton/`` and the
config rig as ``pose2d/cameras``. Group attributes are stored as JSON text. Arrays are
float64 (NaN = missing), chunked along their longest axis (time) and gzip-compressed
once they are large, so a 100k-frame recording stays small.

Every write goes to a temporary sibling first and is renamed into place on success
(:func:`atomic_path`), so an interrupted run never leaves a truncated file.

Integrity: every non-empty dataset carries HDF5's Fletcher-32 checksum filter, and
files are written with HDF5 1.8's object-header format, whose metadata (object
headers with their attributes, link tables, the superblock) carries checksums too;
HDF5 verifies both on every read, so a damaged file fails to load with a
:class:`~flylib.errors.ResultsError` naming the file and the dataset
(:func:`verify_file` checks a whole file, as ``flylib inspect`` does). Names are
stored as fixed-length UTF-8 strings, inside the checksummed chunks.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from .errors import FlylibError, ResultsError, one_line
from .hdf5_files import open_h5
from .paths import atomic_path, out_of_space
from .resources import thread_map
from .skeleton import Skeleton

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from .cameras import CameraGroup

__all__ = [
    "ARTIFACTS",
    "FORMAT_VERSION",
    "STAGE_GROUPS",
    "PoseResult",
    "Pose2dData",
    "assemble_results",
    "atomic_path",
    "load_candidates",
    "open_checked",
    "read_cameras",
    "read_meta",
    "read_skeleton",
    "read_image_sizes",
    "read_stage",
    "save_candidates",
    "verify_file",
    "write_analysis",
    "write_stage",
]

#: The results.h5 schema version this code writes and accepts.
FORMAT_VERSION = 2
#: Stage-artifact file names inside ``<outdir>/stages/``.
ARTIFACTS: dict[str, str] = {
    "pose2d": "pose2d.h5",
    "bundle_adjustment": "bundle_adjustment.h5",
    "pictorial_structures": "pictorial_structures.h5",
    "triangulation": "triangulation.h5",
    "refinement": "refinement.h5",
}
#: Stages that own a group in results.h5, in pipeline order.
STAGE_GROUPS: tuple[str, ...] = (
    "pose2d",
    "bundle_adjustment",
    "pictorial_structures",
    "triangulation",
    "refinement",
)

# Arrays with at least this many elements are chunked and compressed.
_COMPRESS_MIN_ELEMENTS = 4096
# Target size of one chunk: big enough for fast whole-array reads, within h5py's
# default 1 MiB chunk cache for cheap partial reads of a long recording.
_CHUNK_BYTES = 1024 * 1024
# gzip level 1 without the shuffle filter: measured smallest and fastest on detector
# output (NaN runs, heatmap-grid coordinates) and on continuous floats alike
# (benchmarks/results_io.py); any HDF5 reader (MATLAB, R, h5py) can decode it. The
# chunks are deflated on threads (see _write_deflated_chunks): LZF would write faster
# on one core but only h5py reads it.
_COMPRESSION = {"compression": "gzip", "compression_opts": 1}
# chunks deflate on at most this many threads (fewer under a thread budget)
_DEFLATE_THREADS = 8
# HDF5 1.8's file format: object headers, link tables and the superblock carry
# checksums (readable by any HDF5 >= 1.8, i.e. since 2008).
_LIBVER = ("v108", "latest")
# Fletcher-32 on every dataset; off only for benchmarks/results_io.py's baseline.
_FLETCHER32 = True


def _create(path: str | Path) -> h5py.File:
    """A new HDF5 file in the checksummed metadata format."""
    return h5py.File(path, "w", libver=_LIBVER)


# -- checksums -----------------------------------------------------------------


# Word weights n, n-1, ..., 1 (mod 65535), grown on demand: the tail of this array
# is the weight vector of any shorter buffer. Integer dot products (no BLAS threads
# competing with the deflate threads) stay exact in int64.
_WEIGHTS = np.zeros(0, np.int64)


def fletcher32(data: bytes) -> int:
    """HDF5's Fletcher-32 checksum of ``data`` (``H5_checksum_fletcher32``).

    Sums big-endian 16-bit words (an odd last byte is the high byte of a last word)
    in ones'-complement arithmetic modulo 65535, where a non-zero sum is represented
    in ``1..65535``; returns ``(sum2 << 16) | sum1``. The filter appends it to each
    filtered chunk as 4 little-endian bytes.
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


def _checksummed(payload: bytes) -> bytes:
    """A filtered chunk as the Fletcher-32 filter stores it: the data, then its checksum."""
    if not _FLETCHER32:
        return payload
    return payload + struct.pack("<I", fletcher32(payload))


def _damaged(path: str | Path, what: str, err: BaseException) -> ResultsError:
    return ResultsError(
        f"{path}: {what} is damaged (HDF5: {one_line(err)}); the file is corrupt: delete it "
        "and re-run the workflow to regenerate it"
    )


def _read(dataset: h5py.Dataset) -> np.ndarray:
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
        _verify_dataset(path, dataset)  # names the chunk whose checksum fails, if one does
        raise _damaged(path, f"dataset {dataset.name}", err) from None


def verify_file(path: str | Path, *, unchecked: list[str] | None = None) -> list[str]:
    """Check every dataset and attribute of an HDF5 file against its checksums.

    Reads each dataset chunk by chunk (HDF5 verifies the Fletcher-32 checksum of
    every chunk and the checksum of every object header it loads).

    Parameters
    ----------
    path
        A results or stage-artifact file.
    unchecked
        When given, receives the names of non-empty datasets that carry no checksum
        (files of an older flylib): readable, but their integrity cannot be verified.

    Returns
    -------
    list of str
        One line per damaged object (file and dataset or group named); empty when
        the file is intact.
    """
    problems: list[str] = []
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        return [str(_damaged(path, "its HDF5 structure", err))]

    def visit(group: h5py.Group) -> None:
        try:
            names = list(group.keys())
            dict(group.attrs.items())
        except (OSError, KeyError, RuntimeError) as err:
            problems.append(str(_damaged(path, f"group {group.name}", err)))
            return
        for name in names:
            try:
                item = group[name]
            except (OSError, KeyError, RuntimeError) as err:
                problems.append(str(_damaged(path, f"object {group.name.rstrip('/')}/{name}", err)))
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
                    _verify_dataset(path, item)  # the chunk whose checksum fails, if one does
                except ResultsError as precise:
                    problems.append(str(precise))
                else:
                    problems.append(str(_damaged(path, f"dataset {item.name}", err)))
                continue
            if unchecked is not None and item.size and not item.fletcher32:
                unchecked.append(item.name)

    with f:
        visit(f)
    return problems


def _verify_dataset(path: str | Path, dataset: h5py.Dataset) -> None:
    """Check a dataset against its stored checksums without decompressing it.

    A Fletcher-32-filtered dataset's chunks are read raw and their checksums
    recomputed (a fraction of the cost of decoding them); a dataset without the
    filter has nothing to check.

    Raises
    ------
    ResultsError
        Naming the file and the dataset, when a checksum does not match.
    """
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
        raise _damaged(path, f"dataset {dataset.name}", err) from None


def _check_group(path: str | Path, group: h5py.Group, skip: Sequence[str] = ()) -> None:
    """Verify every dataset under ``group`` (but those named in ``skip``, already read)."""
    datasets: list[h5py.Dataset] = []

    def collect(name: str, item: Any) -> None:
        if isinstance(item, h5py.Dataset) and item.name not in skip:
            datasets.append(item)

    try:
        group.visititems(collect)
    except (OSError, KeyError, RuntimeError) as err:
        raise _damaged(path, f"group {group.name}", err) from None
    for dataset in datasets:
        _verify_dataset(path, dataset)


# -- low-level helpers ---------------------------------------------------------


def _new_meta(stage: str, extra: Mapping | None = None) -> dict:
    from . import __version__

    return {
        **(extra or {}),
        "deeperfly_format_version": FORMAT_VERSION,
        "flylib_version": __version__,
        "created_utc": datetime.now(UTC).isoformat(),
        "stage": stage,
    }


def _write_array(group: h5py.Group, name: str, data: Any, dtype: Any = np.float64) -> h5py.Dataset:
    """Write ``data``; big arrays are chunked along their longest axis and compressed."""
    arr = np.asarray(data, dtype=dtype)
    if name in group:
        del group[name]
    if arr.size == 0 or arr.ndim == 0:  # no chunk to checksum (the header holds a scalar)
        return group.create_dataset(name, data=arr)
    if arr.size < _COMPRESS_MIN_ELEMENTS:
        if not _FLETCHER32:
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
        fletcher32=_FLETCHER32,
        **_COMPRESSION,
    )
    _write_deflated_chunks(dataset, arr, axis, step)
    return dataset


def _write_deflated_chunks(dataset: h5py.Dataset, arr: np.ndarray, axis: int, step: int) -> None:
    """Fill a gzip-filtered dataset chunked in slabs of ``step`` along ``axis``.

    HDF5 compresses chunk by chunk on one core (most of the write time of a long
    recording's arrays); here zlib compresses the slabs on threads (it releases the
    GIL) and HDF5 stores the finished chunks as they are. The file is the one
    ``create_dataset(data=..., compression="gzip", fletcher32=True)`` writes: the same
    deflate filter and zlib stream followed by the Fletcher-32 checksum of the
    deflated bytes (what HDF5's filter appends), readable and verified by any HDF5
    reader.
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


def _write_strings(group: h5py.Group, name: str, values: Sequence[str]) -> None:
    if name in group:
        del group[name]
    encoded = [str(v).encode("utf-8") for v in values]
    width = max([1, *map(len, encoded)])
    data = np.array(encoded, dtype=h5py.string_dtype("utf-8", width))
    kwargs = {"chunks": data.shape, "fletcher32": True} if data.size and _FLETCHER32 else {}
    group.create_dataset(name, data=data, **kwargs)


def _read_strings(dataset: h5py.Dataset) -> list[str]:
    values = _read(dataset)
    return [
        v.decode("utf-8") if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel()
    ]


def _json_attrs(group: h5py.Group, attrs: Mapping | None) -> None:
    for key, value in (attrs or {}).items():
        group.attrs[key] = json.dumps(value)


def _read_json_attrs(group: h5py.Group) -> dict:
    out = {}
    for key, value in group.attrs.items():
        text = value.decode() if isinstance(value, bytes) else value
        try:
            out[key] = json.loads(text) if isinstance(text, str) else text
        except json.JSONDecodeError:
            out[key] = text
    return out


def open_hdf5(path: str | Path, fix: str, what: str = "HDF5 file") -> h5py.File:
    """Open a flylib HDF5 file for reading; a missing or non-HDF5 file is one
    :class:`ResultsError` naming the file and ``fix`` (what the user should do)."""
    return open_h5(path, error=ResultsError, what=what, fix=fix)


@contextmanager
def open_checked(path: str | Path, rerun: str = "re-run the workflow") -> Iterator[h5py.File]:
    """Open a flylib HDF5 file (results or stage artifact) read-only, checking its version.

    Parameters
    ----------
    path
        The file.
    rerun
        What the user should do when the file is missing or stale, for the message.

    Raises
    ------
    ResultsError
        Missing, not HDF5, not a flylib file, or a different format version.
    """
    path = Path(path)
    with open_hdf5(path, rerun) as f:
        try:
            version = read_meta_from(f).get("deeperfly_format_version")
        except (OSError, KeyError, RuntimeError) as err:
            raise _damaged(path, "its root attributes", err) from None
        if version is None:
            raise ResultsError(
                f"{path}: not a flylib file (no format version in its meta); {rerun} to regenerate it"
            )
        if version != FORMAT_VERSION:
            raise ResultsError(
                f"{path}: format version {version!r}, expected {FORMAT_VERSION}; {rerun} to regenerate it"
            )
        try:
            yield f
        except (OSError, RuntimeError) as err:  # a damaged object header, link table, ...
            if out_of_space(err) is not None:
                raise  # a write in the block failed (atomic_path reports it), not this file
            raise _damaged(path, "an HDF5 object", err) from None
        except KeyError as err:
            if "Unable to" not in str(err):  # h5py's words for an object HDF5 could not load
                raise
            raise _damaged(path, "an HDF5 object", err) from None


#: What reading a damaged file raises below flylib: h5py's OSError (a bad B-tree, a
#: failed filter or checksum, a truncated file), KeyError (a link that does not resolve),
#: ValueError/TypeError (a dataset of another dtype or shape), RuntimeError (low-level
#: HDF5 failures), and IndexError/AttributeError (JSON attributes of an unexpected type).
_DAMAGE_ERRORS = (
    OSError,
    KeyError,
    ValueError,
    TypeError,
    RuntimeError,
    IndexError,
    AttributeError,
)


@contextmanager
def _read_checked(path: str | Path, rerun: str) -> Iterator[h5py.File]:
    """:func:`open_checked` for the loaders: a read that fails inside the block (the
    file is damaged) raises :class:`ResultsError` naming the file, not h5py's error."""
    try:
        with open_checked(path, rerun) as f:
            yield f
    except ResultsError:
        raise
    except FlylibError as err:  # stored content a constructor refuses (e.g. a skeleton's limbs)
        detail = " ".join(str(err).split())[:300]
        raise ResultsError(f"{path}: invalid content ({detail}); {rerun}") from None
    except _DAMAGE_ERRORS as err:
        detail = " ".join(str(err).split())[:300]
        raise ResultsError(
            f"{path}: damaged or unreadable ({type(err).__name__}: {detail}); {rerun}"
        ) from None


def read_meta_from(f: h5py.File) -> dict:
    """The ``meta`` JSON of an open file (empty when absent or unreadable)."""
    raw = f.attrs.get("meta")
    if raw is None:
        return {}
    try:
        meta = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
    except (json.JSONDecodeError, TypeError):
        return {}
    return meta if isinstance(meta, dict) else {}


def read_meta(path: str | Path) -> dict:
    """The ``meta`` JSON of a flylib HDF5 file (no version check).

    Parameters
    ----------
    path
        A results or stage-artifact file.

    Returns
    -------
    dict
        The parsed meta; empty if the file has none.

    Raises
    ------
    ResultsError
        Not HDF5, or its root object (header, attributes) damaged: one line naming it.
    """
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise ResultsError(f"{path}: not a readable HDF5 file ({err})") from None
    with f:
        try:
            return read_meta_from(f)
        except (OSError, KeyError, RuntimeError) as err:  # a damaged root object header
            raise _damaged(path, "its root attributes", err) from None


# -- cameras and skeleton groups ----------------------------------------------


def _write_cameras(group: h5py.Group, cameras: CameraGroup) -> None:
    """Store a rig as ``names``, ``rvecs``, ``tvecs``, ``intrs`` ([fx, fy, cx, cy]), ``dists``."""
    _write_strings(group, "names", cameras.names)
    for name in ("rvecs", "tvecs", "intrs", "dists"):
        _write_array(group, name, getattr(cameras, name))


def _read_cameras(group: h5py.Group) -> CameraGroup:
    from .cameras import CameraGroup

    return CameraGroup.from_arrays(
        _read_strings(group["names"]),
        _read(group["rvecs"]),
        _read(group["tvecs"]),
        _read(group["intrs"]),
        _read(group["dists"]),
    )


def _write_skeleton(group: h5py.Group, skeleton: Skeleton) -> None:
    group.attrs["name"] = skeleton.name
    _write_strings(group, "point_names", skeleton.point_names)
    _write_strings(group, "limb_names", skeleton.limb_names)
    _write_array(group, "limb_id", skeleton.limb_id, dtype=np.int64)
    _write_array(group, "bones", skeleton.bones, dtype=np.int64)
    palette = group.create_group("palette")
    for limb, color in skeleton.palette.items():
        palette.attrs[limb] = color


def _read_skeleton(group: h5py.Group) -> Skeleton:
    name = group.attrs.get("name", "skeleton")
    palette = (
        {str(k): str(v) for k, v in group["palette"].attrs.items()} if "palette" in group else {}
    )
    return Skeleton.from_arrays(
        _read_strings(group["point_names"]),
        _read_strings(group["limb_names"]),
        _read(group["limb_id"]),
        _read(group["bones"]),
        palette=palette,
        name=str(name),
    )


def read_skeleton(path: str | Path) -> Skeleton:
    """The skeleton stored in a results or stage file's ``skeleton/`` group.

    Raises
    ------
    ResultsError
        If the file is missing, of another version, or has no skeleton.
    """
    with _read_checked(path, "re-run the pipeline") as f:
        if "skeleton" not in f:
            raise ResultsError(f"{path}: has no skeleton/ group; re-run pose2d")
        return _read_skeleton(f["skeleton"])


def read_cameras(path: str | Path, group: str) -> CameraGroup:
    """The rig stored in ``<group>/cameras`` of a results or stage file.

    Parameters
    ----------
    path
        The HDF5 file.
    group
        The stage group, e.g. ``"bundle_adjustment"``.

    Raises
    ------
    ResultsError
        If the file is missing, of another version, or has no such rig.
    """
    with _read_checked(path, f"re-run {group}") as f:
        if f"{group}/cameras" not in f:
            raise ResultsError(f"{path}: has no {group}/cameras group; re-run {group}")
        return _read_cameras(f[f"{group}/cameras"])


def read_image_sizes(path: str | Path) -> dict[str, tuple[int, int]]:
    """``view -> (height, width)`` of a pose2d artifact or results file, without
    reading its arrays.

    Raises
    ------
    ResultsError
        If the file is missing, of another version, or has no pose2d group.
    """
    with _read_checked(path, "re-run the pose2d stage") as f:
        if "pose2d" not in f:
            raise ResultsError(f"{path}: has no pose2d group; re-run the pose2d stage")
        sizes = _read_json_attrs(f["pose2d"]).get("image_sizes") or {}
        return {str(k): (int(v[0]), int(v[1])) for k, v in sizes.items()}


# -- the assembled result ------------------------------------------------------


def _float_or_none(value: Any) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)


@dataclass
class PoseResult:
    """A complete multi-view pose estimate of one recording.

    Attributes
    ----------
    cameras
        The rig (bundle-adjusted when that stage ran).
    skeleton
        The tracked skeleton.
    pts2d
        ``(V, T, P, 2)`` 2D points in raw-frame pixels, NaN = missing.
    conf
        ``(V, T, P)`` detector confidences, or ``None``.
    pts3d
        ``(T, P, 3)`` 3D points, NaN = not reconstructed, or ``None``.
    reproj_error
        ``(V, T, P)`` reprojection error in pixels, or ``None``.
    meta
        Free-form metadata (format version, creation time, ...).
    image_sizes
        ``view -> (height, width)`` of the raw footage, when known.
    """

    cameras: CameraGroup
    skeleton: Skeleton
    pts2d: Float[np.ndarray, "V T P 2"]
    conf: Float[np.ndarray, "V T P"] | None = None
    pts3d: Float[np.ndarray, "T P 3"] | None = None
    reproj_error: Float[np.ndarray, "V T P"] | None = None
    meta: dict = field(default_factory=dict)
    image_sizes: dict[str, tuple[int, int]] | None = None

    def __post_init__(self) -> None:
        self.pts2d = np.asarray(self.pts2d, dtype=np.float64)
        self.conf = _float_or_none(self.conf)
        self.pts3d = _float_or_none(self.pts3d)
        self.reproj_error = _float_or_none(self.reproj_error)
        if self.pts2d.ndim != 4 or self.pts2d.shape[-1] != 2:
            raise ValueError(f"pts2d must be (V, T, P, 2), got shape {self.pts2d.shape}")
        v, t, p, _ = self.pts2d.shape
        expected = {"conf": (v, t, p), "pts3d": (t, p, 3), "reproj_error": (v, t, p)}
        for name, shape in expected.items():
            arr = getattr(self, name)
            if arr is not None and arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape} to match pts2d, got {arr.shape}")
        if p != self.skeleton.n_points:
            raise ValueError(f"pts2d has {p} points but the skeleton has {self.skeleton.n_points}")
        if v != len(self.cameras):
            raise ValueError(f"pts2d has {v} views but the rig has {len(self.cameras)} cameras")

    @property
    def n_views(self) -> int:
        """Number of views ``V``."""
        return self.pts2d.shape[0]

    @property
    def n_frames(self) -> int:
        """Number of frames ``T``."""
        return self.pts2d.shape[1]

    @property
    def n_points(self) -> int:
        """Number of points ``P``."""
        return self.pts2d.shape[2]

    def save(self, path: str | Path) -> None:
        """Write the result to an HDF5 file, atomically (an existing file is replaced).

        ``pts2d``/``conf`` and the rig go to ``pose2d/``; when a 3D pose is present,
        ``pts2d``, ``pts3d`` and ``reproj_error`` also go to ``triangulation/``, so
        :meth:`load` returns the same result.

        Parameters
        ----------
        path
            Destination ``.h5`` file.
        """
        # A loaded result keeps its creation time and stage; version fields are this writer's.
        fresh = _new_meta("result")
        meta = {**fresh, **self.meta}
        meta["deeperfly_format_version"] = fresh["deeperfly_format_version"]
        meta["flylib_version"] = fresh["flylib_version"]
        with atomic_path(path) as tmp, _create(tmp) as f:
            f.attrs["meta"] = json.dumps(meta)
            _write_skeleton(f.create_group("skeleton"), self.skeleton)
            g2d = f.create_group("pose2d")
            _write_array(g2d, "points", self.pts2d)
            if self.conf is not None:
                _write_array(g2d, "conf", self.conf)
            _write_cameras(g2d.create_group("cameras"), self.cameras)
            _json_attrs(g2d, {"view_names": list(self.cameras.names)})
            if self.image_sizes is not None:
                _json_attrs(g2d, {"image_sizes": {k: list(v) for k, v in self.image_sizes.items()}})
            if self.pts3d is not None or self.reproj_error is not None:
                g3d = f.create_group("triangulation")
                _write_array(g3d, "points", self.pts2d)
                if self.pts3d is not None:
                    _write_array(g3d, "points3d", self.pts3d)
                if self.reproj_error is not None:
                    _write_array(g3d, "reproj_error", self.reproj_error)

    @classmethod
    def load(cls, path: str | Path) -> PoseResult:
        """Read the assembled result back, preferring the most-derived data present.

        ``pts2d``: refinement, else triangulation, else pictorial_structures, else
        pose2d. ``pts3d`` and ``reproj_error``: refinement, else triangulation, else
        pictorial_structures. Cameras:
        bundle_adjustment, else the config rig in pose2d. ``conf``: pose2d.

        Parameters
        ----------
        path
            A file written by :meth:`save` or :func:`assemble_results`.

        Returns
        -------
        PoseResult
            The assembled result.

        Raises
        ------
        ResultsError
            If the file is missing, of another format version, or has no pose2d data
            or no rig.
        """
        rerun = "re-run the pipeline"
        with _read_checked(path, rerun) as f:
            if "pose2d/points" not in f:
                raise ResultsError(f"{path}: has no pose2d group (no 2D points); {rerun}")
            if "skeleton" not in f:
                raise ResultsError(f"{path}: has no skeleton group; {rerun}")
            meta = read_meta_from(f)
            meta.pop("deeperfly_format_version", None)
            skeleton = _read_skeleton(f["skeleton"])
            rig = next(
                (f[f"{s}/cameras"] for s in ("bundle_adjustment", "pose2d") if f"{s}/cameras" in f),
                None,
            )
            if rig is None:
                raise ResultsError(
                    f"{path}: has no cameras (pose2d/cameras); assemble it with assemble_results"
                )
            cameras = _read_cameras(rig)

            read: list[str] = []

            def first(name: str, stages: tuple[str, ...]) -> np.ndarray | None:
                stage = next((s for s in stages if f"{s}/{name}" in f), None)
                if stage is None:
                    return None
                read.append(f"/{stage}/{name}")
                return _read(f[f"{stage}/{name}"])

            derived = ("refinement", "triangulation", "pictorial_structures")
            pts2d = first("points", (*derived, "pose2d"))
            pts3d = first("points3d", derived)
            reproj = first("reproj_error", derived)
            conf = first("conf", ("pose2d",))
            sizes = _read_json_attrs(f["pose2d"]).get("image_sizes")
            _check_group(path, f, skip=read)  # damage in what was not loaded is damage too
            return cls(  # inside the block: a shape mismatch of a damaged file names the file
                cameras=cameras,
                skeleton=skeleton,
                pts2d=pts2d,
                conf=conf,
                pts3d=pts3d,
                reproj_error=reproj,
                meta=meta,
                image_sizes=None if sizes is None else {k: tuple(v) for k, v in sizes.items()},
            )


# -- the pose2d artifact -------------------------------------------------------


def _make_candidates(xy: np.ndarray, score: np.ndarray) -> Any:
    from .pictorial import Candidates

    return Candidates(xy=xy, score=score)


def _write_candidates(group: h5py.Group, candidates: Any) -> None:
    _write_array(group, "xy", candidates.xy)
    _write_array(group, "score", candidates.score)


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
    with atomic_path(path) as tmp, _create(tmp) as f:
        f.attrs["meta"] = json.dumps(_new_meta("candidates", meta))
        _write_candidates(f.create_group("candidates"), candidates)


def load_candidates(path: str | Path) -> Any:
    """Read what :func:`save_candidates` wrote.

    Raises
    ------
    ResultsError
        If the file is missing, of another version, or holds no candidates.
    """
    rerun = "re-run the pose2d stage with pictorial structures on"
    with _read_checked(path, rerun) as f:
        if "candidates/xy" not in f:
            raise ResultsError(f"{path}: holds no candidate peaks; {rerun}")
        return _make_candidates(_read(f["candidates/xy"]), _read(f["candidates/score"]))


@dataclass
class Pose2dData:
    """The pose2d stage's output, from the detector or imported from another tool.

    Attributes
    ----------
    pts2d
        ``(V, T, P, 2)`` raw-frame pixels, NaN = missing.
    conf
        ``(V, T, P)`` confidences.
    view_names
        The V axis: camera names in config order.
    image_sizes
        ``view -> (height, width)`` of the raw footage.
    candidates
        Top-K peaks (``xy`` ``(V, T, P, K, 2)``, ``score`` ``(V, T, P, K)``) when
        pictorial structures is on, else ``None``.
    """

    pts2d: Float[np.ndarray, "V T P 2"]
    conf: Float[np.ndarray, "V T P"]
    view_names: list[str]
    image_sizes: dict[str, tuple[int, int]]
    candidates: Any = None

    def __post_init__(self) -> None:
        self.pts2d = np.asarray(self.pts2d, dtype=np.float64)
        self.conf = np.asarray(self.conf, dtype=np.float64)
        self.view_names = [str(v) for v in self.view_names]
        self.image_sizes = {str(k): (int(v[0]), int(v[1])) for k, v in self.image_sizes.items()}
        if self.pts2d.ndim != 4 or self.pts2d.shape[-1] != 2:
            raise ValueError(f"pts2d must be (V, T, P, 2), got shape {self.pts2d.shape}")
        if self.conf.shape != self.pts2d.shape[:3]:
            raise ValueError(f"conf must have shape {self.pts2d.shape[:3]}, got {self.conf.shape}")
        if len(self.view_names) != self.pts2d.shape[0]:
            raise ValueError(f"{len(self.view_names)} view names for {self.pts2d.shape[0]} views")
        if self.candidates is not None:
            v, t, p = self.pts2d.shape[:3]
            xy, score = np.shape(self.candidates.xy), np.shape(self.candidates.score)
            if len(xy) != 5 or xy[:3] != (v, t, p) or xy[4] != 2 or score != xy[:4]:
                raise ValueError(
                    f"candidates must be xy (V, T, P, K, 2) / score (V, T, P, K), got {xy} / {score}"
                )

    def save(
        self, path: str | Path, skeleton: Skeleton, meta: Mapping[str, Any] | None = None
    ) -> None:
        """Write ``skeleton/`` and ``pose2d/`` to ``path`` atomically.

        Parameters
        ----------
        path
            Destination, e.g. ``<out>/stages/pose2d.h5``.
        skeleton
            The skeleton whose points make up the P axis.
        meta
            Extra entries for the file's meta JSON (e.g. its params hash, see
            :mod:`flylib.provenance`).
        """
        if skeleton.n_points != self.pts2d.shape[2]:
            raise ValueError(
                f"pts2d has {self.pts2d.shape[2]} points but the skeleton has {skeleton.n_points}"
            )
        with atomic_path(path) as tmp, _create(tmp) as f:
            f.attrs["meta"] = json.dumps(_new_meta("pose2d", meta))
            _write_skeleton(f.create_group("skeleton"), skeleton)
            group = f.create_group("pose2d")
            _write_array(group, "points", self.pts2d)
            _write_array(group, "conf", self.conf)
            _json_attrs(
                group,
                {
                    "view_names": self.view_names,
                    "image_sizes": {k: list(v) for k, v in self.image_sizes.items()},
                },
            )
            if self.candidates is not None:
                _write_candidates(group.create_group("candidates"), self.candidates)

    @classmethod
    def load(cls, path: str | Path) -> Pose2dData:
        """Read a pose2d artifact (or the pose2d group of a results file).

        Raises
        ------
        ResultsError
            If the file is missing, of another version, or has no pose2d group.
        """
        rerun = "re-run the pose2d stage"
        with _read_checked(path, rerun) as f:
            if "pose2d/points" not in f:
                raise ResultsError(f"{path}: has no pose2d group; {rerun}")
            group = f["pose2d"]
            attrs = _read_json_attrs(group)
            candidates = None
            if "candidates" in group:
                candidates = _make_candidates(
                    _read(group["candidates/xy"]), _read(group["candidates/score"])
                )
            views = attrs.get("view_names")
            if views is None and "cameras" in group:
                views = _read_strings(group["cameras/names"])
            return cls(
                pts2d=_read(group["points"]),
                conf=_read(group["conf"])
                if "conf" in group
                else np.ones(group["points"].shape[:3]),
                view_names=list(views or []),
                image_sizes={k: tuple(v) for k, v in (attrs.get("image_sizes") or {}).items()},
                candidates=candidates,
            )


# -- generic stage artifacts ---------------------------------------------------


def write_analysis(
    path: str | Path, stage: str, arrays: Mapping[str, Any], attrs: Mapping[str, Any]
) -> Path:
    """Write a post-processing stage's file (``kinematics.h5``, ``neuromechfly.h5``)
    atomically: the meta JSON, and a group ``<stage>`` holding ``arrays`` as checksummed
    float64 datasets and ``attrs`` as JSON group attributes."""
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["meta"] = json.dumps(_new_meta(stage))
        group = f.create_group(stage)
        for name, value in arrays.items():
            _write_array(group, name, value)
        for key, value in attrs.items():
            group.attrs[key] = json.dumps(value)
    return Path(path)


def write_stage(
    path: str | Path,
    stage: str,
    arrays: Mapping[str, Any],
    *,
    cameras: CameraGroup | None = None,
    attrs: Mapping[str, Any] | None = None,
    meta: Mapping[str, Any] | None = None,
) -> None:
    """Write one stage's artifact: ``<stage>/`` with its arrays, rig and attributes.

    Parameters
    ----------
    path
        Destination, e.g. ``<out>/stages/triangulation.h5``; written atomically.
    stage
        ``bundle_adjustment``, ``pictorial_structures`` or ``triangulation`` (the
        pose2d artifact is written by :meth:`Pose2dData.save`).
    arrays
        ``name -> array`` stored as float64 datasets (e.g. ``points``, ``points3d``,
        ``reproj_error``); boolean arrays (masks) stay boolean.
    cameras
        A rig to store as ``<stage>/cameras`` (bundle adjustment's refined rig).
    attrs
        JSON-serialisable group attributes (e.g. a bundle-adjustment ``summary``).
    meta
        Extra entries for the file's meta JSON (e.g. its params hash, see
        :mod:`flylib.provenance`).
    """
    if stage not in STAGE_GROUPS or stage == "pose2d":
        raise ValueError(
            f"unknown stage {stage!r} (write_stage takes {', '.join(STAGE_GROUPS[1:])})"
        )
    with atomic_path(path) as tmp, _create(tmp) as f:
        f.attrs["meta"] = json.dumps(_new_meta(stage, meta))
        group = f.create_group(stage)
        for name, value in arrays.items():
            value = np.asarray(value)
            _write_array(
                group, name, value, dtype=np.bool_ if value.dtype == np.bool_ else np.float64
            )
        if cameras is not None:
            _write_cameras(group.create_group("cameras"), cameras)
        _json_attrs(group, attrs)


def read_stage(path: str | Path, stage: str) -> dict[str, Any]:
    """Read one stage's group: its arrays, plus ``"cameras"`` and ``"attrs"``.

    Parameters
    ----------
    path
        A stage artifact (or results file) holding ``<stage>/``.
    stage
        The stage name.

    Returns
    -------
    dict
        ``name -> np.ndarray`` for every dataset of the group, ``"cameras"`` (a
        ``CameraGroup`` or ``None``) and ``"attrs"`` (the decoded group attributes).

    Raises
    ------
    ResultsError
        If the file is missing, of another version, or lacks the group.
    """
    rerun = f"re-run the {stage} stage"
    with _read_checked(path, rerun) as f:
        if stage not in f:
            raise ResultsError(f"{path}: has no {stage} group; {rerun}")
        group = f[stage]
        out: dict[str, Any] = {
            name: _read(item) for name, item in group.items() if isinstance(item, h5py.Dataset)
        }
        out["cameras"] = _read_cameras(group["cameras"]) if "cameras" in group else None
        out["attrs"] = _read_json_attrs(group)
        return out


def assemble_results(
    out_path: str | Path,
    *,
    skeleton: Skeleton,
    config_rig: CameraGroup,
    stage_files: Mapping[str, str | Path],
    meta: Mapping[str, Any] | None = None,
) -> None:
    """Assemble ``results.h5`` from the stage artifacts.

    Each stage group is copied verbatim (HDF5 group copy, compression kept); the
    current config's skeleton and rig are written as ``skeleton/`` and
    ``pose2d/cameras`` (the pose2d artifact holds no rig, so editing the rig never
    invalidates detection).

    Parameters
    ----------
    out_path
        Destination ``results.h5``; written atomically.
    skeleton
        The config's skeleton; its point names must match the pose2d artifact's.
    config_rig
        The config's rig; its camera names must match the pose2d view names.
    stage_files
        ``stage -> artifact path`` for the stages that ran; ``pose2d`` is required.
    meta
        Extra entries for the file's meta JSON.

    Raises
    ------
    ResultsError
        If pose2d is missing, an artifact is unreadable, or the skeleton or rig do not
        match the detected points.
    """
    unknown = sorted(set(stage_files) - set(STAGE_GROUPS))
    if unknown:
        raise ValueError(
            f"unknown stage(s) {', '.join(unknown)} (known: {', '.join(STAGE_GROUPS)})"
        )
    if "pose2d" not in stage_files:
        raise ResultsError(
            f"{out_path}: cannot assemble without the pose2d artifact; run the pose2d stage"
        )
    with atomic_path(out_path) as tmp, _create(tmp) as dst:
        dst.attrs["meta"] = json.dumps(
            _new_meta("assemble", {**(meta or {}), "stages": list(stage_files)})
        )
        _write_skeleton(dst.create_group("skeleton"), skeleton)
        for stage in STAGE_GROUPS:
            if stage not in stage_files:
                continue
            src_path = stage_files[stage]
            with open_checked(src_path, f"re-run the {stage} stage") as src:
                if stage not in src:
                    raise ResultsError(
                        f"{src_path}: has no {stage} group; re-run the {stage} stage"
                    )
                _check_group(src_path, src[stage])  # a raw copy would carry damage over unseen
                src.copy(src[stage], dst, name=stage)
                dst[stage].attrs["meta"] = json.dumps(read_meta_from(src))
                if stage == "pose2d":
                    _check_pose2d_matches(src, src_path, skeleton, config_rig)
        g2d = dst["pose2d"]
        if "cameras" in g2d:
            del g2d["cameras"]
        _write_cameras(g2d.create_group("cameras"), config_rig)


def _check_pose2d_matches(
    src: h5py.File, src_path: str | Path, skeleton: Skeleton, rig: CameraGroup
) -> None:
    if "skeleton" in src:
        detected = _read_strings(src["skeleton/point_names"])
        if list(detected) != list(skeleton.point_names):
            raise ResultsError(
                f"{src_path}: detected with skeleton points {detected[:3]}... which differ from the"
                " config's skeleton; re-run the pose2d stage"
            )
    n_points = src["pose2d/points"].shape[2]
    if n_points != skeleton.n_points:
        raise ResultsError(
            f"{src_path}: has {n_points} points but the skeleton has {skeleton.n_points}; re-run the pose2d stage"
        )
    views = _read_json_attrs(src["pose2d"]).get("view_names")
    if views is not None and list(views) != list(rig.names):
        raise ResultsError(
            f"{src_path}: 2D points are for views {views} but the rig has cameras {list(rig.names)};"
            " re-run the pose2d stage or restore the camera names/order"
        )
