"""Is the 3D a fly or its mirror image (:func:`handedness`, from the skeleton's labels)? Is a
calibration's world the mirror image of the cameras table's (:func:`rig_handedness`)?

A fly's axes make a right-handed frame: forward (hind to front legs) cross left (right to left
legs) points dorsal, read from the tethered posture (a leg's tip hangs ventral of its body-coxa
point). A mirror-image calibration or starting rig (near-orthographic cameras cannot tell a scene
from its depth-reversed twin) puts the left legs on the fly's right: the product points ventral."""

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
    """A verdict: ``score`` in ``[-1, 1]`` (``+1`` a fly, ``-1`` its mirror image, NaN: none
    measured), ``verdict`` (``"right-handed"``, ``"mirrored"`` or ``"undetermined"``), ``reason``
    (what it rests on, or why none) and ``frames`` measured (0 from :func:`rig_handedness`)."""

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
    """``group -> point indices`` the check reads, or why the skeleton allows none. Legs are
    limbs from ``<l|r><f|m|h>_thorax_coxa``: ``left``/``right`` (all their points), ``front``,
    ``hind``, ``coxa`` (front, hind, all legs' body-coxa points), ``tip`` (each leg's last point)."""
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
    """Whether world points ``(T, P, 3)`` (NaN = missing; legs named by ``skeleton``) show a fly
    or its mirror image: the median per-frame cosine over at least :data:`MIN_FRAMES` frames,
    ``right-handed`` above +0.5, ``mirrored`` below -0.5, else ``undetermined``."""
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


#: The largest relative residual of a calibration's fit to the cameras table that decides.
FIT = 0.2


def _rig_vectors(rig, names: list[str]) -> np.ndarray:
    """``(2V, 3)``: the cameras' centres (centred, RMS 1) over their image-up directions in the
    world, negated where the scene (nearest all optical axes) lies behind (:func:`mirror_cameras`)."""
    pick = [rig.names.index(n) for n in names]
    rmats, centres = np.asarray(rig.rmats, float)[pick], np.asarray(rig.positions, float)[pick]
    axes = rmats[:, 2]
    off_axis = np.eye(3) - axes[:, :, None] * axes[:, None, :]
    scene = np.linalg.lstsq(off_axis.sum(0), np.einsum("vij,vj->i", off_axis, centres))[0]
    ahead = np.sign(np.einsum("vi,vi->v", scene - centres, axes))[:, None]
    centred = centres - centres.mean(0)
    scale = max(np.sqrt((centred**2).sum(1).mean()), np.finfo(float).tiny)  # 0: one place
    return np.vstack([centred / scale, -rmats[:, 1] * ahead])


def rig_handedness(rig, typed) -> Handedness:
    """Whether calibration ``rig``'s world is the mirror image of ``typed``'s (the cameras table:
    +x towards camera f, +y the fly's left, +z up), from geometry alone: the orthogonal map that
    best fits ``rig``'s :func:`_rig_vectors` to ``typed``'s (cameras matched by name). ``score``:
    its determinant times ``1 - residual / residual of the other handedness``; undetermined under
    3 shared cameras, a residual over :data:`FIT` or a ``|score|`` under :data:`DECISIVE`."""
    names = [n for n in typed.names if n in rig.names]
    if len(names) < 3:
        return Handedness(np.nan, UNDETERMINED, f"{len(names)} cameras shared; needs 3", 0)
    a, b = _rig_vectors(rig, names), _rig_vectors(typed, names)
    u, _, vt = np.linalg.svd(a.T @ b)  # u @ vt fits best, a reflection allowed
    best, other = (np.linalg.norm(a @ u @ np.diag([1, 1, s]) @ vt - b) for s in (1, -1))
    det, best, other = np.linalg.det(u @ vt), best / np.linalg.norm(b), other / np.linalg.norm(b)
    score = float(np.sign(det) * (1 - best / other)) if other > 0 else 0.0
    facts = (
        f"the centres and image-up directions of its {len(names)} cameras fit the cameras table's "
        + ("only mirrored" if det < 0 else "unmirrored")
        + f" (residual {best:.2f}, {other:.2f} {'un' if det < 0 else ''}mirrored)"
    )
    if best > FIT or abs(score) < DECISIVE:
        why = "too poor a fit to tell" if best > FIT else "the other handedness fits about as well"
        return Handedness(score, UNDETERMINED, f"{facts}: {why}", 0)
    return Handedness(score, MIRRORED if det < 0 else RIGHT_HANDED, facts, 0)


#: The reflection :func:`mirror_cameras` applies to world coordinates: z negated.
WORLD_MIRROR = np.diag([1.0, 1.0, -1.0])


def mirror_cameras(cameras):
    """The same rig (names and order kept) in the world ``S X`` (:data:`WORLD_MIRROR`): rotations
    ``-R S`` (proper), translations ``-t``. The camera-frame point of ``S X`` is ``-(R X + t)``:
    every pixel (distortion included) is kept, and the scene lies behind the cameras, which
    pinhole projection (and all flylib computes from it) does not see."""
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
    """The handedness entry of ``summary.json`` and ``results.h5``: ``result`` (the final 3D's
    verdict) with ``rig`` (the starting rig in words), ``cause`` (``None``, ``"calibration"``,
    ``"starting_rig"`` or ``"bundle_adjustment"``), ``message`` (``None`` unless mirrored) and
    ``starting_rig`` (``start``'s entry: the starting rig's 3D, when bundle adjustment
    ``adjusted`` the cameras). ``from_file``: the rig is a calibration file (:data:`MIRROR_SWITCH`
    fixes it); ``mirror_set``: the config already mirrors it."""
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
    """Why ``stage`` (kinematics, neuromechfly) refuses ``result``'s 3D (one line naming
    ``results_path`` and ``allow_mirrored``), or ``None``: the verdict assemble stored in its
    meta ``handedness`` (naming the cause), else the 3D judged here."""
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
