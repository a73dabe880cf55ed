"""Type stub of flylib's top level: every public name and the module it comes from.

``flylib/__init__.py`` reads this file (``lazy_loader.attach_stub``) and loads each
module on first use, so ``import flylib`` stays cheap while type checkers and IDEs see
the real definitions. A new public name goes here, in its module's import.
"""

from .accuracy import (
    accuracy_summary as accuracy_summary,
    bone_length_spread as bone_length_spread,
    held_out_errors as held_out_errors,
    keep_triangulation as keep_triangulation,
    left_right_asymmetry as left_right_asymmetry,
)
from .bundle_adjustment import (
    bundle_adjust as bundle_adjust,
    bundle_adjust_sequence as bundle_adjust_sequence,
    select_frames as select_frames,
)
from .camera.jax_model import (
    backproject_ray_one as backproject_ray_one,
    closest_point_on_ray as closest_point_on_ray,
    distort as distort,
    distort_one as distort_one,
    intr_to_kmat as intr_to_kmat,
    project_full as project_full,
    project_full_one as project_full_one,
    project_pmat as project_pmat,
    rmat_to_rvec as rmat_to_rvec,
    rmat_to_rvec_one as rmat_to_rvec_one,
    rvec_to_rmat as rvec_to_rmat,
    rvec_to_rmat_one as rvec_to_rmat_one,
    triangulate_dlt as triangulate_dlt,
    undistort_one as undistort_one,
)
from .camera.rig import (
    Camera as Camera,
    CameraGroup as CameraGroup,
    orbit_extrinsics as orbit_extrinsics,
    resolve_extrinsics as resolve_extrinsics,
)
from .config import (
    PARAM_STAGES as PARAM_STAGES,
    STAGE_DEFAULTS as STAGE_DEFAULTS,
    STAGES as STAGES,
    BundleAdjustmentParams as BundleAdjustmentParams,
    Config as Config,
    IoParams as IoParams,
    PictorialParams as PictorialParams,
    Pose2dParams as Pose2dParams,
    TriangulationParams as TriangulationParams,
)
from .demo import synthetic_fly as synthetic_fly
from .errors import (
    ConfigError as ConfigError,
    FlylibError as FlylibError,
    FootageError as FootageError,
    ImportFormatError as ImportFormatError,
    ResultsError as ResultsError,
    StageError as StageError,
    WeightsError as WeightsError,
)
from .interop import (
    export_result as export_result,
    import_points2d as import_points2d,
    load_calibration as load_calibration,
    read_anipose_toml as read_anipose_toml,
    read_dlc_csv as read_dlc_csv,
    read_sleap_analysis as read_sleap_analysis,
    write_anipose_toml as write_anipose_toml,
    write_dlc_csv as write_dlc_csv,
    write_points3d_csv as write_points3d_csv,
)
from .interop.nwb import export_nwb as export_nwb, write_nwb as write_nwb
from .interop.training_data import export_training_data as export_training_data
from .io import (
    FrameReader as FrameReader,
    ImageSequenceReader as ImageSequenceReader,
    VideoReader as VideoReader,
    VideoWriter as VideoWriter,
    is_video_file as is_video_file,
    list_image_files as list_image_files,
    open_reader as open_reader,
)
from .neuromechfly import (
    NmfAngles as NmfAngles,
    compute_nmf_angles as compute_nmf_angles,
)
from .paths import atomic_path as atomic_path
from .pictorial import (
    Candidates as Candidates,
    bone_length_targets as bone_length_targets,
    peak_candidates as peak_candidates,
    skeleton_chains as skeleton_chains,
    solve_frame as solve_frame,
    solve_frames as solve_frames,
)
from .pipeline import run_from_points2d as run_from_points2d
from .pipeline.demo import make_demo as make_demo
from .pipeline.planning import plan_recordings as plan_recordings
from .pipeline.pose2d import import_target as import_target
from .pose2d import (
    DetectionPlan as DetectionPlan,
    HourglassNet as HourglassNet,
    detect_2d as detect_2d,
    detect_recording as detect_recording,
    load_detector as load_detector,
)
from .recordings import (
    Recording as Recording,
    find_recording as find_recording,
    plan_listing as plan_listing,
    resolve_recordings as resolve_recordings,
)
from .results import (
    FORMAT_VERSION as FORMAT_VERSION,
    Pose2dData as Pose2dData,
    PoseResult as PoseResult,
    assemble_results as assemble_results,
    read_stage as read_stage,
    write_stage as write_stage,
)
from .skeleton import Skeleton as Skeleton
from .triangulation import (
    reconstruct as reconstruct,
    reprojection_error as reprojection_error,
    triangulate as triangulate,
    triangulate_ransac as triangulate_ransac,
)
from .visualization import (
    read_video_specs as read_video_specs,
    render_videos as render_videos,
    summary_figure as summary_figure,
)

__version__: str
__all__: list[str]
