"""Synthetic tethered fly for tests and benchmarks: 3D truth and what the rig would see.

``synthetic_fly`` makes a moving 38-point fly (the ``fly38`` skeleton order) in world
coordinates: head towards +x (the front camera ``f`` at azimuth 0), its left side
towards +y (cameras ``lf/lm/lh``), up +z, sized so the default rig (focal 22388 px,
distance 107.463, 960x480 frames) sees it filling a good part of the frame.
``observe`` projects it through a camera rig (OpenCV ``projectPoints``, independent of
flylib's own projection), adds pixel noise and gross outliers, and applies the rig's
real visibility pattern: the side cameras see their own side only, the front camera
the distal leg points of both sides and the antennae (the spec's ``output_points``).
"""

from __future__ import annotations

import cv2
import numpy as np

from flylib.config import Config
from flylib.demo import FLY38_POINTS, synthetic_fly, view_visibility  # noqa: F401  (one motion model)

from rig_constants import AZIMUTHS, DISTANCE, FOCAL, IMAGE_SIZE

POINT_NAMES = list(FLY38_POINTS)


def rig_visibility(view_names, point_names=POINT_NAMES) -> np.ndarray:
    """``(V, P)`` bool: which point each view observes in the default rig (its
    ``pose2d.output_points`` tables); a view the default config does not name sees
    every point."""
    return view_visibility(
        Config.default().data["pose2d"].get("output_points"), list(view_names), list(point_names)
    )


def project_opencv(cameras, pts3d: np.ndarray) -> np.ndarray:
    """Project ``(..., 3)`` world points through every camera with ``cv2.projectPoints``.

    Returns ``(V, ..., 2)`` pixels. Independent of flylib's JAX projection, so
    tests can use it as a reference.
    """
    pts3d = np.asarray(pts3d, float)
    flat = pts3d.reshape(-1, 3)
    out = []
    for rvec, tvec, intr, dist in zip(cameras.rvecs, cameras.tvecs, cameras.intrs, cameras.dists):
        kmat = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
        dist5 = np.zeros(max(5, dist.size)) if dist.size else np.zeros(5)
        dist5[: dist.size] = dist
        ok = np.isfinite(flat).all(axis=1)
        proj = np.full((flat.shape[0], 2), np.nan)
        if ok.any():
            img, _ = cv2.projectPoints(
                flat[ok], np.asarray(rvec, float), np.asarray(tvec, float), kmat, dist5
            )
            proj[ok] = img.reshape(-1, 2)
        out.append(proj.reshape(*pts3d.shape[:-1], 2))
    return np.stack(out)


