"""Export a recording's result as Neurodata Without Borders (NWB) with ndx-pose (0.4) layout for
multi-camera 3D pose, built with ``pynwb`` and ``ndx-pose`` (never by hand):

``/general``
    session metadata (:mod:`flylib.config.nwb_metadata`); ``was_generated_by`` = flylib and its
    version; ``data_collection`` = the recording's path and the config snapshot.
``/general/devices/camera_<view>``
    ``ndx_pose.CalibratedCamera`` with the final rig: ``K``, world-to-camera ``R``, ``t``
    (``x_cam = R x_world + t``), OpenCV distortion; its description holds flylib's camera as JSON.
``/acquisition/video_<view>``
    the footage as an external ``ImageSeries`` (paths relative to the NWB file, never copied).
``/processing/behavior``
    ``Skeletons``; ``MultiCameraPoseEstimation``: one ``PoseEstimationSeries`` per point (3D
    ``(T, 3)`` in the world frame) and one ``PoseEstimation_<view>`` per view (2D ``(T, 2)`` pixels
    and confidence); ``ReprojectionError_<view>`` ``(T, P)`` pixels.

Missing values stay NaN. Frame ``i`` is at ``i / frame_rate`` s after ``session_start_time``
(``nwb.frame_rate``, else the footage's). 3D confidence, in [0, 1]: :data:`CONFIDENCE_DEFINITION`;
two views score at most 0.5: two rays always meet near a point; nothing cross-checks."""

from __future__ import annotations

import json
import logging
import os
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import __version__
from ..config.nwb_metadata import parse_datetime
from ..errors import ConfigError, ResultsError
from ..paths import atomic_path

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

log = logging.getLogger(__name__)

#: Reprojection error (pixels) that divides the 3D confidence by e.
CONFIDENCE_ERROR_SCALE_PX = 5.0
#: Views beyond the first two needed for full 3D confidence (see the module docstring).
CONFIDENCE_FULL_VIEWS = 3
#: Name of the multi-camera container in ``processing/behavior``.
MULTICAMERA_NAME = "MultiCameraPoseEstimation"
#: The BehavioralTimeSeries holding NeuroMechFly's joint angles (when the stage ran).
JOINT_ANGLES_NAME = "NeuroMechFlyJointAngles"
# Arrays with at least this many elements are written gzip-compressed.
_COMPRESS_MIN_ELEMENTS = 4096

CONFIDENCE_DEFINITION = (
    f"exp(-e / {CONFIDENCE_ERROR_SCALE_PX:g} px) * min(1, (n - 1) / {CONFIDENCE_FULL_VIEWS - 1}): "
    "n = number of views the point was triangulated from (views with a finite reprojection error), "
    "e = mean reprojection error over them in pixels; NaN where the point was not reconstructed"
)


def confidence_3d(
    reproj_error: Float[np.ndarray, "V T P"], pts3d: Float[np.ndarray, "T P 3"]
) -> Float[np.ndarray, "T P"]:
    """The 3D confidence ``(T, P)`` in [0, 1] (:data:`CONFIDENCE_DEFINITION`) from reprojection
    errors in pixels (NaN: view not used); NaN where ``pts3d`` is not reconstructed."""
    err = np.asarray(reproj_error, dtype=np.float64)
    used = np.isfinite(err)
    n = used.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_err = np.where(n > 0, np.where(used, err, 0.0).sum(0) / np.maximum(n, 1), np.inf)
    support = np.clip((n - 1) / (CONFIDENCE_FULL_VIEWS - 1), 0.0, 1.0)
    conf = np.exp(-mean_err / CONFIDENCE_ERROR_SCALE_PX) * support
    return np.where(np.isfinite(np.asarray(pts3d, dtype=np.float64)).all(-1), conf, np.nan)


