"""The front-blind case: real DeepFly3D poses, DeepFly3D's rig, the sample's
visibility, the default config rig as the start.

Shared by ``tests/bundle_adjustment/test_front_blind.py`` and ``benchmarks/bundle_adjustment.py
--case front-blind``. Needs ``../shared/data`` (``deepfly3d-package-example``: DeepFly3D
1.x's ``df3d_result.pkl`` with its ``points3d`` and ``calib.pkl``; ``deepfly3d-sample``:
the same recording's 2D as DeepFly3D 0.x wrote it).

- The fly: DeepFly3D's own 3D of the sample recording (15 frames, joint ``j`` is fly38
  point ``(j + 19) mod 38``), played back and forth and linearly interpolated to any
  number of frames (a tethered fly moves little).
- The true rig: DeepFly3D's calibration of that recording (focal ~16,000 px at ~117
  units); projection with OpenCV, independent of flylib's model.
- Visibility: which camera saw which point in the sample (more than half of the
  frames): the front camera nothing, each side camera its own side only, so the two
  sides share no view.
- What a detector reports: 1 px noise, 5 % gross outliers within +-80 px.
- The start: the default config's rig (orbit parameters, focal 22,388 px at 107 units,
  principal points at the image centre), off from the truth in focal length, position,
  aim and principal point, as a user who did not calibrate would run it.

The default rig and DeepFly3D's calibration explain the same images with mirror-image
worlds (near-orthographic cameras cannot tell a scene from its depth-reversed twin), so
errors are measured after the best similarity *or* mirrored similarity
(:func:`mirror_free_error`).
"""

from __future__ import annotations

import numpy as np
from conftest import SHARED_DATA

from flylib.alignment import similarity_aligned
from flylib.camera.rig import CameraGroup
from flylib.config import Config
from flylib.interop.df3d import read_df3d_calibration, read_df3d_points2d
from flylib.interop.safe_pickle import load_restricted
from flylib.pipeline.planning import config_rig

from rig_constants import IMAGE_SIZE, VIEWS
from rough_rig import RoughCase, detections, median_bone

PACKAGE_EXAMPLE = SHARED_DATA / "deepfly3d-package-example"
SAMPLE_2D = SHARED_DATA / "deepfly3d-sample" / "df3d_result_2d.pkl"


def available() -> bool:
    """Whether the DeepFly3D files this case is built from are present."""
    return (PACKAGE_EXAMPLE / "df3d_result.pkl").is_file() and SAMPLE_2D.is_file()


def _fly38(joints: np.ndarray) -> np.ndarray:
    """``(..., J, k)`` with DeepFly3D's joint axis ``J`` reordered to fly38 points."""
    out = np.empty_like(joints)
    out[..., (np.arange(38) + 19) % 38, :] = joints
    return out


def recorded_poses() -> np.ndarray:
    """``(15, 38, 3)``: DeepFly3D's own 3D of the sample recording, fly38 order."""
    data = load_restricted(PACKAGE_EXAMPLE / "df3d_result.pkl", "DeepFly3D result")
    return _fly38(np.asarray(data["points3d"], float))


def deepfly3d_poses(n_frames: int) -> np.ndarray:
    """``(n_frames, 38, 3)``: DeepFly3D's 3D of the sample, back and forth, interpolated
    at 0.1 recorded frames per frame."""
    poses = recorded_poses()
    n = len(poses)
    phase = (0.1 * np.arange(n_frames)) % (2 * (n - 1))
    phase = np.where(phase > n - 1, 2 * (n - 1) - phase, phase)
    lo = np.minimum(np.floor(phase).astype(int), n - 2)
    frac = (phase - lo)[:, None, None]
    return (1 - frac) * poses[lo] + frac * poses[lo + 1]