def observe(
    pts3d: np.ndarray,
    cameras,
    noise_px: float = 1.0,
    outlier_frac: float = 0.0,
    visibility="rig",
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """What the rig's detector would report for ``pts3d`` ``(T, P, 3)``.

    Parameters
    ----------
    pts3d
        World points ``(T, P, 3)``.
    cameras
        A ``CameraGroup`` (anything with ``names``, ``rvecs``, ``tvecs``, ``intrs``,
        ``dists``).
    noise_px
        Standard deviation of the isotropic Gaussian pixel noise per coordinate.
    outlier_frac
        Fraction of visible observations replaced by a gross outlier: a uniformly
        random position in the image (image size taken as twice the principal point).
    visibility
        ``"rig"`` (the default rig's pattern, by view name), ``None`` (every view
        sees every point) or a ``(V, P)`` bool array.
    seed
        Random seed.

    Returns
    -------
    pts2d : np.ndarray
        ``(V, T, P, 2)`` pixels, NaN where the view does not see the point.
    conf : np.ndarray
        ``(V, T, P)`` confidences: inliers in [0.6, 1], outliers in [0.2, 0.7],
        0 where unseen.
    """
    rng = np.random.default_rng(seed)
    pts2d = project_opencv(cameras, pts3d)  # (V, T, P, 2)
    n_views, n_frames, n_points, _ = pts2d.shape
    if isinstance(visibility, str) and visibility == "rig":
        names = POINT_NAMES if n_points == len(POINT_NAMES) else [str(i) for i in range(n_points)]
        vis = rig_visibility(list(cameras.names), names)
    elif visibility is None:
        vis = np.ones((n_views, n_points), bool)
    else:
        vis = np.asarray(visibility, bool)
    pts2d = pts2d + rng.normal(0.0, noise_px, pts2d.shape)
    conf = rng.uniform(0.6, 1.0, pts2d.shape[:3])
    outlier = (rng.random(pts2d.shape[:3]) < outlier_frac) & vis[:, None, :]
    size = 2.0 * np.asarray(cameras.intrs)[:, 2:4]  # (V, 2) = (width, height)
    random_xy = rng.random(pts2d.shape) * size[:, None, None, :]
    pts2d = np.where(outlier[..., None], random_xy, pts2d)
    conf = np.where(outlier, rng.uniform(0.2, 0.7, conf.shape), conf)
    seen = np.broadcast_to(vis[:, None, :], conf.shape)
    pts2d = np.where(seen[..., None], pts2d, np.nan)
    conf = np.where(seen, conf, 0.0)
    return pts2d, conf


def perturb_rig(cameras, *, rot_deg: float = 3.0, dist_frac: float = 0.03, seed: int = 0):
    """A copy of ``cameras`` with each camera rotated about the world origin by up to
    ``rot_deg`` (random axis) and its distance to the origin scaled by up to ``dist_frac``,
    its own orientation otherwise following (an orbit-parameter perturbation)."""
    from flylib.camera.rig import CameraGroup

    rng = np.random.default_rng(seed)
    rvecs, tvecs = [], []
    for rvec, tvec in zip(cameras.rvecs, cameras.tvecs):
        rmat = cv2.Rodrigues(np.asarray(rvec, float))[0]
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        delta = cv2.Rodrigues(axis * np.deg2rad(rng.uniform(0.5, 1.0) * rot_deg))[0]
        scale = 1.0 + rng.choice([-1, 1]) * rng.uniform(0.5, 1.0) * dist_frac
        center = -rmat.T @ tvec
        new_center = scale * (delta @ center)
        new_rmat = rmat @ delta.T  # world -> camera after rotating the camera by delta
        rvecs.append(cv2.Rodrigues(new_rmat)[0].ravel())
        tvecs.append(-new_rmat @ new_center)
    return CameraGroup.from_arrays(
        list(cameras.names), np.array(rvecs), np.array(tvecs), cameras.intrs, cameras.dists
    )


DEFAULT_AZIMUTHS = AZIMUTHS


def default_rig(
    focal: float = FOCAL, distance: float = DISTANCE, image_size: tuple[int, int] = IMAGE_SIZE
):
    """The default 7-view orbit rig (spec ``fly38-rig.yaml``), principal point at the
    image centre, no distortion; built directly so tests need no config file."""
    from flylib.camera.rig import CameraGroup, orbit_extrinsics

    height, width = image_size
    rvecs, tvecs = zip(
        *(orbit_extrinsics((0.0, 0.0, 0.0), distance, az) for az in DEFAULT_AZIMUTHS.values())
    )
    n = len(DEFAULT_AZIMUTHS)
    intrs = np.tile([focal, focal, width / 2.0, height / 2.0], (n, 1))
    return CameraGroup.from_arrays(
        list(DEFAULT_AZIMUTHS), np.array(rvecs), np.array(tvecs), intrs, np.zeros((n, 0))
    )


def detector_errors(
    clean2d: np.ndarray,
    visible: np.ndarray,
    view_names,
    point_names,
    *,
    noise_px: float = 1.5,
    outlier_frac: float = 0.05,
    outlier_px: float = 50.0,
    swap_frac: float = 0.02,
    missing_frac: float = 0.10,
    seed: int = 0,
):
    """Detector-like 2D from exact projections ``(V, T, P, 2)``: Gaussian noise, gross
    outliers (displaced by up to ``outlier_px`` in a random direction), left/right
    swaps in the side views (the view reports the contralateral point's projection:
    the hidden leg behind the body) and missing detections.

    Returns ``(pts2d, conf, truth_kind)``: confidences are [0.6, 1] for good points,
    [0.2, 0.8] for outliers and swaps; ``truth_kind`` ``(V, T, P)`` int8 is 0 good,
    1 outlier, 2 swap, -1 not observed.
    """
    rng = np.random.default_rng(seed)
    n_views, n_frames, n_points, _ = clean2d.shape
    names = list(point_names)
    twin = np.array(
        [
            names.index(("r" + n[1:]) if n[0] == "l" else ("l" + n[1:]))
            if n[0] in "lr" and (("r" + n[1:]) if n[0] == "l" else ("l" + n[1:])) in names
            else i
            for i, n in enumerate(names)
        ]
    )
    pts = clean2d + rng.normal(0.0, noise_px, clean2d.shape)
    kind = np.zeros((n_views, n_frames, n_points), np.int8)
    seen = np.broadcast_to(np.asarray(visible, bool)[:, None, :], kind.shape)
    side = np.array([name != "f" for name in view_names])[:, None, None]
    swap = (
        seen
        & side
        & (twin != np.arange(n_points))[None, None, :]
        & (rng.random(kind.shape) < swap_frac)
    )
    swapped = clean2d[:, :, twin] + rng.normal(0.0, noise_px, clean2d.shape)
    pts = np.where(swap[..., None], swapped, pts)
    outlier = seen & ~swap & (rng.random(kind.shape) < outlier_frac)
    angle = rng.uniform(0, 2 * np.pi, kind.shape)
    radius = rng.uniform(0.0, outlier_px, kind.shape)
    shift = np.stack([np.cos(angle), np.sin(angle)], -1) * radius[..., None]
    pts = np.where(outlier[..., None], clean2d + shift, pts)
    kind[swap] = 2
    kind[outlier] = 1
    conf = rng.uniform(0.6, 1.0, kind.shape)
    conf = np.where(kind > 0, rng.uniform(0.2, 0.8, kind.shape), conf)
    present = seen & (rng.random(kind.shape) >= missing_frac)
    kind[~present] = -1
    pts = np.where(present[..., None], pts, np.nan)
    conf = np.where(present, conf, 0.0)
    return pts, conf, kind