def footage_frame_rate(footage: Mapping[str, Sequence[Path]]) -> float | None:
    """The frame rate in the footage's video headers (the first view that has one; image sequences
    carry none); views whose videos disagree are logged."""
    from ..io import VIDEO_EXTS, open_reader

    rates: dict[str, float] = {}
    for view, files in footage.items():
        if len(files) == 1 and Path(files[0]).suffix.lower() in VIDEO_EXTS:
            fps = open_reader(Path(files[0])).fps()
            if fps:
                rates[view] = float(fps)
    if not rates:
        return None
    if len({round(r, 6) for r in rates.values()}) > 1:
        log.warning(
            "the views' videos report different frame rates %s; using %s's",
            rates,
            next(iter(rates)),
        )
    return next(iter(rates.values()))


def _data(array: np.ndarray):
    from hdmf.backends.hdf5.h5_utils import H5DataIO

    array = np.ascontiguousarray(array)
    if array.size >= _COMPRESS_MIN_ELEMENTS:
        return H5DataIO(array, compression="gzip", compression_opts=4)
    return array


def _camera_description(camera, view: str, image_size) -> str:
    return json.dumps(
        {
            "about": "flylib camera model (OpenCV): x_cam = R(rvec) x_world + tvec; pixel = K distort(x_cam / z); "
            "distortion in OpenCV order (k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4)",
            "view": view,
            "rvec": [float(x) for x in camera.rvec],
            "tvec": [float(x) for x in camera.tvec],
            "intrinsics_fx_fy_cx_cy": [float(x) for x in camera.intr],
            "distortion": [float(x) for x in camera.dist],
            "image_size_hw": None
            if image_size is None
            else [int(image_size[0]), int(image_size[1])],
        }
    )


def _relative(path: Path, start: Path) -> str:
    try:
        return Path(os.path.relpath(Path(path).resolve(), start.resolve())).as_posix()
    except ValueError:  # another drive (Windows): NWB then needs the absolute path
        return Path(path).resolve().as_posix()


def _nwbfile_kwargs(
    metadata: Mapping, *, recording: str | None, config_text: str | None, result
) -> dict[str, Any]:
    def as_list(value):
        return [value] if isinstance(value, str) else list(value)

    n_views, n_frames, n_points = result.n_views, result.n_frames, result.n_points
    description = metadata.get("session_description") or (
        f"Markerless pose of a tethered fly: {n_points} keypoints over {n_frames} frames from "
        f"{n_views} synchronized cameras, estimated with flylib {__version__}"
    )
    stages = ", ".join(result.meta.get("stages") or []) or "unknown"
    collection = [f"Keypoints estimated with flylib {__version__} (stages: {stages})."]
    if recording:
        collection.append(f"Recording (footage): {recording}")
    if config_text:
        collection.append(
            "flylib configuration that produced these results (YAML):\n" + config_text
        )
    kwargs: dict[str, Any] = {
        "session_description": description,
        "identifier": metadata.get("identifier") or str(uuid.uuid4()),
        "session_start_time": parse_datetime(
            metadata["session_start_time"], "nwb.session_start_time"
        ),
        "experimenter": as_list(metadata["experimenter"]),
        "session_id": metadata.get("session_id") or (Path(recording).name if recording else None),
        "keywords": as_list(
            metadata.get("keywords")
            or ["pose estimation", "Drosophila melanogaster", "multi-camera", "flylib"]
        ),
        "was_generated_by": [["flylib", __version__]],
        "data_collection": "\n".join(collection),
    }
    for key in ("institution", "lab", "experiment_description", "protocol", "notes"):
        if metadata.get(key):
            kwargs[key] = str(metadata[key])
    if metadata.get("related_publications"):
        kwargs["related_publications"] = as_list(metadata["related_publications"])
    return kwargs


def _subject(metadata: Mapping):
    from pynwb.file import Subject

    fields = dict(metadata.get("subject") or {})
    if fields.get("date_of_birth") is not None:
        fields["date_of_birth"] = parse_datetime(
            fields["date_of_birth"], "nwb.subject.date_of_birth"
        )
    return Subject(**{k: v for k, v in fields.items() if v is not None})


