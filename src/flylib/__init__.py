"""flylib: markerless 3D pose estimation of tethered Drosophila from a multi-camera rig.

Every public name is importable from the top level (``from flylib import CameraGroup``).
Submodules load lazily, so ``import flylib`` does not pull in JAX or PyTorch until a
name that needs them is used.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# public name -> submodule that defines it
_EXPORTS: dict[str, str] = {
    # errors
    "FlylibError": "errors",
    "ConfigError": "errors",
    "FootageError": "errors",
    "WeightsError": "errors",
    "ResultsError": "errors",
    "ImportFormatError": "errors",
    # config
    "Config": "config",
    "STAGES": "config",
    "STAGE_DEFAULTS": "config",
    "PARAM_STAGES": "config",
    "Pose2dParams": "config",
    "BundleAdjustmentParams": "config",
    "TriangulationParams": "config",
    "PictorialParams": "config",
    "IoParams": "config",
    "FORMAT_VERSION": "results",
    "Pose2dData": "results",
    "write_stage": "results",
    "read_stage": "results",
    "assemble_results": "results",
    "atomic_path": "paths",
    # cameras / skeleton / results
    "Camera": "cameras",
    "CameraGroup": "cameras",
    "orbit_extrinsics": "cameras",
    "resolve_extrinsics": "cameras",
    "Skeleton": "skeleton",
    "PoseResult": "results",
    # recordings
    "Recording": "recordings",
    "resolve_recordings": "recordings",
    "find_recording": "recordings",
    "plan_recordings": "recordings",
    "make_demo": "demo",
    "synthetic_fly": "demo",
    # geometry
    "rvec_to_rmat": "geometry",
    "rmat_to_rvec": "geometry",
    "rvec_to_rmat_one": "geometry",
    "rmat_to_rvec_one": "geometry",
    "distort": "geometry",
    "distort_one": "geometry",
    "undistort_one": "geometry",
    "project_full": "geometry",
    "project_full_one": "geometry",
    "project_pmat": "geometry",
    "intr_to_kmat": "geometry",
    "triangulate_dlt": "geometry",
    "backproject_ray_one": "geometry",
    "closest_point_on_ray": "geometry",
    # triangulation
    "triangulate": "triangulation",
    "reprojection_error": "triangulation",
    "triangulate_ransac": "triangulation",
    "triangulate_greedy": "triangulation",
    "reconstruct_dlt": "triangulation",
    "reconstruct_ransac": "triangulation",
    "reconstruct_greedy": "triangulation",
    # reconstruction stages
    "bundle_adjust": "bundle_adjustment",
    "bundle_adjust_from_config": "bundle_adjustment",
    "Candidates": "pictorial",
    "peak_candidates": "pictorial",
    "bone_length_targets": "pictorial",
    "skeleton_chains": "pictorial",
    "solve_frame": "pictorial",
    "run_from_points2d": "pipeline",
    "bundle_adjust_sequence": "bundle_adjustment",
    "select_frames": "bundle_adjustment",
    "solve_frames": "pictorial",
    # detector (torch is imported only when these are used)
    "load_detector": "pose2d",
    "detect_2d": "pose2d",
    "detect_recording": "pose2d",
    "HourglassNet": "pose2d",
    "DetectionPlan": "pose2d",
    "is_video_file": "io",
    "list_image_files": "io",
    # frame I/O
    "open_reader": "io",
    "FrameReader": "io",
    "VideoReader": "io",
    "ImageSequenceReader": "io",
    "VideoWriter": "io",
    # visualization
    "render_videos": "visualization",
    "summary_figure": "visualization",
    "read_video_specs": "visualization",
    # interoperability: 2D import, calibration files, exports
    "import_points2d": "interop",
    "load_calibration": "interop",
    "read_anipose_toml": "interop",
    "write_anipose_toml": "interop",
    "export_result": "interop",
    "write_points3d_csv": "interop",
    "read_dlc_csv": "interop",
    "write_dlc_csv": "interop",
    "read_sleap_analysis": "interop",
    "write_nwb": "interop.nwb",
    "export_nwb": "interop.nwb",
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'flylib' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"flylib.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:  # pragma: no cover - for static analysers only
    from .cameras import Camera, CameraGroup  # noqa: F401
    from .config import Config  # noqa: F401
    from .results import PoseResult  # noqa: F401
    from .skeleton import Skeleton  # noqa: F401
