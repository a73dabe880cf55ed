"""Interoperability with other pose tools.

- 2D import as the pose2d stage output: DeepFly3D result pickles, DeepLabCut /
  Lightning Pose CSV and HDF5, SLEAP analysis HDF5 (:func:`import_points2d`).
- Calibrations: Anipose TOML read/write, DeepFly3D calibration pickles, the
  ``calibrations.csv`` session index (:func:`load_calibration`).
- Exports: Anipose's pose-3d CSV and per-view DeepLabCut CSVs (:func:`export_result`);
  NWB with ndx-pose in :mod:`flylib.interop.nwb` (imported on demand: it loads pynwb).
"""

from __future__ import annotations

from .anipose import (
    calibration_from_index,
    calibration_image_sizes,
    calibration_inputs,
    load_calibration,
    read_anipose_toml,
    write_anipose_toml,
)
from .df3d import (
    FLY38_POINT_NAMES,
    df3d_joint_to_fly38,
    read_df3d_calibration,
    read_df3d_points2d,
)
from .dlc import ViewKeypoints, dlc_frame, read_dlc_csv, read_dlc_h5, write_dlc_csv
from .exports import export_result, points3d_table, write_dlc_views, write_points3d_csv
from .importer import FORMATS, ImportTarget, import_points2d, import_spec
from .sleap import read_sleap_analysis

__all__ = [
    "FLY38_POINT_NAMES",
    "FORMATS",
    "ImportTarget",
    "ViewKeypoints",
    "calibration_from_index",
    "calibration_image_sizes",
    "calibration_inputs",
    "df3d_joint_to_fly38",
    "dlc_frame",
    "export_result",
    "import_points2d",
    "import_spec",
    "load_calibration",
    "points3d_table",
    "read_anipose_toml",
    "read_df3d_calibration",
    "read_df3d_points2d",
    "read_dlc_csv",
    "read_dlc_h5",
    "read_sleap_analysis",
    "write_anipose_toml",
    "write_dlc_csv",
    "write_dlc_views",
    "write_points3d_csv",
]