def write_nwb(
    result,
    path: str | Path,
    metadata: Mapping[str, Any],
    *,
    footage: Mapping[str, Sequence[Path]] | None = None,
    frame_rate: float | None = None,
    recording: str | Path | None = None,
    config_text: str | None = None,
    joint_angles: tuple[np.ndarray, Sequence[str]] | None = None,
) -> Path:
    """Write one recording's :class:`~flylib.results.PoseResult` as an NWB file (atomically).

    ``metadata``: :func:`flylib.config.nwb_metadata.recording_metadata`; ``footage``: ``view ->
    files``; ``frame_rate`` defaults to ``metadata["frame_rate"]``, else the footage's;
    ``joint_angles``: ``(angles (T, J) radians, joint names)``, one ``TimeSeries`` per joint.
    :class:`ConfigError` without a frame rate, :class:`ResultsError` without 3D points."""
    from pynwb import NWBHDF5IO, NWBFile

    path = Path(path)
    if result.pts3d is None:
        raise ResultsError(
            "the result has no 3D points (no triangulation or pictorial_structures group); "
            "enable a 3D stage and re-run before exporting NWB"
        )
    footage = {v: [Path(f) for f in files] for v, files in (footage or {}).items() if files}
    rate = frame_rate or metadata.get("frame_rate") or footage_frame_rate(footage)
    if not rate:
        raise ConfigError(
            f"nwb.frame_rate: no frame rate for {recording or path}: the footage "
            f"{'is image sequences' if footage else 'was not found'}; set nwb.frame_rate (frames per second) "
            "in the config or the recording's nwb.yaml"
        )
    rate = float(rate)
    names = list(result.skeleton.point_names)
    views = list(result.cameras.names)
    recording_text = None if recording is None else str(Path(recording).resolve())
    nwbfile = NWBFile(
        **_nwbfile_kwargs(
            metadata, recording=recording_text, config_text=config_text, result=result
        )
    )
    nwbfile.subject = _subject(metadata)
    cameras = _add_cameras(nwbfile, result, views)
    videos = _add_videos(nwbfile, result, views, footage, cameras, rate, path.parent)

    behavior = nwbfile.create_processing_module(
        name="behavior",
        description=f"keypoints of the fly estimated by flylib from {len(views)} cameras",
    )
    skeleton = _add_skeleton(behavior, result, names, nwbfile.subject)
    per_view = _pose_estimations_2d(result, views, names, skeleton, cameras, videos, rate)
    _add_pose_3d(behavior, result, metadata, views, names, skeleton, per_view, rate)
    if result.reproj_error is not None:
        _add_reprojection_errors(behavior, result.reproj_error, views, names, rate)
    if joint_angles is not None:
        _add_joint_angles(behavior, joint_angles, rate)

    with atomic_path(path) as tmp, NWBHDF5IO(str(tmp), mode="w") as io:
        io.write(nwbfile)
    return path


def _add_cameras(nwbfile, result, views: list[str]) -> dict:
    """One ``CalibratedCamera`` device per view with the final rig: ``view -> device``."""
    import ndx_pose

    from ..camera.model import intr_to_kmat_numpy, rvec_to_rmat_numpy

    cameras = {}
    for camera, view in zip(result.cameras, views):
        size = (result.image_sizes or {}).get(view)
        device = ndx_pose.CalibratedCamera(
            name=f"camera_{view}",
            description=_camera_description(camera, view, size),
            intrinsic_matrix=intr_to_kmat_numpy(camera.intr),
            rotation_matrix=rvec_to_rmat_numpy(camera.rvec),
            translation_vector=np.asarray(camera.tvec, dtype=np.float64),
            distortion_coefficients=np.asarray(camera.dist, dtype=np.float64).reshape(-1),
        )
        nwbfile.add_device(device)
        cameras[view] = device
    return cameras


