"""HDF5 results (schema version 2) and the per-stage artifacts they are assembled from.

Every file holds ``attrs["meta"]`` (JSON: ``deeperfly_format_version``,
``flylib_version``, ``created_utc``, ``stage``) and the group of each stage that
produced it; ``results.h5`` is the union of the stage files plus ``skeleton/`` and the
config rig as ``pose2d/cameras``. Group attributes are stored as JSON text. Arrays are
float64 (NaN = missing), chunked along their longest axis (time) and gzip-compressed
once they are large, so a 100k-frame recording stays small.

Every write goes to a temporary sibling first and is renamed into place on success
(:func:`atomic_path`), so an interrupted run never leaves a truncated file.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from .errors import ResultsError
from .paths import atomic_path
from .resources import usable_cpus
from .skeleton import Skeleton

if TYPE_CHECKING:  # pragma: no cover
    from .cameras import CameraGroup

__all__ = [
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
    "write_stage",
]

#: The results.h5 schema version this code writes and accepts.
FORMAT_VERSION = 2
#: Stages that own a group in results.h5, in pipeline order.
STAGE_GROUPS: tuple[str, ...] = ("pose2d", "bundle_adjustment", "pictorial_structures", "triangulation",
                                  "refinement")

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
_DEFLATE_THREADS = min(8, usable_cpus())




# -- low-level helpers ---------------------------------------------------------


def _new_meta(stage: str, extra: Mapping | None = None) -> dict:
    from . import __version__

    return {
        **(extra or {}),
        "deeperfly_format_version": FORMAT_VERSION,
        "flylib_version": __version__,
        "created_utc": datetime.now(timezone.utc).isoformat(),
        "stage": stage,
    }


def _write_array(group: h5py.Group, name: str, data: Any, dtype: Any = np.float64) -> h5py.Dataset:
    """Write ``data``; big arrays are chunked along their longest axis and compressed."""
    arr = np.asarray(data, dtype=dtype)
    if name in group:
        del group[name]
    if arr.size < _COMPRESS_MIN_ELEMENTS or arr.ndim == 0:
        return group.create_dataset(name, data=arr)
    axis = int(np.argmax(arr.shape))
    per_step = arr.itemsize * arr.size // arr.shape[axis]
    step = int(max(1, min(arr.shape[axis], _CHUNK_BYTES // max(per_step, 1))))
    chunks = list(arr.shape)
    chunks[axis] = step
    dataset = group.create_dataset(name, shape=arr.shape, dtype=arr.dtype, chunks=tuple(chunks),
                                   **_COMPRESSION)
    _write_deflated_chunks(dataset, arr, axis, step)
    return dataset


def _write_deflated_chunks(dataset: h5py.Dataset, arr: np.ndarray, axis: int, step: int) -> None:
    """Fill a gzip-filtered dataset chunked in slabs of ``step`` along ``axis``.

    HDF5 compresses chunk by chunk on one core (most of the write time of a long
    recording's arrays); here zlib compresses the slabs on threads (it releases the
    GIL) and HDF5 stores the finished chunks as they are. The file is the one
    ``create_dataset(data=..., compression="gzip")`` writes: the same deflate filter
    and zlib stream, readable by any HDF5 reader.
    """
    starts = range(0, arr.shape[axis], step)

    def deflate(start: int) -> bytes:
        slab = arr[(slice(None),) * axis + (slice(start, start + step),)]
        if slab.shape[axis] < step:  # an edge chunk is stored whole, padded with zeros
            pad = [(0, 0)] * arr.ndim
            pad[axis] = (0, step - slab.shape[axis])
            slab = np.pad(slab, pad)
        return zlib.compress(np.ascontiguousarray(slab).tobytes(), _COMPRESSION["compression_opts"])

    workers = min(_DEFLATE_THREADS, len(starts))
    with ThreadPoolExecutor(max_workers=max(workers, 1)) as pool:
        for start, payload in zip(starts, pool.map(deflate, starts)):
            offset = tuple(start if i == axis else 0 for i in range(arr.ndim))
            dataset.id.write_direct_chunk(offset, payload)


def _write_strings(group: h5py.Group, name: str, values: Sequence[str]) -> None:
    if name in group:
        del group[name]
    group.create_dataset(name, data=np.array(list(values), dtype=object), dtype=h5py.string_dtype())


def _read_strings(dataset: h5py.Dataset) -> list[str]:
    return [str(s) for s in dataset.asstr()[()]]


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
    if not path.is_file():
        raise ResultsError(f"{path}: file not found; {rerun}")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise ResultsError(f"{path}: not a readable HDF5 file ({err}); {rerun}") from None
    with f:
        version = read_meta_from(f).get("deeperfly_format_version")
        if version is None:
            raise ResultsError(f"{path}: not a flylib file (no format version in its meta); {rerun} to regenerate it")
        if version != FORMAT_VERSION:
            raise ResultsError(
                f"{path}: format version {version!r}, expected {FORMAT_VERSION}; {rerun} to regenerate it"
            )
        yield f


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
    """
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise ResultsError(f"{path}: not a readable HDF5 file ({err})") from None
    with f:
        return read_meta_from(f)


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
        group["rvecs"][()],
        group["tvecs"][()],
        group["intrs"][()],
        group["dists"][()],
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
    palette = {str(k): str(v) for k, v in group["palette"].attrs.items()} if "palette" in group else {}
    return Skeleton.from_arrays(
        _read_strings(group["point_names"]),
        _read_strings(group["limb_names"]),
        group["limb_id"][()],
        group["bones"][()],
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
    with open_checked(path, "re-run the pipeline") as f:
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
    with open_checked(path, f"re-run {group}") as f:
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
    with open_checked(path, "re-run the pose2d stage") as f:
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
    pts2d: np.ndarray
    conf: np.ndarray | None = None
    pts3d: np.ndarray | None = None
    reproj_error: np.ndarray | None = None
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
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
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
        with open_checked(path, rerun) as f:
            if "pose2d/points" not in f:
                raise ResultsError(f"{path}: has no pose2d group (no 2D points); {rerun}")
            if "skeleton" not in f:
                raise ResultsError(f"{path}: has no skeleton group; {rerun}")
            meta = read_meta_from(f)
            meta.pop("deeperfly_format_version", None)
            skeleton = _read_skeleton(f["skeleton"])
            rig = next((f[f"{s}/cameras"] for s in ("bundle_adjustment", "pose2d") if f"{s}/cameras" in f), None)
            if rig is None:
                raise ResultsError(f"{path}: has no cameras (pose2d/cameras); assemble it with assemble_results")
            cameras = _read_cameras(rig)

            def first(name: str, stages: tuple[str, ...]) -> np.ndarray | None:
                return next((f[f"{s}/{name}"][()] for s in stages if f"{s}/{name}" in f), None)

            derived = ("refinement", "triangulation", "pictorial_structures")
            pts2d = first("points", (*derived, "pose2d"))
            pts3d = first("points3d", derived)
            reproj = first("reproj_error", derived)
            conf = first("conf", ("pose2d",))
            sizes = _read_json_attrs(f["pose2d"]).get("image_sizes")
        return cls(
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


def save_candidates(path: str | Path, candidates: Any) -> None:
    """Write the detector's top-K peaks to their own artifact (``candidates/{xy, score}``).

    Parameters
    ----------
    path
        Destination, e.g. ``<out>/stages/candidates.h5``; written atomically.
    candidates
        A :class:`flylib.pictorial.Candidates` (``xy (V, T, P, K, 2)``, ``score (V, T, P, K)``).
    """
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["meta"] = json.dumps(_new_meta("candidates"))
        _write_candidates(f.create_group("candidates"), candidates)


def load_candidates(path: str | Path) -> Any:
    """Read what :func:`save_candidates` wrote.

    Raises
    ------
    ResultsError
        If the file is missing, of another version, or holds no candidates.
    """
    rerun = "re-run the pose2d stage with pictorial structures on"
    with open_checked(path, rerun) as f:
        if "candidates/xy" not in f:
            raise ResultsError(f"{path}: holds no candidate peaks; {rerun}")
        return _make_candidates(f["candidates/xy"][()], f["candidates/score"][()])


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

    pts2d: np.ndarray
    conf: np.ndarray
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
                raise ValueError(f"candidates must be xy (V, T, P, K, 2) / score (V, T, P, K), got {xy} / {score}")

    def save(self, path: str | Path, skeleton: Skeleton) -> None:
        """Write ``skeleton/`` and ``pose2d/`` to ``path`` atomically.

        Parameters
        ----------
        path
            Destination, e.g. ``<out>/stages/pose2d.h5``.
        skeleton
            The skeleton whose points make up the P axis.
        """
        if skeleton.n_points != self.pts2d.shape[2]:
            raise ValueError(f"pts2d has {self.pts2d.shape[2]} points but the skeleton has {skeleton.n_points}")
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            f.attrs["meta"] = json.dumps(_new_meta("pose2d"))
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
        with open_checked(path, rerun) as f:
            if "pose2d/points" not in f:
                raise ResultsError(f"{path}: has no pose2d group; {rerun}")
            group = f["pose2d"]
            attrs = _read_json_attrs(group)
            candidates = None
            if "candidates" in group:
                candidates = _make_candidates(group["candidates/xy"][()], group["candidates/score"][()])
            views = attrs.get("view_names")
            if views is None and "cameras" in group:
                views = _read_strings(group["cameras/names"])
            return cls(
                pts2d=group["points"][()],
                conf=group["conf"][()] if "conf" in group else np.ones(group["points"].shape[:3]),
                view_names=list(views or []),
                image_sizes={k: tuple(v) for k, v in (attrs.get("image_sizes") or {}).items()},
                candidates=candidates,
            )


# -- generic stage artifacts ---------------------------------------------------


def write_stage(
    path: str | Path,
    stage: str,
    arrays: Mapping[str, Any],
    *,
    cameras: CameraGroup | None = None,
    attrs: Mapping[str, Any] | None = None,
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
        ``reproj_error``).
    cameras
        A rig to store as ``<stage>/cameras`` (bundle adjustment's refined rig).
    attrs
        JSON-serialisable group attributes (e.g. a bundle-adjustment ``summary``).
    """
    if stage not in STAGE_GROUPS or stage == "pose2d":
        raise ValueError(f"unknown stage {stage!r} (write_stage takes {', '.join(STAGE_GROUPS[1:])})")
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["meta"] = json.dumps(_new_meta(stage))
        group = f.create_group(stage)
        for name, value in arrays.items():
            _write_array(group, name, value)
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
    with open_checked(path, rerun) as f:
        if stage not in f:
            raise ResultsError(f"{path}: has no {stage} group; {rerun}")
        group = f[stage]
        out: dict[str, Any] = {
            name: item[()] for name, item in group.items() if isinstance(item, h5py.Dataset)
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
        raise ValueError(f"unknown stage(s) {', '.join(unknown)} (known: {', '.join(STAGE_GROUPS)})")
    if "pose2d" not in stage_files:
        raise ResultsError(f"{out_path}: cannot assemble without the pose2d artifact; run the pose2d stage")
    with atomic_path(out_path) as tmp, h5py.File(tmp, "w") as dst:
        dst.attrs["meta"] = json.dumps(_new_meta("assemble", {**(meta or {}), "stages": list(stage_files)}))
        _write_skeleton(dst.create_group("skeleton"), skeleton)
        for stage in STAGE_GROUPS:
            if stage not in stage_files:
                continue
            src_path = stage_files[stage]
            with open_checked(src_path, f"re-run the {stage} stage") as src:
                if stage not in src:
                    raise ResultsError(f"{src_path}: has no {stage} group; re-run the {stage} stage")
                src.copy(src[stage], dst, name=stage)
                dst[stage].attrs["meta"] = json.dumps(read_meta_from(src))
                if stage == "pose2d":
                    _check_pose2d_matches(src, src_path, skeleton, config_rig)
        g2d = dst["pose2d"]
        if "cameras" in g2d:
            del g2d["cameras"]
        _write_cameras(g2d.create_group("cameras"), config_rig)


def _check_pose2d_matches(src: h5py.File, src_path: str | Path, skeleton: Skeleton, rig: CameraGroup) -> None:
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
