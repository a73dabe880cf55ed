"""DeepFly3D files: the 2D result pickle and the calibration pickle.

2D (``df3d_result*.pkl``, a pickled dict). ``points2d`` ``(C, T, J, 2)`` comes in two layouts, told
apart by its values (:func:`points2d_layout`):

- 0.x, normalized: ``[..., 0]`` is row / height (y), ``[..., 1]`` column / width (x), in ``[0, 1]``;
  undetected is ``(0, 0)``, or ``(0, 1)`` in mirrored cameras. Pixels are ``x = col * width``,
  ``y = row * height`` (no half-cell shift: how DeepFly3D scales its heatmap grid back).
- 1.x (the ``df3d`` package): raw-frame pixels ``(x, y)``, undetected ``(0, 0)``; the pickle also
  holds the calibration (NumPy-integer camera keys) and ``points3d``.

``heatmap_confidence`` ``(C, T, K, 1)``: the heatmap peak per channel; the network has ``K = J / 2``
channels, run on one side of the fly at a time, so joint ``j`` takes channel ``j mod K``.
``camera_ordering`` ``(C,)``: DeepFly3D's ``cidread2cid``; row ``i`` of ``points2d`` goes on the
``i``-th configured view (or ``views[i]``).

Joint order: joints 0-18 are the side seen by cameras 0-2, 19-37 the side seen by cameras 4-6;
within a side: front, middle, hind leg (thorax-coxa, coxa-trochanter, femur-tibia, tibia-tarsus,
claw), antenna, abdomen 0-2. Cameras 0-2 (rh, rm, rf) film the right flank, so joint ``j`` is fly38
point ``(j + 19) mod 38`` (pinned in ``tests/interop/test_interop.py``).

Calibration (a pickled dict): per integer camera index, ``R`` (3x3 world-to-camera), ``tvec`` (3,),
``intr`` (3x3 K) and ``distort`` (5, OpenCV order), projecting to raw-frame (x, y) pixels; other
keys are ignored."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ImportFormatError
from .calib_checks import camera_value, numeric_array
from .safe_pickle import load_restricted

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int


def _fly38_names() -> tuple[str, ...]:
    names: list[str] = []
    for side in ("l", "r"):
        for limb in ("f", "m", "h"):
            names += [
                f"{side}{limb}_{j}"
                for j in ("thorax_coxa", "coxa_trochanter", "femur_tibia", "tibia_tarsus", "claw")
            ]
        names += [f"{side}_antenna", f"{side}_abdomen0", f"{side}_abdomen1", f"{side}_abdomen2"]
    return tuple(names)


#: fly38 point names, in fly38 order (``../shared/spec/fly38-rig.yaml``).
FLY38_POINT_NAMES: tuple[str, ...] = _fly38_names()


def df3d_joint_to_fly38(joint: int) -> str:
    """The fly38 point name of DeepFly3D joint ``joint`` (``(joint + 19) mod 38``)."""
    return FLY38_POINT_NAMES[(int(joint) + 19) % 38]


@dataclass
class Df3dPoints2d:
    """DeepFly3D 2D output in raw-frame pixels: ``xy`` ``(C, T, J, 2)`` pixel ``(x, y)`` and
    ``conf`` ``(C, T, J)`` (the heatmap peak of the joint's channel), NaN where the joint was not
    detected, and DeepFly3D's ``camera_ordering`` (``cidread2cid``) ``(C,)``."""

    xy: Float[np.ndarray, "C T J 2"]
    conf: Float[np.ndarray, "C T J"]
    camera_ordering: Int[np.ndarray, " C"]


def result_folders(recording_dir: Path) -> tuple[str, ...]:
    """Where DeepFly3D's result pickles of a recording may lie, relative to it: beside the footage,
    in ``df3d/`` (DeepFly3D 0.x) or in ``<name>_df3d`` (``df3d-cli``'s default output folder)."""
    return ("", "df3d/", f"../{recording_dir.name}_df3d/")


def load_pickle(path: Path, what: str) -> dict:
    path = Path(path)
    if not path.is_file():
        raise ImportFormatError(f"{path}: no such {what}; check the path in the config")
    data = load_restricted(path, what)
    if not isinstance(data, dict):
        raise ImportFormatError(
            f"{path}: a {what} pickle must hold a dict, got {type(data).__name__}"
        )
    return data


def read_df3d_points2d(path: Path, image_sizes: list[tuple[int, int]]) -> Df3dPoints2d:
    """Read a DeepFly3D 2D result pickle into raw-frame pixels; ``image_sizes``: ``(height,
    width)`` of each camera row's frames (the normalization base)."""
    data = load_pickle(path, "DeepFly3D 2D result")
    if "points2d" not in data:
        raise ImportFormatError(
            f"{path}: no 'points2d' key (keys: {sorted(map(str, data))}); "
            "pass DeepFly3D's df3d_result*.pkl"
        )
    fix = "pass DeepFly3D's df3d_result*.pkl unchanged"
    norm = numeric_array(data["points2d"], str(path), "points2d", fix)
    if norm.ndim != 4 or norm.shape[-1] != 2:
        raise ImportFormatError(
            f"{path}: 'points2d' has shape {norm.shape}, expected (cameras, frames, joints, 2); {fix}"
        )
    n_cams, n_frames, n_joints, _ = norm.shape
    if len(image_sizes) != n_cams:
        raise ImportFormatError(
            f"{path}: holds {n_cams} cameras but {len(image_sizes)} views are configured; "
            "set pose2d.import.views to name the view of each pickle camera"
        )
    sizes = np.asarray(image_sizes, dtype=np.float64)  # (C, 2) = (h, w)
    if points2d_layout(norm, sizes, path) == "pixels":
        missing = (norm == 0).all(-1) | ~np.isfinite(norm).all(-1)
        xy = norm.copy()
    else:
        row, col = norm[..., 0], norm[..., 1]
        missing = (row == 0) & ((col == 0) | (col == 1)) | ~np.isfinite(norm).all(-1)
        xy = np.stack([col * sizes[:, 1, None, None], row * sizes[:, 0, None, None]], axis=-1)
    xy[missing] = np.nan

    conf = np.ones((n_cams, n_frames, n_joints))
    if "heatmap_confidence" in data:
        heat = numeric_array(data["heatmap_confidence"], str(path), "heatmap_confidence", fix)
        if heat.ndim < 3 or heat.size != np.prod(heat.shape[:3]):
            raise ImportFormatError(
                f"{path}: 'heatmap_confidence' has shape {heat.shape}, expected (cameras, frames, channels, 1); {fix}"
            )
        heat = heat.reshape(heat.shape[:3])
        if heat.shape[:2] != (n_cams, n_frames) or heat.shape[2] == 0 or n_joints % heat.shape[2]:
            raise ImportFormatError(
                f"{path}: 'heatmap_confidence' shape {heat.shape} does not fit 'points2d' {norm.shape}; {fix}"
            )
        conf = heat[:, :, np.arange(n_joints) % heat.shape[2]]
    conf[missing] = np.nan
    ordering = _camera_ordering(data, path, n_cams)
    return Df3dPoints2d(xy=xy, conf=conf, camera_ordering=ordering)


#: How far (as a fraction of the frame) a 1.x pixel coordinate may lie outside its frame before the
#: file is refused: DeepFly3D's heatmap grid reaches the border.
_PIXEL_MARGIN = 0.05


def points2d_layout(
    points2d: Float[np.ndarray, "C T J 2"],
    image_sizes: Float[np.ndarray, "C 2"],
    path: Path | str = "points2d",
) -> str:
    """``"normalized"`` (0.x: every detected coordinate in ``[0, 1]``) or ``"pixels"`` (1.x, which
    must lie within each camera's ``(height, width)``); cameras that disagree are an
    :class:`ImportFormatError`."""
    finite = np.isfinite(points2d).all(-1)
    detected = finite & ~(points2d == 0).all(-1)
    pixel_cams = [
        c for c in range(points2d.shape[0]) if (np.abs(points2d[c][detected[c]]) > 1).any()
    ]
    if not pixel_cams:
        return "normalized"
    normalized_cams = [
        c for c in range(points2d.shape[0]) if detected[c].any() and c not in pixel_cams
    ]
    if normalized_cams:
        raise ImportFormatError(
            f"{path}: 'points2d' is ambiguous: camera(s) {normalized_cams} hold only values "
            f"in [0, 1] (DeepFly3D 0.x, normalized) but camera(s) {pixel_cams} hold pixels "
            "(DeepFly3D 1.x); pass one DeepFly3D result unchanged, not a merge of two"
        )
    sizes = np.asarray(image_sizes, np.float64)
    for c in pixel_cams:
        xy = points2d[c][detected[c]]
        height, width = sizes[c]
        low = -_PIXEL_MARGIN * np.array([width, height])
        high = (1 + _PIXEL_MARGIN) * np.array([width, height])
        outside = (xy < low) | (xy > high)
        if outside.any():
            worst = xy[outside.any(-1)][0]
            raise ImportFormatError(
                f"{path}: 'points2d' of camera {c} is in pixels (DeepFly3D 1.x) but holds "
                f"(x, y) = ({worst[0]:g}, {worst[1]:g}), outside its {width:g}x{height:g} frames; "
                "check the footage's size (or pose2d.import.image_size) and that the file "
                "is DeepFly3D's result unchanged"
            )
    return "pixels"


def _camera_ordering(data: dict, path: Path, n_cams: int) -> np.ndarray:
    """``camera_ordering`` as ``(C,)`` distinct integers (default ``0..C-1``)."""
    if "camera_ordering" not in data:
        return np.arange(n_cams)
    fix = (
        f"it must list {n_cams} distinct integer camera indices (DeepFly3D's cidread2cid); "
        "delete the key to take the rows in order"
    )
    ordering = numeric_array(data["camera_ordering"], str(path), "camera_ordering", fix)
    if (
        ordering.shape != (n_cams,)
        or not np.isfinite(ordering).all()
        or (ordering != np.round(ordering)).any()
        or len(set(ordering.tolist())) != n_cams
    ):
        raise ImportFormatError(f"{path}: 'camera_ordering' is {ordering.tolist()}; {fix}")
    return ordering.astype(int)


def read_df3d_calibration(path: Path) -> dict[int, dict[str, np.ndarray]]:
    """Read a DeepFly3D calibration pickle: ``camera index -> {"rvec", "tvec", "kmat", "dist"}``
    (float64), sorted by index."""
    import cv2

    data = load_pickle(path, "DeepFly3D calibration")
    out: dict[int, dict[str, np.ndarray]] = {}
    for key, entry in data.items():
        try:
            index = int(key)
        except (TypeError, ValueError, OverflowError):
            continue  # DeepFly3D stores extra, non-camera keys beside the cameras
        if not isinstance(entry, dict):
            continue
        missing = [k for k in ("R", "tvec", "intr") if k not in entry]
        if missing:
            raise ImportFormatError(
                f"{path}: camera {index} lacks {missing}; a DeepFly3D calibration needs "
                "R (3x3), tvec (3), intr (3x3) and distort (5) per camera"
            )
        where = f"{path}: camera {index}"
        rmat = camera_value(entry["R"], "rotmat", where, "R")
        rvec, _ = cv2.Rodrigues(rmat)
        out[index] = {
            "rvec": rvec.ravel(),
            "tvec": camera_value(entry["tvec"], "vec3", where, "tvec"),
            "kmat": camera_value(entry["intr"], "matrix", where, "intr"),
            "dist": camera_value(entry.get("distort", np.zeros(5)), "dist", where, "distort"),
        }
    if not out:
        raise ImportFormatError(
            f"{path}: no per-camera entries (integer keys) in the calibration pickle"
        )
    return dict(sorted(out.items()))
