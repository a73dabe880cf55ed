"""Manual corrections: the ``corrections.h5`` sidecar and how triangulation applies it.

The sidecar is the seed system's GUI format, version 3
(``../shared/spec/corrections-h5.md``), written beside ``results.h5`` and never
inside it::

    attrs["meta"]          JSON {"deeperfly_corrections_format_version": 3, "source", "created_utc"}
    pose2d_corrections/    points (V, T, P, 2) float64, edited / fixed / invisible (V, T, P) bool
    pose3d_corrections/    points3d (T, P, 3) float64, edited (T, P) bool

A file of version 1 or 2 (no ``invisible``, or no ``fixed`` either) loads with the
missing masks all False.

How the triangulation stage applies a sidecar (:func:`reconstruct_corrected`, which the
GUI calls too, for one point at a time, so what it shows is what a re-run computes):

- an edited 2D point replaces the detection in its view (a NaN edit removes it) and
  gets confidence 1;
- an invisible point is dropped from triangulation;
- a ``fixed`` view is always part of the solution: when the robust method rejected
  it, the point is re-solved by DLT from the kept views plus the fixed ones;
- an edited 3D point replaces the triangulated one (reprojection errors follow).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from .errors import ResultsError
from .paths import atomic_path
from .results import open_hdf5, read_meta_from

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

    from .cameras import CameraGroup

__all__ = [
    "CORRECTIONS_FILE",
    "CORRECTIONS_FORMAT_VERSION",
    "Corrections",
    "corrections_path",
    "read_corrected",
    "reconstruct_corrected",
]

#: The sidecar's file name beside ``results.h5``.
CORRECTIONS_FILE = "corrections.h5"
#: The sidecar format version this code writes (and the newest it reads).
CORRECTIONS_FORMAT_VERSION = 3
_META_KEY = "deeperfly_corrections_format_version"


@dataclass
class Corrections:
    """Manual edits of one recording's result (the seed GUI's sidecar).

    Attributes
    ----------
    points
        ``(V, T, P, 2)`` edited 2D pixels; NaN where not edited.
    edited
        ``(V, T, P)`` bool: which entries of ``points`` are edits (a NaN edit is an edit).
    fixed
        ``(V, T, P)`` bool: finalized 2D points, always used when the point is
        re-solved; a subset of ``edited``.
    invisible
        ``(V, T, P)`` bool: dropped from triangulation; disjoint from ``edited``.
    points3d
        ``(T, P, 3)`` edited 3D points; NaN where not edited.
    edited3d
        ``(T, P)`` bool.
    source
        The ``results.h5`` these corrections apply to (informative).
    created_utc
        When the file was written (ISO 8601).
    """

    points: Float[np.ndarray, "V T P 2"]
    edited: Bool[np.ndarray, "V T P"]
    fixed: Bool[np.ndarray, "V T P"]
    invisible: Bool[np.ndarray, "V T P"]
    points3d: Float[np.ndarray, "T P 3"]
    edited3d: Bool[np.ndarray, "T P"]
    source: str = ""
    created_utc: str = ""

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
    def load(cls, path: str | Path, shape: tuple[int, int, int] | None = None) -> Corrections:
        """Read a sidecar (format version 1 to 3).

        Parameters
        ----------
        path
            The ``corrections.h5``.
        shape
            ``(V, T, P)`` of the result it must correct, checked when given.

        Raises
        ------
        ResultsError
            Missing or unreadable file, a newer format version, missing datasets, or a
            shape that does not match ``shape`` (one line naming the file).
        """
        path = Path(path)
        fix = "delete or move it aside, or save the corrections again from `flylib gui`"
        with open_hdf5(path, fix, "HDF5 corrections file") as f:
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
            for name in (
                "pose2d_corrections/points",
                "pose2d_corrections/edited",
                "pose3d_corrections/points3d",
                "pose3d_corrections/edited",
            ):
                if name not in f:
                    raise ResultsError(f"{path}: has no {name} dataset; {fix}")
            g2 = f["pose2d_corrections"]
            points = np.asarray(g2["points"][()], dtype=np.float64)
            if points.ndim != 4 or points.shape[-1] != 2:
                raise ResultsError(
                    f"{path}: pose2d_corrections/points must be (V, T, P, 2), "
                    f"got {points.shape}; {fix}"
                )
            masks = {}
            for name in ("edited", "fixed", "invisible"):
                masks[name] = (
                    np.asarray(g2[name][()], dtype=bool)
                    if name in g2
                    else np.zeros(points.shape[:3], bool)
                )
            g3 = f["pose3d_corrections"]
            try:
                out = cls(
                    points=points,
                    points3d=g3["points3d"][()],
                    edited3d=g3["edited"][()],
                    source=str(meta.get("source", "")),
                    created_utc=str(meta.get("created_utc", "")),
                    **masks,
                )
            except ValueError as err:
                raise ResultsError(f"{path}: inconsistent shapes ({err}); {fix}") from None
        if shape is not None and tuple(out.shape) != tuple(shape):
            raise ResultsError(
                f"{path}: corrects a result of (views, frames, points) {out.shape}, but this one "
                f"is {tuple(shape)}; it belongs to another recording or run ({fix})"
            )
        return out

    def save(self, path: str | Path) -> Path:
        """Write the sidecar atomically (format version 3).

        Parameters
        ----------
        path
            Destination, normally ``<outdir>/corrections.h5``.
        """
        self.created_utc = datetime.now(UTC).isoformat()
        meta = {
            _META_KEY: CORRECTIONS_FORMAT_VERSION,
            "source": self.source,
            "created_utc": self.created_utc,
        }
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            f.attrs["meta"] = json.dumps(meta)
            g2 = f.create_group("pose2d_corrections")
            g2.create_dataset("points", data=self.points, dtype=np.float64)
            for name in ("edited", "fixed", "invisible"):
                g2.create_dataset(name, data=getattr(self, name), dtype=bool)
            g3 = f.create_group("pose3d_corrections")
            g3.create_dataset("points3d", data=self.points3d, dtype=np.float64)
            g3.create_dataset("edited", data=self.edited3d, dtype=bool)
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
        """Clear the edits and flags of a point (in one view or all), a view or a frame.

        ``reset(t)``: the whole frame; ``reset(t, point=p)``: point ``p`` in every view and
        its 3D edit; ``reset(t, point=p, view=v)``: one observation; ``reset(t, view=v)``:
        every point of one view.
        """
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

    def corrected_points(self) -> Bool[np.ndarray, "T P"]:
        """``(T, P)`` bool: 3D points whose input a person changed (any view, or in 3D)."""
        return self.touched().any(axis=0) | self.edited3d

    def count(self) -> int:
        """Number of edited or invisible observations plus edited 3D points."""
        return int(self.touched().sum() + self.edited3d.sum())

    def apply_2d(
        self, pts2d: Float[np.ndarray, "V T P 2"], conf: Float[np.ndarray, "V T P"] | None = None
    ) -> tuple[Float[np.ndarray, "V T P 2"], Float[np.ndarray, "V T P"] | None]:
        """The 2D triangulation reads: edits replace detections, invisible ones go.

        Parameters
        ----------
        pts2d
            ``(V, T, P, 2)`` detected (or pictorial-structures) 2D.
        conf
            ``(V, T, P)`` confidences or ``None``; an edit gets confidence 1.

        Returns
        -------
        pts2d, conf
            Corrected copies.
        """
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
            source=self.source,
        )


def reconstruct_corrected(
    config: Any,
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None = None,
    corrections: Corrections | None = None,
) -> tuple[
    Float[np.ndarray, "T P 3"],
    Float[np.ndarray, "V T P 2"],
    Float[np.ndarray, "V T P"],
    Bool[np.ndarray, "T P"],
]:
    """Triangulate as ``config.triangulation`` says, with manual corrections applied.

    Parameters
    ----------
    config
        The run config (its ``triangulation`` table).
    cameras
        The final rig (first, as in every triangulation function).
    pts2d
        ``(V, T, P, 2)`` the 2D triangulation reads (pose2d or pictorial structures).
    conf
        ``(V, T, P)`` or ``None``.
    corrections
        The sidecar's edits for exactly these ``(V, T, P)``, or ``None``.

    Returns
    -------
    pts3d, pts2d_clean, reproj_error, corrected
        ``(T, P, 3)``, ``(V, T, P, 2)`` (the views the points were solved from),
        ``(V, T, P)`` pixels and ``(T, P)`` bool (points a correction changed).

    Raises
    ------
    TypeError
        If the points and the rig are swapped (the order before the rig came first).
    """
    from . import camera_model
    from .triangulation import reconstruct_from_config, reprojection_error

    if hasattr(pts2d, "pmats") or not hasattr(cameras, "pmats"):
        raise TypeError(
            "reconstruct_corrected(config, cameras, pts2d, ...) takes the rig before "
            f"the points, got {type(cameras).__name__} for cameras"
        )
    pts2d = np.asarray(pts2d, dtype=np.float64)
    if corrections is None:
        pts3d, clean, error = reconstruct_from_config(config, cameras, pts2d, conf)
        return pts3d, clean, error, np.zeros(pts2d.shape[1:3], bool)
    if corrections.shape != pts2d.shape[:3]:
        raise ResultsError(
            f"corrections of shape {corrections.shape} (views, frames, points) do not "
            f"match the 2D points {pts2d.shape[:3]}; save them again from `flylib gui`"
        )
    pts2d, conf = corrections.apply_2d(pts2d, conf)
    pts3d, clean, error = reconstruct_from_config(config, cameras, pts2d, conf)
    fixed = corrections.fixed & corrections.edited & np.isfinite(pts2d).all(-1)
    lost = fixed & ~np.isfinite(clean).all(-1)  # fixed views the robust fit left out
    redo = np.argwhere(lost.any(axis=0))  # (n, 2) frame, point
    if len(redo):
        t, p = redo[:, 0], redo[:, 1]
        keep = np.isfinite(clean[:, t, p]).all(-1) | fixed[:, t, p]  # (V, n)
        obs = np.where(keep[..., None], pts2d[:, t, p], np.nan)
        und = cameras.undistort_points(obs) if np.any(cameras.dists) else obs
        pts3d[t, p] = camera_model.dlt_solve(np, und, cameras.pmats)
        clean[:, t, p] = obs
    if corrections.edited3d.any():
        pts3d = pts3d.copy()
        pts3d[corrections.edited3d] = corrections.points3d[corrections.edited3d]
    if len(redo) or corrections.edited3d.any():
        error = reprojection_error(cameras, pts3d, clean)
    return pts3d, clean, error, corrections.corrected_points()


def corrections_path(
    config: Any,
    outdir: str | Path,
    recording_dir: str | Path | None = None,
    recording_id: str | None = None,
) -> tuple[Path, bool]:
    """Where a recording's corrections sidecar is, and whether the config named it.

    ``<outdir>/corrections.h5`` unless the config's ``corrections`` key gives a path
    template (placeholders ``{outdir}``, ``{recording}``, ``{id}``, ``{name}``; a
    relative path is relative to the outdir).

    Returns
    -------
    path, named
        The sidecar's path (it may not exist) and whether ``corrections`` named it.

    Raises
    ------
    ConfigError
        On an unknown placeholder or a non-string value.
    """
    from .errors import ConfigError

    outdir = Path(outdir)
    data = getattr(config, "data", config) or {}
    template = data.get("corrections")
    if template is None:
        return outdir / CORRECTIONS_FILE, False
    if not isinstance(template, str) or not template.strip():
        raise ConfigError(
            f"corrections: expected the path (template) of a corrections.h5 or null, "
            f"got {template!r}"
        )
    recording = Path(recording_dir) if recording_dir is not None else outdir
    try:
        text = template.format(
            outdir=str(outdir),
            recording=str(recording),
            id=recording_id or recording.name,
            name=recording.name,
        )
    except (KeyError, IndexError, ValueError) as exc:
        raise ConfigError(
            f"corrections: unknown placeholder {exc} in {template!r}; use {{outdir}}, "
            "{recording}, {id} or {name}"
        ) from None
    path = Path(text).expanduser()
    return (path if path.is_absolute() else outdir / path), True


def read_corrected(results_path: str | Path) -> Bool[np.ndarray, "T P"] | None:
    """``(T, P)`` bool: the points of a ``results.h5`` a person corrected, or ``None``
    when it was computed without corrections (``triangulation/corrected``)."""
    from .results import open_checked

    with open_checked(results_path) as f:
        if "triangulation/corrected" not in f:
            return None
        return np.asarray(f["triangulation/corrected"][()], dtype=bool)
