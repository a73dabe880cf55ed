"""The embedded demo: a small synthetic recording generated deterministically.

:func:`write_demo` writes, into one directory, what a real experiment would give flylib with
the 2D coming from another tool (:func:`flylib.pipeline.demo.make_demo` gives it a config's rig,
skeleton, sources and ``demo`` table):

- one H.264 video per configured source (``camera_N.mp4`` for the default rig), rendering a
  walking fly skeleton through the configured camera rig;
- one DeepLabCut CSV per view with the 2D keypoints a detector would report: the true
  projections plus pixel noise, dropouts (missing points) and a few gross outliers, only for
  the points each view observes (the config's ``pose2d.output_points``);
- ``truth.h5``: the 3D truth ``(T, P, 3)`` and its exact projections;
- ``nwb.yaml``: the (synthetic) session metadata the NWB export reads.

The workflow imports the CSVs through ``pose2d.import`` (format ``dlc``), so the demo needs no
detector weights and no network. :func:`demo_error` compares a reconstruction with the truth.
:func:`synthetic_fly` is the motion model (a tethered fly walking in a tripod gait) and is what
the test-suite's synthetic data builds on too.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .alignment import similarity_aligned
from .errors import ConfigError, did_you_mean
from .interop.df3d import FLY38_POINT_NAMES
from .paths import atomic_path
from .recordings.listing import DLC_SCORER, TRUTH_FILE

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

    from .camera.rig import CameraGroup
    from .skeleton import Skeleton

log = logging.getLogger(__name__)

#: Demo parameters (the config's ``demo`` table overrides them).
DEMO_DEFAULTS: dict[str, Any] = {
    "frames": 60,
    "height": 480,
    "width": 960,
    "fps": 100.0,
    "seed": 0,
    "noise_px": 1.0,
    "dropout": 0.05,
    "outliers": 0.01,
    "outlier_px": [40.0, 120.0],
    # the workflow's videos of the demo play at this multiple of fps (slow motion: the legs step
    # at 6-10 Hz); a rate set in the visualization table wins
    "video_speed": 0.1,
}


_JOINTS = ("thorax_coxa", "coxa_trochanter", "femur_tibia", "tibia_tarsus", "claw")
#: fly38 point order (left side 0-18, right side 19-37), as in the default skeleton.
FLY38_POINTS: tuple[str, ...] = FLY38_POINT_NAMES

# Leg geometry in world units of the default rig (about millimetres).
_SEGMENTS = np.array([0.30, 0.70, 0.65, 0.55])  # coxa, femur, tibia, tarsus
_PITCH_DEG = np.array([65.0, -10.0, 55.0, 80.0])  # each segment's angle below horizontal
_COXA_X = {"f": 0.35, "m": 0.0, "h": -0.30}
_COXA_Y = {"f": 0.14, "m": 0.20, "h": 0.17}
_YAW_DEG = {"f": 45.0, "m": 0.0, "h": -40.0}  # from lateral towards the head
_GAIT_PHASE = {"lf": 0.0, "rm": 0.0, "lh": 0.0, "rf": np.pi, "lm": np.pi, "rh": np.pi}
_BODY_Z = 0.60  # lifts the fly so that legs and antennae are centred in the frame


def synthetic_fly(
    n_frames: int, seed: int = 0, *, fps: float = 100.0
) -> Float[np.ndarray, "T 38 3"]:
    """A tethered fly walking in a tripod gait: ``(n_frames, 38, 3)`` float64 world points,
    sampled at ``fps``.

    Points are in :data:`FLY38_POINTS` order. The head points to +x (the default rig's front
    camera ``f``, azimuth 0), the left side to +y (cameras ``lf/lm/lh``), up is +z. Each leg is a
    chain of four segments of constant length whose yaw and pitches oscillate at a random step
    frequency (``seed`` draws it and the phase) around 8 Hz, legs of one tripod in phase;
    antennae and abdomen move slightly. Every bone keeps its length exactly.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / fps
    freq = rng.uniform(6.0, 10.0)
    phase0 = rng.uniform(0, 2 * np.pi)
    out = np.zeros((n_frames, len(FLY38_POINTS), 3))
    index = {n: i for i, n in enumerate(FLY38_POINTS)}
    for side, sign in (("l", 1.0), ("r", -1.0)):
        for pos in ("f", "m", "h"):
            leg = f"{side}{pos}"
            sin = np.sin(2 * np.pi * freq * t + phase0 + _GAIT_PHASE[leg])
            cos = np.cos(2 * np.pi * freq * t + phase0 + _GAIT_PHASE[leg])
            yaw = np.deg2rad(_YAW_DEG[pos] + 18.0 * sin)
            pitch = np.deg2rad(_PITCH_DEG)[None, :] + np.deg2rad(
                np.stack([5 * cos, 15 * cos, -15 * sin, 8 * sin], axis=1)
            )
            lateral = np.stack([np.sin(yaw), sign * np.cos(yaw), np.zeros_like(yaw)], -1)
            joint = np.tile([_COXA_X[pos], sign * _COXA_Y[pos], _BODY_Z - 0.12], (n_frames, 1))
            names = [f"{leg}_{j}" for j in _JOINTS]
            out[:, index[names[0]]] = joint
            for s, length in enumerate(_SEGMENTS):
                direction = np.cos(pitch[:, s : s + 1]) * lateral
                direction[:, 2] = -np.sin(pitch[:, s])
                joint = joint + length * direction
                out[:, index[names[s + 1]]] = joint
        wiggle = 0.03 * np.sin(2 * np.pi * 3.0 * t + sign)[:, None]
        out[:, index[f"{side}_antenna"]] = [0.80, sign * 0.12, _BODY_Z + 0.30] + wiggle
        # the abdomen pitches as one rigid piece about its first stripe (its "bones" keep their
        # lengths): the tip rises and falls by about 0.05
        pitch = 0.05 / 0.8 * np.sin(2 * np.pi * 1.5 * t + phase0)
        base = np.array(
            [
                (-0.45, sign * 0.22, _BODY_Z + 0.05),
                (-0.85, sign * 0.20, _BODY_Z),
                (-1.25, sign * 0.12, _BODY_Z - 0.05),
            ]
        )
        for k, point in enumerate(base):
            rel = point - base[0]
            i = index[f"{side}_abdomen{k}"]
            out[:, i, 0] = base[0, 0] + rel[0] * np.cos(pitch) - rel[2] * np.sin(pitch)
            out[:, i, 1] = point[1]
            out[:, i, 2] = base[0, 2] + rel[0] * np.sin(pitch) + rel[2] * np.cos(pitch)
    return out