def _add_videos(nwbfile, result, views, footage, cameras, rate: float, start: Path) -> dict:
    """Each view's footage as external ``ImageSeries`` (paths relative to ``start``), by view."""
    from pynwb.image import ImageSeries

    videos = {}
    for view in views:
        files = footage.get(view)
        if not files:
            continue
        size = (result.image_sizes or {}).get(view)
        videos[view] = ImageSeries(
            name=f"video_{view}",
            description=f"raw footage of camera {view} (external file{'s' if len(files) > 1 else ''}, not copied)",
            external_file=[_relative(f, start) for f in files],
            starting_frame=[0] if len(files) == 1 else list(range(len(files))),
            format="external",
            num_samples=int(result.n_frames),
            rate=rate,
            starting_time=0.0,
            unit="n.a.",
            dimension=None if size is None else [int(size[1]), int(size[0])],
            device=cameras[view],
        )
        nwbfile.add_acquisition(videos[view])
    return videos


def _add_skeleton(behavior, result, names: list[str], subject):
    """The ``ndx_pose.Skeleton`` (point names, bones as edges), added to ``behavior``."""
    import ndx_pose

    n_points = len(names)
    skeleton = ndx_pose.Skeleton(
        name=str(result.skeleton.name or "skeleton"),
        nodes=names,
        edges=np.asarray(
            result.skeleton.bones, dtype=np.uint8 if n_points < 256 else np.uint32
        ).reshape(-1, 2),
        subject=subject,
    )
    behavior.add(ndx_pose.Skeletons(skeletons=[skeleton]))
    return skeleton


def _pose_estimations_2d(result, views, names, skeleton, cameras, videos, rate: float) -> list:
    """One ``PoseEstimation`` per view: its 2D keypoints with the detection confidence."""
    import ndx_pose

    per_view = []
    for v, view in enumerate(views):
        series = [
            ndx_pose.PoseEstimationSeries(
                name=name,
                description=f"2D position of {name} in camera {view}; NaN = not detected",
                data=_data(result.pts2d[v, :, p]),
                unit="pixels",
                reference_frame=(
                    f"OpenCV image coordinates of camera {view}'s raw frame: x to the right, "
                    "y down, (0, 0) at the centre of the top-left pixel"
                ),
                confidence=None if result.conf is None else _data(result.conf[v, :, p]),
                confidence_definition=None
                if result.conf is None
                else "the 2D detector's (or the imported tool's) confidence in this detection",
                starting_time=0.0,
                rate=rate,
            )
            for p, name in enumerate(names)
        ]
        per_view.append(
            ndx_pose.PoseEstimation(
                name=f"PoseEstimation_{view}",
                description=f"2D keypoints of camera {view}, the ones the 3D rests on (NaN where a view's "
                "detection was missing or rejected as an outlier)",
                pose_estimation_series=series,
                skeleton=skeleton,
                device=cameras[view],
                source_video=videos.get(view),
                scorer="flylib",
                source_software="flylib",
                source_software_version=__version__,
            )
        )
    return per_view


