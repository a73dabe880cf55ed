"""flylib.interop's names and their modules: ``__init__.py`` reads this file
(``lazy_loader.attach_stub``) and loads each module on first use of one of its names."""

from .anipose import (
    calibration_from_index as calibration_from_index,
    calibration_image_sizes as calibration_image_sizes,
    calibration_inputs as calibration_inputs,
    load_calibration as load_calibration,
    read_anipose_toml as read_anipose_toml,
    write_anipose_toml as write_anipose_toml,
)
from .df3d import (
    FLY38_POINT_NAMES as FLY38_POINT_NAMES,
    df3d_joint_to_fly38 as df3d_joint_to_fly38,
    read_df3d_calibration as read_df3d_calibration,
    read_df3d_points2d as read_df3d_points2d,
)
from .dlc import (
    ViewKeypoints as ViewKeypoints,
    dlc_frame as dlc_frame,
    read_dlc_csv as read_dlc_csv,
    read_dlc_h5 as read_dlc_h5,
    write_dlc_csv as write_dlc_csv,
)
from .exports import (
    export_result as export_result,
    points3d_table as points3d_table,
    write_dlc_views as write_dlc_views,
    write_points3d_csv as write_points3d_csv,
)
from .importer import (
    FORMATS as FORMATS,
    ImportTarget as ImportTarget,
    import_points2d as import_points2d,
    import_spec as import_spec,
)
from .sleap import read_sleap_analysis as read_sleap_analysis
