"""Is the 3D a fly or its mirror image? :func:`handedness`, from the skeleton's labels.

A fly's own axes make a right-handed frame: forward (hind legs to front legs) cross left
(right legs to left legs) points dorsal. Dorsal is read from the tethered posture: a leg's
tip (the last point of its chain) hangs ventral of its body-coxa point (the first). A
reconstruction whose calibration or starting rig is the mirror image of the real one
(near-orthographic cameras cannot tell a scene from its depth-reversed twin) puts the left
legs on the fly's right: the same product then points ventral. Each frame gives the cosine
between ``forward x left`` and ``dorsal``; the score is their median over the frames where
every group has a point, so a few bad frames do not decide it: a verdict needs
:data:`MIN_FRAMES` such frames.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from .skeleton import Skeleton

RIGHT_HANDED = "right-handed"
MIRRORED = "mirrored"
UNDETERMINED = "undetermined"

#: A median cosine beyond this (either sign) decides the verdict.
DECISIVE = 0.5
#: Fewest measured frames (each with 3D for :data:`MEASURED`) for a verdict: with 10, five
#: bad frames cannot flip the median. DeepFly3D's sample and package example measure all
#: their 15 frames; a verdict from 2 of 60 frames rests on one frame against one.
MIN_FRAMES = 10
MEASURED = "a front and a hind body-coxa point, a left and a right leg point and a leg tip"


@dataclass(frozen=True)
class Handedness:
    """The verdict of :func:`handedness`.

    ``score`` is the median cosine in ``[-1, 1]`` (``+1``: a fly; ``-1``: its mirror image;
    NaN when no frame could be measured); ``verdict`` ``"right-handed"``, ``"mirrored"`` or
    ``"undetermined"``; ``reason`` one sentence on what it rests on (or why there is none);
    ``frames`` the number of frames measured.
    """

    score: float
    verdict: str
    reason: str
    frames: int

    @property
    def mirrored(self) -> bool:
        """Whether the 3D is the fly's mirror image."""
        return self.verdict == MIRRORED

    def as_dict(self) -> dict:
        """JSON-ready: NaN score as ``None``."""
        out = asdict(self)
        out["score"] = None if not np.isfinite(self.score) else round(float(self.score), 4)
        return out


def side_groups(skeleton: Skeleton) -> dict[str, list[int]] | str:
    """``group -> point indices`` the check reads, or why the skeleton allows no check.

    Legs are the limbs whose first point is ``<l|r><f|m|h>_thorax_coxa``: ``left``/``right``
    (every point of that side's legs), ``front``/``hind`` (the body-coxa points of those
    legs), ``coxa`` (every body-coxa point) and ``tip`` (each leg's last point).
    """
    legs = {}
    for chain in skeleton.limbs.values():
        first = chain[0]
        if (
            len(chain) > 1
            and first.endswith("_thorax_coxa")
            and len(first) > 2
            and first[0] in "lr"
            and first[1] in "fmh"
        ):
            legs[first[:2]] = [skeleton.index(p) for p in chain]
    groups = {
        "left": [i for leg, chain in legs.items() if leg[0] == "l" for i in chain],
        "right": [i for leg, chain in legs.items() if leg[0] == "r" for i in chain],
        "front": [chain[0] for leg, chain in legs.items() if leg[1] == "f"],
        "hind": [chain[0] for leg, chain in legs.items() if leg[1] == "h"],
        "coxa": [chain[0] for chain in legs.values()],
        "tip": [chain[-1] for chain in legs.values()],
    }
    empty = [name for name, members in groups.items() if not members]
    if empty:
        return (
            "the skeleton has no legs labelled for "
            + ", ".join(empty)
            + " (limbs starting at <l|r><f|m|h>_thorax_coxa)"
        )
    return groups


def _mean(points: np.ndarray, members: list[int]) -> np.ndarray:
    sub = points[:, members, :]
    seen = np.isfinite(sub).all(-1)
    count = seen.sum(-1)
    total = np.where(seen[..., None], sub, 0.0).sum(-2)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count[:, None] > 0, total / count[:, None], np.nan)