def deepfly3d_rig() -> CameraGroup:
    """DeepFly3D's calibration of the sample recording, cameras named as the default rig."""
    calib = read_df3d_calibration(PACKAGE_EXAMPLE / "calib.pkl")
    cams = [calib[k] for k in sorted(calib)][: len(VIEWS)]
    intrs = [[c["kmat"][0, 0], c["kmat"][1, 1], c["kmat"][0, 2], c["kmat"][1, 2]] for c in cams]
    return CameraGroup.from_arrays(
        list(VIEWS),
        np.array([c["rvec"] for c in cams]),
        np.array([c["tvec"] for c in cams]),
        np.array(intrs),
        np.array([c["dist"] for c in cams]),
    )


def sample_visibility() -> np.ndarray:
    """``(V, 38)``: which camera saw which fly38 point in more than half the frames."""
    points = read_df3d_points2d(SAMPLE_2D, [IMAGE_SIZE] * len(VIEWS))
    seen = np.isfinite(points.xy).all(-1).mean(axis=1) > 0.5  # (V, J)
    return _fly38(seen[..., None])[..., 0]


def package_visibility() -> np.ndarray:
    """``(V, 38)``: which camera DeepFly3D's package example holds 2D for (its
    ``points2d`` not zero in more than half the frames): each side camera its own side,
    the front camera both sides."""
    data = load_restricted(PACKAGE_EXAMPLE / "df3d_result.pkl", "DeepFly3D result")
    points = np.asarray(data["points2d"], float)[: len(VIEWS)]  # (V, T, J, 2)
    seen = (np.abs(points).sum(-1) > 0).mean(axis=1) > 0.5  # (V, J)
    return _fly38(seen[..., None])[..., 0]


def package_points2d() -> np.ndarray:
    """``(7, 15, 38, 2)``: DeepFly3D's 2D of its package example, raw pixels, fly38 order."""
    data = read_df3d_points2d(PACKAGE_EXAMPLE / "df3d_result.pkl", [IMAGE_SIZE] * len(VIEWS))
    return _fly38(np.asarray(data.xy, float)[: len(VIEWS)])


def default_start() -> CameraGroup:
    """The default config's rig for 960x480 footage."""
    return config_rig(Config.default(), image_sizes={v: IMAGE_SIZE for v in VIEWS})


def make_case(
    n_frames: int = 1000,
    *,
    seed: int = 0,
    noise_px: float = 1.0,
    outlier_frac: float = 0.05,
    outlier_px: float = 80.0,
) -> RoughCase:
    """Generate the front-blind case (module docstring)."""
    rng = np.random.default_rng(seed)
    truth = deepfly3d_poses(n_frames)
    rig = deepfly3d_rig()
    vis = sample_visibility()
    pts2d, conf, outlier = detections(rig, truth, vis, rng, noise_px, outlier_frac, outlier_px)
    return RoughCase(
        truth=truth,
        rig=rig,
        start=default_start(),
        pts2d=pts2d,
        conf=conf,
        outlier=outlier,
        bone=median_bone(truth),
    )


def mirror_free_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``(T, P)`` distances after the similarity alignment of ``estimate`` or of its
    mirror image onto ``truth``, whichever fits better (median); NaN where missing."""
    best = None
    for flip in (1.0, -1.0):
        moved = similarity_aligned(estimate * [flip, 1.0, 1.0], truth)
        err = np.linalg.norm(moved - truth, axis=-1)
        if best is None or np.nanmedian(err) < np.nanmedian(best):
            best = err
    return best


def held_out_error(cameras: CameraGroup, pts2d: np.ndarray) -> np.ndarray:
    """``(V, T, P)`` leave-one-camera-out reprojection error in pixels over every frame:
    :func:`flylib.accuracy.held_out_errors` with the DLT, so two rigs are judged on the
    same observations (compare medians: gross outliers stay in)."""
    from flylib.accuracy import held_out_errors
    from flylib.config.params import TriangulationParams
    from flylib.pipeline.triangulation import triangulation_method

    method = triangulation_method(TriangulationParams(method="dlt"), cameras)
    return held_out_errors(cameras, pts2d, method, windows=[(0, pts2d.shape[1])])["triangulation"]
