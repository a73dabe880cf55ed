"""The realistic bundle-adjustment case: a tethered fly, a rough starting rig.

Shared by ``tests/bundle_adjustment/test_rough_rig.py`` and
``benchmarks/bundle_adjustment.py --case rough``.

- The fly: thorax fixed (tethered), six legs of four bones of constant length, joint
  angles wandering smoothly so that joints move a few percent of a bone per frame;
  antennae and abdomen almost still. About 3 units long (fly38 point order).
- The rig: like DeepFly3D's real one, seven cameras on an orbit (azimuths -120..120,
  small elevations and rolls, ``look_at`` jittered) at about 116 units, focal about
  16,000 px, principal points away from the image centre, five distortion
  coefficients listed, all zero.
- What a detector reports: the default detection plan's visibility (each side camera
  sees its own side, the front camera the distal leg joints of both sides and the
  antennae), 1 px noise, 5 % gross outliers within +-80 px of the truth.
- The starting rig, as a user would type it: each camera about 4 degrees off on its
  orbit, 4 % off in distance, 0.1 degree off in aim; intrinsics as the truth.

``hard=True`` is the variant where the front camera sees nothing (the two sides
connect only through the rig) and every camera's aim is 3 degrees off.

Projection uses OpenCV (``cv2.projectPoints``), independent of flylib's model.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from flylib.alignment import similarity_aligned
from flylib.camera.rig import CameraGroup, orbit_extrinsics

from rig_constants import AZIMUTHS as RIG_AZIMUTHS, IMAGE_SIZE, VIEWS
from synthetic import POINT_NAMES, project_opencv, rig_visibility

AZIMUTHS = tuple(RIG_AZIMUTHS.values())
DISTANCE = 116.0
FOCAL = 16000.0
LEG_POINTS = tuple(
    p for p, name in enumerate(POINT_NAMES) if name[:2] in ("lf", "lm", "lh", "rf", "rm", "rh")
)

_JOINTS = ("thorax_coxa", "coxa_trochanter", "femur_tibia", "tibia_tarsus", "claw")
_SCALE = 1.4
_SEGMENTS = _SCALE * np.array([0.30, 0.70, 0.65, 0.55])  # coxa, femur, tibia, tarsus
_PITCH_DEG = np.array([65.0, -10.0, 55.0, 80.0])
_COXA = {"f": (0.35, 0.14), "m": (0.0, 0.20), "h": (-0.30, 0.17)}
_YAW_DEG = {"f": 45.0, "m": 0.0, "h": -40.0}
_BODY_Z = _SCALE * 0.45


@dataclass
class RoughCase:
    """One generated case.

    Attributes
    ----------
    truth
        ``(T, 38, 3)`` world points.
    rig, start
        The true rig and the rough starting rig (``CameraGroup``).
    pts2d, conf
        ``(V, T, 38, 2)`` detections (NaN = not seen) and ``(V, T, 38)`` confidences.
    outlier
        ``(V, T, 38)`` bool: which detections are gross outliers.
    bone
        Median true bone length (the error unit).
    """

    truth: np.ndarray
    rig: CameraGroup
    start: CameraGroup
    pts2d: np.ndarray
    conf: np.ndarray
    outlier: np.ndarray
    bone: float


def _smooth_walk(rng, n_frames: int, n_series: int, step: float) -> np.ndarray:
    """``(T, n)`` smooth random trajectories whose per-frame change has RMS ~``step``."""
    t = np.arange(n_frames)[:, None, None]
    freqs = rng.uniform(0.004, 0.03, (1, n_series, 3))  # cycles per frame
    phases = rng.uniform(0, 2 * np.pi, (1, n_series, 3))
    amps = rng.uniform(0.5, 1.0, (1, n_series, 3))
    # d/dt of a sin(2 pi f t) is 2 pi f a: normalize the RMS per-frame change to `step`
    speed = np.sqrt((((2 * np.pi * freqs * amps) ** 2) / 2).sum(-1))
    walk = (amps * np.sin(2 * np.pi * freqs * t + phases)).sum(-1)
    return walk * (step / speed)


def tethered_fly(n_frames: int, seed: int = 0, step_frac: float = 0.03) -> np.ndarray:
    """A tethered fly: ``(n_frames, 38, 3)`` world points, bone lengths constant.

    The thorax (and with it every thorax-coxa point) is fixed; each leg's yaw and four
    pitch angles wander smoothly so that the leg joints move about ``step_frac`` of a
    median bone per frame.
    """
    rng = np.random.default_rng(seed)
    out = np.zeros((n_frames, len(POINT_NAMES), 3))
    index = {n: i for i, n in enumerate(POINT_NAMES)}
    median_bone = float(np.median(_SEGMENTS))
    # an angle change of d radians moves a joint ~ d * (chain length to it)
    angle_step = step_frac * median_bone / (1.5 * median_bone)
    for side, sign in (("l", 1.0), ("r", -1.0)):
        for pos in ("f", "m", "h"):
            leg = f"{side}{pos}"
            angles = _smooth_walk(rng, n_frames, 5, angle_step)
            yaw = np.deg2rad(_YAW_DEG[pos]) + angles[:, 0]
            pitch = np.deg2rad(_PITCH_DEG)[None] + angles[:, 1:]
            lateral = np.stack([np.sin(yaw), sign * np.cos(yaw), np.zeros_like(yaw)], -1)
            x, y = _COXA[pos]
            joint = np.tile([_SCALE * x, sign * _SCALE * y, _BODY_Z - 0.18], (n_frames, 1))
            out[:, index[f"{leg}_{_JOINTS[0]}"]] = joint
            for s, length in enumerate(_SEGMENTS):
                direction = np.cos(pitch[:, s : s + 1]) * lateral
                direction[:, 2] = -np.sin(pitch[:, s])
                joint = joint + length * direction
                out[:, index[f"{leg}_{_JOINTS[s + 1]}"]] = joint
        wiggle = 0.01 * np.sin(2 * np.pi * 0.02 * np.arange(n_frames) + sign)[:, None]
        out[:, index[f"{side}_antenna"]] = np.array([0.80, sign * 0.12, 0.75]) * _SCALE + wiggle
        for k, (x, y, z) in enumerate(
            [(-0.45, 0.22, 0.05), (-0.85, 0.20, 0.0), (-1.25, 0.12, -0.05)]
        ):
            out[:, index[f"{side}_abdomen{k}"]] = np.array([x, sign * y, 0.45 + z]) * _SCALE
    out[..., 2] -= 0.5 * (out[..., 2].max() + out[..., 2].min())  # centred on the rig's aim
    return out


def true_rig(seed: int = 0) -> CameraGroup:
    """A DeepFly3D-like rig: orbit cameras with small irregularities, 5 zero distortions."""
    rng = np.random.default_rng(seed)
    height, width = IMAGE_SIZE
    rvecs, tvecs, intrs = [], [], []
    for az in AZIMUTHS:
        look_at = rng.normal(0.0, 0.1, 3)
        rvec, tvec = orbit_extrinsics(
            look_at,
            DISTANCE + rng.normal(0, 1.0),
            az + rng.normal(0, 1.0),
            rng.normal(0, 2.0),
            rng.normal(0, 1.0),
        )
        rvecs.append(rvec)
        tvecs.append(tvec)
        focal = FOCAL + rng.normal(0, 150.0)
        intrs.append(
            [focal, focal, width / 2 + rng.uniform(-40, 40), height / 2 + rng.uniform(-25, 25)]
        )
    return CameraGroup.from_arrays(
        list(VIEWS), np.array(rvecs), np.array(tvecs), np.array(intrs), np.zeros((len(VIEWS), 5))
    )


def _random_perpendicular(rng, axis: np.ndarray) -> np.ndarray:
    v = rng.normal(size=3)
    v -= v @ axis * axis
    return v / np.linalg.norm(v)


def rough_start(
    rig: CameraGroup,
    *,
    orbit_deg: float = 4.0,
    dist_frac: float = 0.04,
    aim_deg: float = 0.1,
    seed: int = 1,
) -> CameraGroup:
    """The rig as a user enters it: each camera moved about ``orbit_deg`` along its
    orbit (about the world origin, still looking the same way relative to it), its
    distance off by about ``dist_frac`` and its aim off by about ``aim_deg``."""
    rng = np.random.default_rng(seed)
    rvecs, tvecs = [], []
    for rvec, tvec in zip(rig.rvecs, rig.tvecs):
        rmat = cv2.Rodrigues(np.asarray(rvec, float))[0]
        centre = -rmat.T @ tvec
        radial = centre / np.linalg.norm(centre)
        orbit = cv2.Rodrigues(
            _random_perpendicular(rng, radial) * np.deg2rad(rng.uniform(0.75, 1.25) * orbit_deg)
        )[0]
        scale = 1.0 + rng.choice([-1, 1]) * rng.uniform(0.75, 1.25) * dist_frac
        aim = cv2.Rodrigues(
            _random_perpendicular(rng, np.array([0.0, 0.0, 1.0]))
            * np.deg2rad(rng.uniform(0.75, 1.25) * aim_deg)
        )[0]
        new_centre = scale * (orbit @ centre)
        new_rmat = aim @ rmat @ orbit.T  # orbit the camera, then turn it about its centre
        rvecs.append(cv2.Rodrigues(new_rmat)[0].ravel())
        tvecs.append(-new_rmat @ new_centre)
    return CameraGroup.from_arrays(
        list(rig.names), np.array(rvecs), np.array(tvecs), rig.intrs, rig.dists
    )


def bone_pairs() -> tuple[np.ndarray, np.ndarray]:
    """fly38 leg bones as index arrays ``(i, j)``."""
    index = {n: i for i, n in enumerate(POINT_NAMES)}
    pairs = [
        (index[f"{leg}_{a}"], index[f"{leg}_{b}"])
        for leg in ("lf", "lm", "lh", "rf", "rm", "rh")
        for a, b in zip(_JOINTS[:-1], _JOINTS[1:])
    ]
    return tuple(np.array(x) for x in zip(*pairs))


def make_case(
    n_frames: int = 300,
    *,
    hard: bool = False,
    blind_front: bool | None = None,
    seed: int = 0,
    noise_px: float = 1.0,
    outlier_frac: float = 0.05,
    outlier_px: float = 80.0,
) -> RoughCase:
    """Generate the rough case (``hard=True``: front camera blind, aim 3 degrees off;
    ``blind_front``: the front camera blind or not, whatever ``hard`` says)."""
    rng = np.random.default_rng(seed + 100)
    truth = tethered_fly(n_frames, seed=seed)
    rig = true_rig(seed=seed)
    start = rough_start(rig, aim_deg=3.0 if hard else 0.1, seed=seed + 1)
    vis = rig_visibility(list(VIEWS), POINT_NAMES)
    if hard if blind_front is None else blind_front:
        vis[VIEWS.index("f")] = False
    pts2d, conf, outlier = detections(rig, truth, vis, rng, noise_px, outlier_frac, outlier_px)
    return RoughCase(
        truth=truth,
        rig=rig,
        start=start,
        pts2d=pts2d,
        conf=conf,
        outlier=outlier,
        bone=median_bone(truth),
    )


def detections(rig, truth, vis, rng, noise_px, outlier_frac, outlier_px):
    """What a detector reports of ``truth`` ``(T, P, 3)`` through ``rig`` where ``vis``
    ``(V, P)``: ``noise_px`` Gaussian noise, a fraction ``outlier_frac`` of gross
    outliers within ``+-outlier_px``, confidences lower on the outliers.

    Returns ``(pts2d (V, T, P, 2), conf (V, T, P), outlier (V, T, P))``, NaN / 0 / False
    where not seen.
    """
    clean = project_opencv(rig, truth)  # (V, T, P, 2)
    pts2d = clean + rng.normal(0.0, noise_px, clean.shape)
    outlier = (rng.random(clean.shape[:3]) < outlier_frac) & vis[:, None, :]
    pts2d = np.where(
        outlier[..., None], clean + rng.uniform(-outlier_px, outlier_px, clean.shape), pts2d
    )
    conf = np.where(
        outlier, rng.uniform(0.2, 0.7, outlier.shape), rng.uniform(0.6, 1.0, outlier.shape)
    )
    seen = np.broadcast_to(vis[:, None, :], outlier.shape)
    return np.where(seen[..., None], pts2d, np.nan), np.where(seen, conf, 0.0), outlier & seen


def median_bone(pts3d: np.ndarray) -> float:
    """Median leg-bone length of ``(T, 38, 3)`` points (the error unit)."""
    i, j = bone_pairs()
    return float(np.nanmedian(np.linalg.norm(pts3d[:, i] - pts3d[:, j], axis=-1)))


def similarity_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-point distance after the least-squares similarity (Umeyama) alignment of all
    points both hold (no trimming); NaN where either is missing."""
    return np.linalg.norm(similarity_aligned(estimate, truth) - truth, axis=-1)