def _unit(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, v / norm, np.nan)


def frame_scores(points3d: Float[np.ndarray, "T P 3"], skeleton: Skeleton) -> np.ndarray:
    """``(T,)`` per-frame cosine between ``forward x left`` and ``dorsal`` (NaN where a group
    has no finite point in the frame)."""
    groups = side_groups(skeleton)
    if isinstance(groups, str):
        raise ValueError(groups)
    pts = np.asarray(points3d, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[1:] != (skeleton.n_points, 3):
        raise ValueError(f"points3d must be (T, {skeleton.n_points}, 3), got {pts.shape}")
    means = {name: _mean(pts, members) for name, members in groups.items()}
    forward = means["front"] - means["hind"]
    left = means["left"] - means["right"]
    dorsal = means["coxa"] - means["tip"]
    return (_unit(np.cross(forward, left)) * _unit(dorsal)).sum(-1)


def handedness(points3d: Float[np.ndarray, "T P 3"], skeleton: Skeleton) -> Handedness:
    """Whether world points ``(T, P, 3)`` (NaN = missing) show a fly or its mirror image: the
    median per-frame cosine over at least :data:`MIN_FRAMES` frames, ``right-handed`` above
    +0.5, ``mirrored`` below -0.5, else ``undetermined``; the ``skeleton`` names the legs
    (:func:`side_groups`)."""
    groups = side_groups(skeleton)
    if isinstance(groups, str):
        return Handedness(float("nan"), UNDETERMINED, groups, 0)
    scores = frame_scores(points3d, skeleton)
    measured = scores[np.isfinite(scores)]
    few = f"{measured.size} of {scores.size} frames have 3D for {MEASURED}"
    few += f"; a verdict needs {MIN_FRAMES}"
    if measured.size == 0:
        return Handedness(float("nan"), UNDETERMINED, few, 0)
    score = float(np.clip(np.median(measured), -1.0, 1.0))
    facts = (
        f"forward x left against dorsal (leg tips below the body-coxa points) "
        f"is {score:+.2f}, median of {measured.size} frames"
    )
    if measured.size < MIN_FRAMES:
        verdict, why = UNDETERMINED, f"too few to tell ({few})"
    elif score > DECISIVE:
        verdict, why = RIGHT_HANDED, "the left legs are on the fly's left"
    elif score < -DECISIVE:
        verdict, why = MIRRORED, "the left legs are on the fly's right"
    else:
        verdict, why = UNDETERMINED, "too close to 0 to tell a fly from its mirror image"
    return Handedness(score, verdict, f"{facts}: {why}", measured.size)


#: The reflection :func:`mirror_cameras` applies to world coordinates: z negated.
WORLD_MIRROR = np.diag([1.0, 1.0, -1.0])


def mirror_cameras(cameras):
    """The same rig (names and order kept) in mirrored world coordinates (world ``z`` negated).

    A world point ``X`` becomes ``S X`` with ``S = diag(1, 1, -1)``; each camera's rotation
    becomes ``-R S`` (proper again: ``det(-R S) = +1``) and its translation ``-t``. The
    camera-frame point of ``S X`` is then ``-(R X + t)``, whose ratios ``x / z``, ``y / z``
    -- so every pixel, distortion included -- are those of ``X`` before: intrinsics and
    distortion are kept, and triangulating the same 2D gives ``S`` times the old 3D. The
    price is the sign of depth: the scene lies behind the mirrored cameras, which pinhole
    projection (and everything flylib computes from it) does not see.
    """
    import cv2

    from .camera.rig import CameraGroup

    rvecs = []
    for rmat in np.asarray(cameras.rmats, dtype=np.float64):
        rvec, _ = cv2.Rodrigues(-rmat @ WORLD_MIRROR)
        rvecs.append(rvec.ravel())
    return CameraGroup.from_arrays(
        list(cameras.names),
        np.stack(rvecs),
        -np.asarray(cameras.tvecs, dtype=np.float64),
        cameras.intrs,
        cameras.dists,
    )


def mirror_image(result: Handedness) -> str:
    """``"the 3D is the fly's mirror image ..."``: the verdict and its figures."""
    return (
        "the 3D is the fly's mirror image, its left legs on its right (handedness "
        f"{result.score:+.2f}, median of {result.frames} frames)"
    )


#: The config switch that mirrors a calibration file's world back (documented in DOCS_PAGE).
MIRROR_SWITCH = "calibration: {mirror: true}"
MIRROR_OFF = "calibration: {mirror: false}"
DOCS_PAGE = "docs/how-it-works/handedness.md"


def rig_check(
    result: Handedness,
    *,
    rig: str,
    from_file: bool,
    mirror_set: bool = False,
    adjusted: bool = False,
    start: Handedness | None = None,
) -> dict:
    """The handedness entry of ``summary.json`` and ``results.h5``: the verdict on the final
    3D (``result``) and, when it is a mirror image, its cause and the one-line message.

    ``rig`` is the starting rig in words (``"the calibration file <path>"`` or the cameras
    table); ``from_file``: it is a calibration file (:data:`MIRROR_SWITCH` fixes it);
    ``mirror_set``: the config already mirrors it; ``adjusted``: bundle adjustment moved the
    cameras from it, and ``start`` is the verdict on the 3D the starting rig gives.

    Returns ``score``, ``verdict``, ``reason``, ``frames``, ``rig``, ``cause`` (``None``,
    ``"calibration"``, ``"starting_rig"`` or ``"bundle_adjustment"``), ``message`` (``None``
    unless mirrored) and ``starting_rig`` (``start``'s entry or ``None``).
    """
    out = {
        **result.as_dict(),
        "rig": rig,
        "cause": None,
        "message": None,
        "starting_rig": start.as_dict() if start is not None else None,
    }
    if not result.mirrored:
        return out
    what = mirror_image(result)
    kept = ", and bundle adjustment started from it" if adjusted else ""
    if adjusted and start is not None and start.verdict == RIGHT_HANDED:
        out["cause"] = "bundle_adjustment"
        out["message"] = (
            f"{what}; bundle adjustment turned its starting rig ({rig}, which gives a "
            f"right-handed fly, {start.score:+.2f}) into its depth-reversed twin, which "
            "near-orthographic cameras cannot tell apart; start it from a rig closer to the "
            "real one, or set pipeline.do_bundle_adjustment: false"
        )
    elif from_file and mirror_set:
        out["cause"] = "calibration"
        out["message"] = (
            f"{what}; {rig} mirrored by calibration.mirror: true gives a mirror-image "
            f"world{kept}; set {MIRROR_OFF} (see {DOCS_PAGE})"
        )
    elif from_file:
        out["cause"] = "calibration"
        out["message"] = (
            f"{what}; {rig} gives a mirror-image world{kept}; set {MIRROR_SWITCH} in "
            f"the config to mirror it back (reprojection stays the same; see {DOCS_PAGE})"
        )
    else:
        out["cause"] = "starting_rig"
        out["message"] = (
            f"{what}; the starting rig ({rig}) gives a mirror-image world{kept}; check "
            "which side of the fly each camera films (cameras.<view>.azimuth_deg and the "
            f"views' order; see {DOCS_PAGE})"
        )
    return out


def mirrored_refusal(result, results_path, stage: str) -> str | None:
    """Why ``stage`` (kinematics, neuromechfly) refuses the 3D of ``result``, or ``None``.

    The verdict assemble stored in ``results.h5`` (meta ``handedness``, naming the cause) is
    used when present, else the 3D is judged here. The one-line refusal names
    ``results_path`` and the stage's ``allow_mirrored`` switch.
    """
    stored = (result.meta or {}).get("handedness")
    if isinstance(stored, dict) and stored.get("verdict") is not None:
        if stored["verdict"] != MIRRORED:
            return None
        message = stored.get("message") or stored.get("reason")
    else:
        check = handedness(result.pts3d, result.skeleton)
        if not check.mirrored:
            return None
        message = mirror_image(check)
    return (
        f"{results_path}: {stage} refused: {message}. To run {stage} on the mirror image "
        f"anyway, set {stage}: {{allow_mirrored: true}}"
    )
