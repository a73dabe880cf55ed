"""Manual corrections: the ``corrections.h5`` sidecar and its edits.

The sidecar is the seed system's GUI format, version 3 (``../shared/spec/corrections-h5.md``),
written beside ``results.h5`` and never inside it::

    attrs["meta"]          JSON {"deeperfly_corrections_format_version": 3, "source", "created_utc"}
    pose2d_corrections/    points (V, T, P, 2) float64, edited / fixed / invisible (V, T, P) bool
    pose3d_corrections/    points3d (T, P, 3) float64, edited (T, P) bool
    flylib_review/         reviewed (T, P) bool (flylib's addition, see below)

Versions 1 and 2 (no ``invisible``, or no ``fixed`` either) load with those masks all False.
flylib writes every dataset Fletcher-32 checksummed and adds ``flylib_revision`` (the GUI session's
edit revision) to the meta and the ``flylib_review/reviewed`` mask; the seed's readers ignore all
three, so the version stays 3. A seed-written file (no checksums) still loads; the file is guarded
whole (:func:`~flylib.results.guard.guard_file`) before :meth:`Corrections.load` reads it.

The triangulation stage applies a sidecar
(:func:`flylib.pipeline.triangulation.compute_triangulation`, which the GUI calls too, so what it
shows is what a re-run computes): 2D edits through :meth:`Corrections.apply_2d`, then its ``fixed``
views and 3D edits."""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from .errors import ResultsError, one_line
from .paths import atomic_path, fill_template
from .results import open_hdf5, read_meta_from

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

    from .camera.rig import CameraGroup


__all__ = [
    "CORRECTIONS_FILE",
    "CORRECTIONS_FORMAT_VERSION",
    "EDIT3D_RIG_SPANS",
    "Corrections",
    "corrections_path",
    "read_corrected",
]

#: The sidecar's file name beside ``results.h5``.
CORRECTIONS_FILE = "corrections.h5"
#: The sidecar format version this code writes (and the newest it reads).
CORRECTIONS_FORMAT_VERSION = 3
_META_KEY = "deeperfly_corrections_format_version"
# HDF5 1.8's file format: checksummed object headers (as results.h5 and the artifacts)
_LIBVER = ("v108", "latest")
#: How far a 3D edit may lie from the cameras' mean centre, in rig sizes (the largest distance
#: between two camera centres): an edit 1000 rig sizes away is no place on a fly the cameras see
#: (and a 1e300 would overflow what follows).
EDIT3D_RIG_SPANS = 1000.0
_DATASETS = (
    "pose2d_corrections/points",
    "pose2d_corrections/edited",
    "pose3d_corrections/points3d",
    "pose3d_corrections/edited",
)

#: flylib's review-progress mask in the sidecar (the seed's readers do not read it).
_REVIEWED = "flylib_review/reviewed"