def demo_settings(table: Mapping[str, Any] | None) -> dict[str, Any]:
    """The demo parameters: :data:`DEMO_DEFAULTS` updated by the config's ``demo`` table
    (``None``: the defaults); ConfigError on an unknown key or an out-of-range value."""
    table = table or {}
    if not isinstance(table, Mapping):
        raise ConfigError(f"demo: must be a mapping of demo parameters, got {table!r}")
    unknown = sorted(set(table) - set(DEMO_DEFAULTS))
    if unknown:
        raise ConfigError(
            f"demo: unknown key(s) {unknown}; {did_you_mean(unknown[0], DEMO_DEFAULTS)}allowed: {sorted(DEMO_DEFAULTS)}"
        )
    settings = {**DEMO_DEFAULTS, **table}
    for key in ("frames", "height", "width"):
        if not isinstance(settings[key], int) or settings[key] < 2:
            raise ConfigError(f"demo.{key}: must be an integer >= 2, got {settings[key]!r}")
    for key in ("dropout", "outliers"):
        if not 0.0 <= float(settings[key]) < 1.0:
            raise ConfigError(f"demo.{key}: must be a fraction in [0, 1), got {settings[key]!r}")
    if float(settings["noise_px"]) < 0 or float(settings["fps"]) <= 0:
        raise ConfigError("demo.noise_px must be >= 0 and demo.fps > 0")
    speed = settings["video_speed"]
    if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not 0 < speed <= 10:
        raise ConfigError(f"demo.video_speed: must be a number in (0, 10], got {speed!r}")
    return settings