#: the bundle-adjustment settings before issue 12 (scipy, no facts about the fly): the
#: baseline the benchmark prints beside the default config
PREVIOUS_DEFAULTS = {
    "solver": "scipy",
    "bone_lengths": False,
    "symmetric_bones": False,
    "rigid_points": [],
}


def fit_with_default_config(case: RoughCase, start: CameraGroup | None = None, **overrides):
    """Bundle-adjust ``case`` from ``start`` (default: the rough rig) with the default
    config's ``bundle_adjustment`` table (``overrides`` replace its keys), then
    triangulate every frame with the default triangulation.

    Returns ``(result, refined rig, pts3d (T, 38, 3), error in median bones (T, 38))``.
    """
    from flylib.config import Config
    from flylib.pipeline.bundle_adjustment import compute_bundle_adjustment
    from flylib.pipeline.inputs import stage_inputs
    from flylib.triangulation import reconstruct

    base = Config.default()
    data = dict(base.data)
    data["bundle_adjustment"] = {**(data.get("bundle_adjustment") or {}), **overrides}
    config = Config.from_dict(data)
    adjusted = compute_bundle_adjustment(
        stage_inputs(config, "bundle_adjustment"),
        case.start if start is None else start,
        case.pts2d,
        case.conf,
    )
    result, refined = adjusted.solution, adjusted.cameras
    pts3d, _, _ = reconstruct(refined, case.pts2d, config.triangulation, case.conf)
    return result, refined, pts3d, similarity_error(pts3d, case.truth) / case.bone
