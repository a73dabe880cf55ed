"""The assembled result of one recording, :class:`PoseResult`, and its corrected detections."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ResultsError
from ..paths import atomic_path
from ..skeleton import Skeleton
from ..stages import FINAL_3D
from .checksums import check_group
from .datasets import json_attrs, read_dataset, read_json_attrs, write_array
from .groups import cameras_from_group, skeleton_from_group, write_cameras, write_skeleton
from .hdf5 import create_file, new_meta, read_checked, read_meta_from

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..camera.rig import CameraGroup


def _float_or_none(value: Any) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)


@dataclass
class PoseResult:
    """A complete multi-view pose estimate of one recording: the rig (bundle-adjusted when that
    stage ran), the skeleton, ``pts2d`` in raw-frame pixels (NaN = missing), ``conf``, ``pts3d``
    (NaN = not reconstructed), ``reproj_error`` in pixels, ``meta`` (format version, creation
    time, ...) and ``image_sizes`` (``view -> (height, width)`` of the raw footage, if known)."""

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
        """Write the result to an HDF5 file, atomically: ``pts2d``/``conf`` and the rig to
        ``pose2d/``; with a 3D pose, ``pts2d``, ``pts3d`` and ``reproj_error`` also to
        ``triangulation/``, so :meth:`load` returns the same result."""
        # A loaded result keeps its creation time and stage; version fields are this writer's.
        fresh = new_meta("result")
        meta = {**fresh, **self.meta}
        meta["deeperfly_format_version"] = fresh["deeperfly_format_version"]
        meta["flylib_version"] = fresh["flylib_version"]
        with atomic_path(path) as tmp, create_file(tmp) as f:
            f.attrs["meta"] = json.dumps(meta)
            write_skeleton(f.create_group("skeleton"), self.skeleton)
            g2d = f.create_group("pose2d")
            write_array(g2d, "points", self.pts2d)
            if self.conf is not None:
                write_array(g2d, "conf", self.conf)
            write_cameras(g2d.create_group("cameras"), self.cameras)
            json_attrs(g2d, {"view_names": list(self.cameras.names)})
            if self.image_sizes is not None:
                json_attrs(g2d, {"image_sizes": {k: list(v) for k, v in self.image_sizes.items()}})
            if self.pts3d is not None or self.reproj_error is not None:
                g3d = f.create_group("triangulation")
                write_array(g3d, "points", self.pts2d)
                if self.pts3d is not None:
                    write_array(g3d, "points3d", self.pts3d)
                if self.reproj_error is not None:
                    write_array(g3d, "reproj_error", self.reproj_error)

    @classmethod
    def load(cls, path: str | Path) -> PoseResult:
        """Read a file :meth:`save` or :func:`assemble_results` wrote, preferring the most-derived
        data present: ``pts2d`` from refinement, else triangulation, else pictorial_structures,
        else pose2d; ``pts3d`` and ``reproj_error`` likewise but for pose2d; the rig from
        bundle_adjustment, else pose2d's (the config's). A ResultsError if the file is missing,
        of another format version, or has no pose2d data or no rig."""
        rerun = "re-run the pipeline"
        with read_checked(path, rerun) as f:
            if "pose2d/points" not in f:
                raise ResultsError(f"{path}: has no pose2d group (no 2D points); {rerun}")
            if "skeleton" not in f:
                raise ResultsError(f"{path}: has no skeleton group; {rerun}")
            meta = read_meta_from(f)
            meta.pop("deeperfly_format_version", None)
            skeleton = skeleton_from_group(f["skeleton"])
            rig = next(
                (f[f"{s}/cameras"] for s in ("bundle_adjustment", "pose2d") if f"{s}/cameras" in f),
                None,
            )
            if rig is None:
                raise ResultsError(
                    f"{path}: has no cameras (pose2d/cameras); assemble it with assemble_results"
                )
            cameras = cameras_from_group(rig)

            read: list[str] = []

            def first(name: str, stages: tuple[str, ...]) -> np.ndarray | None:
                stage = next((s for s in stages if f"{s}/{name}" in f), None)
                if stage is None:
                    return None
                read.append(f"/{stage}/{name}")
                return read_dataset(f[f"{stage}/{name}"])

            pts2d = first("points", (*FINAL_3D, "pose2d"))
            pts3d = first("points3d", FINAL_3D)
            reproj = first("reproj_error", FINAL_3D)
            conf = first("conf", ("pose2d",))
            sizes = read_json_attrs(f["pose2d"]).get("image_sizes")
            check_group(path, f, skip=read)  # damage in what was not loaded is damage too
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


@dataclass(frozen=True)
class Detections:
    """The 2D detections of a result with the manual corrections applied: ``points`` is
    ``pose2d/points`` but where a person edited a point (that point) or marked it invisible
    (NaN); ``conf`` their confidences (1 for an edit, NaN where invisible) or ``None``;
    ``corrected`` how many observations a person changed."""

    points: Float[np.ndarray, "V T P 2"]
    conf: Float[np.ndarray, "V T P"] | None
    corrected: int


def apply_edits(values: np.ndarray, touched: np.ndarray, edited: np.ndarray) -> np.ndarray:
    """``values`` ``(V, T, P, ...)`` with the entries ``touched`` ``(V, T, P)`` replaced
    by ``edited`` (the triangulation's ``corrected_2d`` and ``edited_2d``)."""
    touched = np.asarray(touched, bool).reshape(touched.shape + (1,) * (values.ndim - 3))
    return np.where(touched, edited, values)


def read_detections(path: str | Path) -> Detections:
    """The detections in ``results.h5`` at ``path``, corrections applied.

    The corrections the triangulation applied are in its group (``corrected_2d``, the mask, and
    ``edited_2d``, a person's 2D, NaN = marked invisible); ``pose2d/points`` itself holds the
    detections as detected. A ResultsError if the file has no ``pose2d/points``, or holds
    corrections without the 2D they set.
    """
    rerun = "re-run the pipeline"
    with read_checked(path, rerun) as f:
        if "pose2d/points" not in f:
            raise ResultsError(f"{path}: has no pose2d group (no 2D points); {rerun}")
        points = read_dataset(f["pose2d/points"])
        conf = read_dataset(f["pose2d/conf"]) if "pose2d/conf" in f else None
        if "triangulation/corrected_2d" not in f:
            return Detections(points, conf, 0)
        if "triangulation/edited_2d" not in f:
            raise ResultsError(
                f"{path}: holds corrections (triangulation/corrected_2d) but not the 2D they "
                "set (written by an older flylib); re-run the triangulation stage"
            )
        touched = np.asarray(read_dataset(f["triangulation/corrected_2d"]), bool)
        edited = read_dataset(f["triangulation/edited_2d"])
    points = apply_edits(points, touched, edited)
    if conf is not None:
        conf = apply_edits(conf, touched, np.where(np.isfinite(edited).all(-1), 1.0, np.nan))
    return Detections(points, conf, int(touched.sum()))