@dataclass
class Corrections:
    """Manual edits of one recording's result (the seed GUI's sidecar).

    ``points`` (2D pixels) and ``points3d`` are NaN where not edited; ``edited`` / ``edited3d`` say
    which entries are edits (a NaN edit is an edit). ``fixed``: finalized 2D points, always used
    when re-solved (subset of ``edited``); ``invisible``: dropped from triangulation (disjoint from
    ``edited``); ``reviewed`` ``(T, P)``: marked OK in ``flylib gui``, never applied (default all
    False); ``revision``: the GUI session revision saved (0 for a seed-written file)."""

    points: Float[np.ndarray, "V T P 2"]
    edited: Bool[np.ndarray, "V T P"]
    fixed: Bool[np.ndarray, "V T P"]
    invisible: Bool[np.ndarray, "V T P"]
    points3d: Float[np.ndarray, "T P 3"]
    edited3d: Bool[np.ndarray, "T P"]
    source: str = ""
    created_utc: str = ""
    revision: int = 0
    reviewed: Any = None

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64)
        if self.points.ndim != 4 or self.points.shape[-1] != 2:
            raise ValueError(f"points must be (V, T, P, 2), got {self.points.shape}")
        shape = self.points.shape[:3]
        for name in ("edited", "fixed", "invisible"):
            arr = np.asarray(getattr(self, name), dtype=bool)
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape} (V, T, P), got {arr.shape}")
            setattr(self, name, arr)
        self.points3d = np.asarray(self.points3d, dtype=np.float64)
        self.edited3d = np.asarray(self.edited3d, dtype=bool)
        if self.points3d.shape != (*shape[1:], 3) or self.edited3d.shape != shape[1:]:
            raise ValueError(
                f"points3d / edited must be {(*shape[1:], 3)} / {shape[1:]}, got "
                f"{self.points3d.shape} / {self.edited3d.shape}"
            )
        self.reviewed = (
            np.zeros(shape[1:], bool)
            if self.reviewed is None
            else np.asarray(self.reviewed, dtype=bool)
        )
        if self.reviewed.shape != shape[1:]:
            raise ValueError(f"reviewed must be {shape[1:]} (T, P), got {self.reviewed.shape}")

    # -- construction and I/O ---------------------------------------------------------

    @classmethod
    def empty(cls, n_views: int, n_frames: int, n_points: int, source: str = "") -> Corrections:
        """No edits for a ``(V, T, P)`` result."""
        shape = (n_views, n_frames, n_points)
        return cls(
            points=np.full((*shape, 2), np.nan),
            edited=np.zeros(shape, bool),
            fixed=np.zeros(shape, bool),
            invisible=np.zeros(shape, bool),
            points3d=np.full((n_frames, n_points, 3), np.nan),
            edited3d=np.zeros((n_frames, n_points), bool),
            source=str(source),
        )

    @classmethod
    def load(
        cls,
        path: str | Path,
        shape: tuple[int, int, int] | None = None,
        image_sizes: Sequence[tuple[int, int] | None] | None = None,
        cameras: CameraGroup | None = None,
    ) -> Corrections:
        """Read a sidecar (format version 1 to 3), its checksums verified.

        ``shape``: the ``(V, T, P)`` it must correct; ``image_sizes`` (``(height, width)`` or
        ``None`` per view) refuses 2D edits outside the image; ``cameras`` refuses 3D edits farther
        than :data:`EDIT3D_RIG_SPANS` rig sizes. Any problem is one
        :class:`~flylib.errors.ResultsError` line naming the file."""
        path = Path(path)
        fix = "delete or move it aside, or save the corrections again from `flylib gui`"
        with open_hdf5(path, fix, "HDF5 corrections file") as f:
            try:
                meta, arrays = _read_sidecar(f, path, fix, shape)
            except (OSError, KeyError, RuntimeError) as err:  # a damaged header or link table
                raise ResultsError(f"{path}: damaged ({one_line(err)}); {fix}") from None
        points = arrays["pose2d_corrections/points"]
        if points.ndim != 4 or points.shape[-1] != 2:
            raise ResultsError(
                f"{path}: pose2d_corrections/points must be (V, T, P, 2), got {points.shape}; {fix}"
            )
        masks = {
            name: (
                arrays[f"pose2d_corrections/{name}"].astype(bool)
                if f"pose2d_corrections/{name}" in arrays
                else np.zeros(points.shape[:3], bool)
            )
            for name in ("edited", "fixed", "invisible")
        }
        revision = meta.get("flylib_revision", 0)
        try:
            out = cls(
                points=points,
                points3d=arrays["pose3d_corrections/points3d"],
                edited3d=arrays["pose3d_corrections/edited"],
                source=str(meta.get("source", "")),
                created_utc=str(meta.get("created_utc", "")),
                revision=revision if type(revision) is int and revision >= 0 else 0,
                reviewed=arrays.get(_REVIEWED),
                **masks,
            )
        except ValueError as err:
            raise ResultsError(f"{path}: inconsistent shapes ({err}); {fix}") from None
        problem = out.invalid_values(image_sizes, cameras)
        if problem:
            raise ResultsError(f"{path}: {problem}; nothing was applied ({fix})")
        return out

    def invalid_values(
        self,
        image_sizes: Sequence[tuple[int, int] | None] | None = None,
        cameras: CameraGroup | None = None,
    ) -> str:
        """What makes these corrections unusable, or ``""``: an infinite number, a non-finite 3D
        edit, a 3D edit farther from the cameras' mean centre than :data:`EDIT3D_RIG_SPANS` x the
        rig's span, a 2D edit outside its image. A NaN 2D edit is the seed's deliberate "remove"."""
        for name in ("points", "points3d"):
            bad = np.argwhere(np.isinf(getattr(self, name)))
            if len(bad):
                return f"{name} holds an infinite value at index {tuple(bad[0].tolist())}"
        bad = np.argwhere(self.edited3d & ~np.isfinite(self.points3d).all(-1))
        if len(bad):
            t, p = bad[0].tolist()
            return f"the 3D edit of frame {t}, point {p} is not a finite point"
        if cameras is not None and self.edited3d.any():
            problem = _outside_rig(self.points3d, self.edited3d, cameras)
            if problem:
                return problem
        for v, size in enumerate(image_sizes or ()):
            if size is None:
                continue
            height, width = size
            xy = self.points[v]
            with np.errstate(invalid="ignore"):
                outside = self.edited[v] & (
                    (xy[..., 0] < 0)
                    | (xy[..., 0] > width)
                    | (xy[..., 1] < 0)
                    | (xy[..., 1] > height)
                )
            bad = np.argwhere(outside)
            if len(bad):
                t, p = bad[0].tolist()
                x, y = xy[t, p].tolist()
                return (
                    f"the 2D edit of view {v}, frame {t}, point {p} at ({x:.6g}, {y:.6g}) lies "
                    f"outside the {width}x{height} image"
                )
        return ""

    def save(self, path: str | Path) -> Path:
        """Write the sidecar atomically, format version 3, every dataset Fletcher-32 checksummed;
        :class:`~flylib.errors.ResultsError` (nothing written) on infinite numbers or a non-finite
        3D edit."""
        problem = self.invalid_values()
        if problem:
            raise ResultsError(f"{path}: not saved, {problem}")
        self.created_utc = datetime.now(UTC).isoformat()
        meta = {
            _META_KEY: CORRECTIONS_FORMAT_VERSION,
            "source": self.source,
            "created_utc": self.created_utc,
            "flylib_revision": int(self.revision),
        }
        # built in memory, then written as plain bytes: a write that fails (full disk) is then
        # an OSError of Python's, never a half-created file inside libhdf5's state, which
        # would crash the GUI's process later (at exit or the next close)
        buffer = io.BytesIO()
        with h5py.File(buffer, "w", libver=_LIBVER) as f:
            f.attrs["meta"] = json.dumps(meta)
            g2 = f.create_group("pose2d_corrections")
            _write_checksummed(g2, "points", self.points, np.float64)
            for name in ("edited", "fixed", "invisible"):
                _write_checksummed(g2, name, getattr(self, name), bool)
            g3 = f.create_group("pose3d_corrections")
            _write_checksummed(g3, "points3d", self.points3d, np.float64)
            _write_checksummed(g3, "edited", self.edited3d, bool)
            if self.reviewed.any():
                group, name = _REVIEWED.split("/")
                _write_checksummed(f.create_group(group), name, self.reviewed, bool)
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(buffer.getbuffer())
        return Path(path)

    # -- edits (the seed GUI's semantics) ----------------------------------------------

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(V, T, P)``."""
        return tuple(self.edited.shape)

    def set_point(
        self,
        view: int,
        frame: int,
        point: int,
        xy: Float[np.ndarray, " 2"] | tuple[float, float],
        *,
        fixed: bool = False,
    ) -> None:
        """Place a 2D point (clears its ``invisible`` flag)."""
        self.points[view, frame, point] = np.asarray(xy, dtype=np.float64)
        self.edited[view, frame, point] = True
        self.fixed[view, frame, point] = bool(fixed)
        self.invisible[view, frame, point] = False

    def set_invisible(self, view: int, frame: int, point: int) -> None:
        """Mark a point obscured in one view (clears its 2D edit and ``fixed`` flag)."""
        self.points[view, frame, point] = np.nan
        self.edited[view, frame, point] = False
        self.fixed[view, frame, point] = False
        self.invisible[view, frame, point] = True

    def set_point3d(
        self, frame: int, point: int, xyz: Float[np.ndarray, " 3"] | tuple[float, float, float]
    ) -> None:
        """Place a 3D point."""
        self.points3d[frame, point] = np.asarray(xyz, dtype=np.float64)
        self.edited3d[frame, point] = True

    def reset(self, frame: int, point: int | None = None, view: int | None = None) -> None:
        """Clear the edits and flags of a frame (``reset(t)``), of point ``p`` in every view and
        its 3D edit (``point=p``), of one observation (``point=p, view=v``) or of every point
        of one view (``view=v``)."""
        vs = slice(None) if view is None else view
        ps = slice(None) if point is None else point
        self.points[vs, frame, ps] = np.nan
        for mask in (self.edited, self.fixed, self.invisible):
            mask[vs, frame, ps] = False
        if view is None:
            self.points3d[frame, ps] = np.nan
            self.edited3d[frame, ps] = False

    # -- applying ----------------------------------------------------------------------

    def touched(self) -> Bool[np.ndarray, "V T P"]:
        """``(V, T, P)`` bool: observations a person edited or marked invisible."""
        return self.edited | self.invisible

    def edited_2d(self) -> Float[np.ndarray, "V T P 2"]:
        """``(V, T, P, 2)`` the 2D a person gave where :meth:`touched` (NaN elsewhere and where
        marked invisible): with :meth:`touched`, what :meth:`apply_2d` puts in."""
        out = np.full((*self.shape, 2), np.nan)
        out[self.edited] = self.points[self.edited]
        out[self.invisible] = np.nan
        return out

    def corrected_points(self) -> Bool[np.ndarray, "T P"]:
        """``(T, P)`` bool: 3D points whose input a person changed (any view, or in 3D)."""
        return self.touched().any(axis=0) | self.edited3d

    def count(self) -> int:
        """Number of edited or invisible observations plus edited 3D points."""
        return int(self.touched().sum() + self.edited3d.sum())

    def apply_2d(
        self, pts2d: Float[np.ndarray, "V T P 2"], conf: Float[np.ndarray, "V T P"] | None = None
    ) -> tuple[Float[np.ndarray, "V T P 2"], Float[np.ndarray, "V T P"] | None]:
        """Corrected copies of the 2D triangulation reads, ``pts2d`` ``(V, T, P, 2)`` and ``conf``
        ``(V, T, P)`` or ``None``: edits replace detections (confidence 1), invisible ones go."""
        pts2d = np.array(pts2d, dtype=np.float64)
        pts2d[self.edited] = self.points[self.edited]
        pts2d[self.invisible] = np.nan
        if conf is not None:
            conf = np.array(conf, dtype=np.float64)
            conf[self.edited] = 1.0
            conf[self.invisible] = np.nan
        return pts2d, conf

    def subset(self, frames, points) -> Corrections:
        """The corrections of ``frames`` x ``points`` (index arrays or slices)."""
        f = np.arange(self.shape[1])[frames]
        p = np.arange(self.shape[2])[points]
        ix = np.ix_(f, p)
        return Corrections(
            points=self.points[:, ix[0], ix[1]],
            edited=self.edited[:, ix[0], ix[1]],
            fixed=self.fixed[:, ix[0], ix[1]],
            invisible=self.invisible[:, ix[0], ix[1]],
            points3d=self.points3d[ix],
            edited3d=self.edited3d[ix],
            reviewed=self.reviewed[ix],
            source=self.source,
        )


def _write_checksummed(group: h5py.Group, name: str, data: np.ndarray, dtype: Any) -> None:
    arr = np.asarray(data, dtype=dtype)
    if arr.size == 0:  # no chunk to checksum
        group.create_dataset(name, data=arr)
        return
    group.create_dataset(name, data=arr, chunks=arr.shape, fletcher32=True)


def _outside_rig(points3d: np.ndarray, edited3d: np.ndarray, cameras: CameraGroup) -> str:
    """The first 3D edit farther from the rig than :data:`EDIT3D_RIG_SPANS` rig sizes."""
    centres = np.asarray(cameras.positions, dtype=np.float64)
    span = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
    if not (np.isfinite(span) and span > 0):  # one camera: no size to measure by
        return ""
    limit = EDIT3D_RIG_SPANS * span
    offset = points3d - centres.mean(axis=0)
    scale = np.max(np.abs(offset), axis=-1, keepdims=True)  # no overflow squaring a 1e300
    scale = np.where(scale > 0, scale, 1.0)
    with np.errstate(invalid="ignore"):
        distance = scale[..., 0] * np.linalg.norm(offset / scale, axis=-1)
    bad = np.argwhere(edited3d & (distance > limit))
    if not len(bad):
        return ""
    t, p = bad[0].tolist()
    x, y, z = points3d[t, p].tolist()
    return (
        f"the 3D edit of frame {t}, point {p} at ({x:.6g}, {y:.6g}, {z:.6g}) lies "
        f"{distance[t, p]:.3g} from the cameras, more than {EDIT3D_RIG_SPANS:g} x the rig's "
        f"size ({span:.3g}, the largest distance between two camera centres)"
    )


def _read_sidecar(
    f: h5py.File, path: Path, fix: str, shape: tuple[int, int, int] | None = None
) -> tuple[dict, dict[str, np.ndarray]]:
    """The meta and every dataset of an open sidecar; HDF5 checks each Fletcher-32 chunk it reads
    (seed-written files carry none). With ``shape`` ``(V, T, P)``, each dataset's declared shape
    is checked before it is read."""
    meta = read_meta_from(f)
    version = meta.get(_META_KEY)
    if not isinstance(version, int) or isinstance(version, bool):
        raise ResultsError(
            f"{path}: no {_META_KEY} in attrs['meta']; not a corrections sidecar ({fix})"
        )
    if version > CORRECTIONS_FORMAT_VERSION or version < 1:
        raise ResultsError(
            f"{path}: corrections format version {version}, this flylib "
            f"reads 1 to {CORRECTIONS_FORMAT_VERSION}; update flylib"
        )
    for name in _DATASETS:
        if name not in f:
            raise ResultsError(f"{path}: has no {name} dataset; {fix}")
    arrays = {}
    for name in (*_DATASETS, "pose2d_corrections/fixed", "pose2d_corrections/invisible", _REVIEWED):
        if name not in f:
            continue
        dataset = f[name]
        if not isinstance(dataset, h5py.Dataset) or dataset.dtype.kind not in "biuf":
            raise ResultsError(f"{path}: {name} is not a numeric or boolean dataset; {fix}")
        expected = None if shape is None else _expected_shape(name, shape)
        if expected is not None and dataset.shape != expected:
            declared = (
                f"corrects a result of (views, frames, points) {dataset.shape[:3]}, but this "
                f"one is {tuple(shape)}"
                if name == "pose2d_corrections/points" and len(dataset.shape) == 4
                else f"its {name} is {dataset.shape}, not the {expected} of a result of "
                f"(views, frames, points) {tuple(shape)}"
            )
            raise ResultsError(
                f"{path}: {declared}; it belongs to another recording or run ({fix})"
            )
        try:
            arrays[name] = np.asarray(dataset[()], dtype=np.float64 if "points" in name else bool)
        except OSError as err:
            raise ResultsError(
                f"{path}: dataset {name} is damaged ({one_line(err)}); the file is corrupt, "
                f"nothing was applied ({fix})"
            ) from None
    return meta, arrays


def _expected_shape(name: str, shape: tuple[int, int, int]) -> tuple[int, ...]:
    """The shape of sidecar dataset ``name`` for a ``(V, T, P)`` result."""
    v, t, p = (int(n) for n in shape)
    return {
        "pose2d_corrections/points": (v, t, p, 2),
        "pose3d_corrections/points3d": (t, p, 3),
        "pose3d_corrections/edited": (t, p),
        _REVIEWED: (t, p),
    }.get(name, (v, t, p))


def corrections_path(
    template: str | None,
    outdir: str | Path,
    recording_dir: str | Path | None = None,
    recording_id: str | None = None,
) -> tuple[Path, bool]:
    """Where a recording's sidecar is (may not exist), and whether the config named it:
    ``<outdir>/corrections.h5`` unless ``template`` (config ``corrections``: ``{outdir}``,
    ``{recording}``, ``{id}``, ``{name}``; relative to the outdir) says otherwise."""
    from .errors import ConfigError

    outdir = Path(outdir)
    if template is None:
        return outdir / CORRECTIONS_FILE, False
    if not isinstance(template, str) or not template.strip():
        raise ConfigError(
            f"corrections: expected the path (template) of a corrections.h5 or null, "
            f"got {template!r}"
        )
    recording = Path(recording_dir) if recording_dir is not None else outdir
    values = {
        "outdir": str(outdir),
        "recording": str(recording),
        "id": recording_id or recording.name,
        "name": recording.name,
    }
    text = fill_template(template, values, "corrections")
    path = Path(text).expanduser()
    return (path if path.is_absolute() else outdir / path), True


def read_corrected(results_path: str | Path) -> Bool[np.ndarray, "T P"] | None:
    """``(T, P)`` bool: the points of a ``results.h5`` a person corrected, or ``None`` when it was
    computed without corrections (``triangulation/corrected``)."""
    from .results import open_checked

    with open_checked(results_path) as f:
        if "triangulation/corrected" not in f:
            return None
        return np.asarray(f["triangulation/corrected"][()], dtype=bool)