def view_visibility(
    output_points: Mapping[str, Any] | None, view_names: list[str], point_names: list[str]
) -> Bool[np.ndarray, "V P"]:
    """``(V, P)`` bool: the points each view observes, from ``pose2d.output_points``
    (``view -> {point: ...}``, or ``None``); a view with no table observes every point."""
    tables = output_points or {}
    vis = np.ones((len(view_names), len(point_names)), bool)
    for v, view in enumerate(view_names):
        if tables.get(view):
            vis[v] = [p in tables[view] for p in point_names]
    return vis


def observe(
    clean2d: np.ndarray,
    visible: np.ndarray,
    settings: Mapping[str, Any],
    image_size: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Corrupt the exact projections ``clean2d`` ``(V, T, P, 2)`` like a detector: noise,
    dropouts and gross outliers (kept inside the ``(height, width)`` frame), as
    :func:`demo_settings` says (``noise_px``, ``dropout``, ``outliers``, ``outlier_px``,
    ``seed``); points a view does not observe (``visible`` ``(V, P)``) are NaN.

    Returns ``pts2d`` ``(V, T, P, 2)`` observed pixels (NaN = missing) and ``likelihood``
    ``(V, T, P)``: in ``[0.7, 1]`` for inliers, ``[0.3, 0.8]`` for outliers, NaN where missing.
    """
    rng = np.random.default_rng(int(settings["seed"]) + 1)
    pts2d = clean2d + rng.normal(0.0, float(settings["noise_px"]), clean2d.shape)
    likelihood = rng.uniform(0.7, 1.0, clean2d.shape[:3])
    seen = np.broadcast_to(visible[:, None, :], likelihood.shape)
    outlier = seen & (rng.random(likelihood.shape) < float(settings["outliers"]))
    low, high = (float(x) for x in settings["outlier_px"])
    angle = rng.uniform(0, 2 * np.pi, likelihood.shape)
    radius = rng.uniform(low, high, likelihood.shape)
    shifted = clean2d + np.stack([np.cos(angle), np.sin(angle)], -1) * radius[..., None]
    height, width = image_size
    shifted = np.clip(shifted, [0.0, 0.0], [width - 1.0, height - 1.0])
    pts2d = np.where(outlier[..., None], shifted, pts2d)
    likelihood = np.where(outlier, rng.uniform(0.3, 0.8, likelihood.shape), likelihood)
    dropped = rng.random(likelihood.shape) < float(settings["dropout"])
    present = seen & ~dropped & np.isfinite(clean2d).all(-1)
    pts2d = np.where(present[..., None], pts2d, np.nan)
    likelihood = np.where(present, likelihood, np.nan)
    return pts2d, likelihood


def render_frames(
    points2d: np.ndarray,
    bones: np.ndarray,
    colors: list[tuple[int, int, int]],
    image_size: tuple[int, int],
):
    """Yield ``(H, W, 3)`` uint8 frames of one view's ``points2d`` ``(T, P, 2)``: the skeleton
    (one RGB colour per bone) drawn on a dark, slightly textured background (so the video has
    something to encode); ``image_size`` is ``(height, width)``."""
    import cv2

    height, width = image_size
    yy, xx = np.mgrid[0:height, 0:width]
    background = (18 + 10 * np.sin(xx / 37.0) * np.cos(yy / 23.0)).astype(np.uint8)
    background = np.repeat(background[..., None], 3, axis=2)
    shift = 4  # sub-pixel precision of cv2 drawing: coordinates * 2**shift

    def fixed(p: np.ndarray) -> tuple[int, int]:
        return int(round(p[0] * (1 << shift))), int(round(p[1] * (1 << shift)))

    for frame_points in points2d:
        frame = background.copy()
        for (a, b), color in zip(bones, colors):
            pa, pb = frame_points[a], frame_points[b]
            if np.isfinite(pa).all() and np.isfinite(pb).all():
                cv2.line(frame, fixed(pa), fixed(pb), color, 3, cv2.LINE_AA, shift)
        for p in frame_points:
            if np.isfinite(p).all():
                cv2.circle(frame, fixed(p), 4 << shift, (235, 235, 235), -1, cv2.LINE_AA, shift)
        yield frame


def _hex_to_rgb(color: str) -> tuple[int, int, int]:
    text = color.lstrip("#")
    return int(text[0:2], 16), int(text[2:4], 16), int(text[4:6], 16)


@dataclass
class DemoRecording:
    """What :func:`write_demo` wrote."""

    directory: Path
    footage: dict[str, Path]
    dlc: dict[str, Path]
    truth: Path
    points3d: Float[np.ndarray, "T P 3"]
    points2d: Float[np.ndarray, "V T P 2"]


def write_demo(
    directory: str | Path,
    settings: Mapping[str, Any],
    skeleton: Skeleton,
    cameras: CameraGroup,
    visible: Bool[np.ndarray, "V P"],
    view_sources: Mapping[str, str],
    source_files: Mapping[str, str],
    dlc_files: Sequence[str],
) -> DemoRecording:
    """Write the demo recording (footage, per-view DeepLabCut CSVs, ``truth.h5``) into
    ``directory`` (created if needed); the same arguments give the same keypoints and truth.

    ``settings``: :func:`demo_settings`. ``skeleton``: the fly38 skeleton (any point order),
    what is animated and drawn. ``cameras``: the rig the fly is rendered through (principal
    points for the settings' image size); its names are the views. ``visible``: ``(V, P)``, the
    points each view observes (:func:`view_visibility`). ``view_sources``:
    ``view -> footage source`` (a source feeding several views is rendered once);
    ``source_files``: ``source -> footage file name`` (an ``.mp4`` in ``directory``);
    ``dlc_files``: one DeepLabCut CSV name per view, in view order.

    ConfigError if the skeleton is not the fly's 38 points, or the fly projects outside a view's
    frame.
    """
    from .interop.dlc import write_dlc_csv
    from .io import VideoWriter

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    points = list(skeleton.point_names)
    if set(points) != set(FLY38_POINTS):
        raise ConfigError(
            "skeleton: the demo animates the fly38 skeleton; its point_names "
            f"must be the 38 fly points (got {len(points)} points)"
        )
    order = [FLY38_POINTS.index(p) for p in points]
    pts3d = synthetic_fly(settings["frames"], settings["seed"], fps=float(settings["fps"]))[
        :, order
    ]
    image_size = (settings["height"], settings["width"])
    views = list(cameras.names)
    clean2d = np.asarray(cameras.project(pts3d), dtype=np.float64)  # (V, T, P, 2)
    _check_in_frame(clean2d, image_size, views)
    observed, likelihood = observe(clean2d, visible, settings, image_size)

    bones = np.asarray(skeleton.bones, dtype=int)
    limb_of_point = np.asarray(skeleton.limb_id, dtype=int)
    limb_names = list(skeleton.limb_names)
    colors = [_hex_to_rgb(skeleton.limb_color(limb_names[limb_of_point[a]])) for a, _ in bones]

    footage: dict[str, Path] = {}
    for v, view in enumerate(views):
        source = view_sources[view]
        if source in footage:
            continue  # one source feeding several views is rendered once
        path = directory / source_files[source]
        with (
            atomic_path(path) as tmp,
            VideoWriter(
                # A keyframe every 10 frames, as camera recorders write them: a reader (the
                # review GUI) seeks to any frame without decoding from the start.
                tmp,
                fps=float(settings["fps"]),
                preset="ultrafast",
                crf=23,
                options={"g": "10"},
            ) as writer,
        ):
            writer.write_frames(render_frames(clean2d[v], bones, colors, image_size))
        footage[source] = path
    dlc: dict[str, Path] = {}
    for v, (view, name) in enumerate(zip(views, dlc_files)):
        keep = visible[v]
        dlc[view] = write_dlc_csv(
            directory / name,
            observed[v][:, keep],
            likelihood[v][:, keep],
            [p for p, k in zip(points, keep) if k],
            scorer=DLC_SCORER,
        )
    truth = write_truth(directory / TRUTH_FILE, pts3d, clean2d, views, points, settings)
    # The session metadata a lab puts beside its footage for the NWB export (synthetic here).
    from .config.nwb_metadata import DEMO_METADATA, SIDECAR, write_sidecar

    write_sidecar(directory / SIDECAR, DEMO_METADATA)
    log.info(
        "demo recording written to %s (%d frames, %d views)", directory, len(pts3d), len(views)
    )
    return DemoRecording(directory, footage, dlc, truth, pts3d, clean2d)


def _check_in_frame(clean2d: np.ndarray, image_size: tuple[int, int], views: list[str]) -> None:
    height, width = image_size
    x, y = clean2d[..., 0], clean2d[..., 1]
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    for v, view in enumerate(views):
        if not inside[v].all():
            raise ConfigError(
                f"cameras.{view}: the demo fly projects outside the "
                f"{width}x{height} frame; check the rig's distance/focal length"
            )


def write_truth(
    path: Path,
    pts3d: Float[np.ndarray, "T P 3"],
    clean2d: Float[np.ndarray, "V T P 2"],
    views: Sequence[str],
    points: Sequence[str],
    settings: Mapping[str, Any],
) -> Path:
    """Write the demo's ground truth atomically to ``path`` (``truth.h5``: the 3D points and their
    projections before noise; names and settings as the JSON meta)."""
    import h5py

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.create_dataset("points3d", data=pts3d)
        f.create_dataset("points2d", data=clean2d)
        f.attrs["meta"] = json.dumps(
            {"views": list(views), "point_names": list(points), "settings": settings}
        )
    return path


def load_truth(path: str | Path) -> dict[str, Any]:
    """Read ``truth.h5``: ``points3d`` ``(T, P, 3)``, ``points2d`` ``(V, T, P, 2)``, meta."""
    from .results import open_hdf5

    with open_hdf5(path, "make the demo recording again", "demo truth file") as f:
        meta = json.loads(f.attrs["meta"])
        return {"points3d": f["points3d"][()], "points2d": f["points2d"][()], **meta}


def demo_error(points3d: np.ndarray, truth3d: np.ndarray) -> dict[str, float]:
    """3D error of a reconstruction against the demo truth (world units): ``median``, ``mean``,
    ``p95`` and ``max`` of the per-point Euclidean error, ``median_aligned`` after the best
    similarity transform (bundle adjustment may move the rig's gauge), ``reconstructed``
    (fraction of finite points) and ``body_length`` (the truth's head-to-tail extent, for scale)."""
    points3d = np.asarray(points3d, float)
    truth3d = np.asarray(truth3d, float)
    if points3d.shape != truth3d.shape:
        raise ValueError(
            f"reconstruction {points3d.shape} and truth {truth3d.shape} differ in shape"
        )
    ok = np.isfinite(points3d).all(-1)
    err = np.linalg.norm(points3d - truth3d, axis=-1)[ok]
    aligned = np.linalg.norm(similarity_aligned(points3d, truth3d) - truth3d, axis=-1)[ok]
    if aligned.size == 0:
        aligned = np.array([np.nan])
    extent = np.ptp(truth3d.reshape(-1, 3), axis=0).max()
    if err.size == 0:
        err = np.array([np.nan])
    return {
        "median": float(np.median(err)),
        "mean": float(np.mean(err)),
        "p95": float(np.percentile(err, 95)),
        "max": float(np.max(err)),
        "median_aligned": float(np.median(aligned)),
        "reconstructed": float(ok.mean()),
        "body_length": float(extent),
    }