def _add_pose_3d(behavior, result, metadata, views, names, skeleton, per_view, rate) -> None:
    """The ``MultiCameraPoseEstimation``: each point's 3D and confidence, the views' 2D."""
    import ndx_pose

    confidence = (
        None if result.reproj_error is None else confidence_3d(result.reproj_error, result.pts3d)
    )
    world_unit = str(metadata.get("world_unit") or "n.a.")
    series_3d = [
        ndx_pose.PoseEstimationSeries(
            name=name,
            description=f"3D position of {name}; NaN = not reconstructed",
            data=_data(result.pts3d[:, p]),
            unit=world_unit,
            reference_frame=(
                "the world frame of the camera calibration (the CalibratedCamera devices map it to each "
                "camera as x_cam = R x_world + t); for flylib's orbit rig the origin is the point the "
                "cameras look at; units are the calibration's"
            ),
            confidence=None if confidence is None else _data(confidence[:, p]),
            confidence_definition=None if confidence is None else CONFIDENCE_DEFINITION,
            starting_time=0.0,
            rate=rate,
        )
        for p, name in enumerate(names)
    ]
    behavior.add(
        ndx_pose.MultiCameraPoseEstimation(
            name=MULTICAMERA_NAME,
            description=(
                f"3D keypoints triangulated by flylib from {len(views)} calibrated cameras "
                f"({', '.join(views)}), with each camera's 2D keypoints"
            ),
            pose_estimation_series=series_3d,
            pose_estimations=per_view,
            skeleton=skeleton,
            scorer="flylib",
            source_software="flylib",
            source_software_version=__version__,
        )
    )


def _add_reprojection_errors(behavior, reproj_error, views, names, rate: float) -> None:
    """One ``ReprojectionError_<view>`` time series ``(T, P)`` per view."""
    from pynwb import TimeSeries

    for v, view in enumerate(views):
        behavior.add(
            TimeSeries(
                name=f"ReprojectionError_{view}",
                description=(
                    f"distance in pixels between camera {view}'s 2D keypoint and the 3D point's "
                    f"projection; columns are the skeleton points in order ({', '.join(names)}); "
                    "NaN where the view was not used"
                ),
                data=_data(reproj_error[v]),
                unit="pixels",
                starting_time=0.0,
                rate=rate,
            )
        )


def _add_joint_angles(behavior, joint_angles, rate: float) -> None:
    """NeuroMechFly's ``(angles (T, J), joint names)`` as one ``TimeSeries`` per joint."""
    from pynwb import TimeSeries
    from pynwb.behavior import BehavioralTimeSeries

    values, joints = joint_angles
    behavior.add(
        BehavioralTimeSeries(
            name=JOINT_ANGLES_NAME,
            time_series=[
                TimeSeries(
                    name=joint,
                    description=(
                        f"NeuroMechFly (flygym) joint {joint}: inverse kinematics of the 3D on the "
                        "model's leg chains; NaN where the leg was not solved"
                    ),
                    data=_data(values[:, j]),
                    unit="radians",
                    starting_time=0.0,
                    rate=rate,
                )
                for j, joint in enumerate(joints)
            ],
        )
    )


def read_joint_angles(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """``(angles (T, 42) radians, joint names)`` from a ``neuromechfly.h5``."""
    from ..results import open_hdf5

    with open_hdf5(path, "re-run the neuromechfly stage", "NeuroMechFly angles file") as f:
        group = f["neuromechfly"]
        return np.asarray(group["angles"], dtype=np.float64), json.loads(group.attrs["dof_names"])


def export_nwb(
    results_path: str | Path,
    out_path: str | Path,
    metadata: Mapping[str, Any],
    *,
    footage: Mapping[str, Sequence[Path]] | None = None,
    recording_dir: str | Path | None = None,
    config_text: str | None = None,
    angles_path: str | Path | None = None,
) -> Path:
    """Export a run's ``results.h5`` as NWB (arguments as for :func:`write_nwb`); ``recording_dir
    =None`` links no video, ``angles_path`` (``neuromechfly.h5``) adds joint angles."""
    from ..results import PoseResult

    result = PoseResult.load(results_path)
    footage = footage or {}
    missing = [v for v in result.cameras.names if not footage.get(v)]
    if recording_dir is not None and missing:
        log.warning(
            "%s: no footage found for view(s) %s; the NWB file links no video for them",
            recording_dir,
            ", ".join(missing),
        )
    return write_nwb(
        result,
        out_path,
        metadata,
        footage=footage,
        recording=recording_dir,
        config_text=config_text,
        joint_angles=None if angles_path is None else read_joint_angles(angles_path),
    )
