"""A recording's 3D in NeuroMechFly's template body: one similarity from the thorax-coxa points,
then each leg scaled to the model's leg length about its thorax-coxa joint.

The similarity (Umeyama) maps the recording's six thorax-coxa points, their median over the frames,
onto the model's; a tethered fly's thorax does not move, so one similarity serves every frame, and a
recording whose thorax-coxa points do move is refused. As in SeqIKPy's ``AlignPose``, each leg is
then translated so that its thorax-coxa joint sits on the model's and scaled so that its median
length (the sum of its four segments) is the model's; the inverse kinematics fits chains of the
fly's own segment lengths (SeqIKPy's ``body_size``), so that the angles, not the proportions, carry
the fit. Coordinates in which the legs hang dorsally are mirrored first."""

from __future__ import annotations

import logging
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..alignment import similarity_transform
from ..config.neuromechfly import NeuromechflyParams
from ..errors import ConfigError, ResultsError
from .model import LEGS, leg_lengths, segment_offsets, thorax_coxa_template

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..skeleton import Skeleton

logger = logging.getLogger(__name__)
_MIRROR = np.array([1.0, 1.0, -1.0])


@dataclass
class TemplateAlignment:
    """How a recording was put in the template body.

    The similarity ``x -> scale * rotation @ x + translation`` (recording -> model mm);
    ``leg_scale``: each leg's extra scale about its thorax-coxa joint (NaN: too few points);
    ``segment_scale``: each aligned segment's median length over the model's, the fly's own
    proportions, which the inverse kinematics' chains take; ``thorax_motion``: the 95th percentile
    of the thorax-coxa points' distance from their median position, in model leg lengths;
    ``mirrored``: the coordinates were mirrored first (the legs hung on the dorsal side: a
    left-handed frame, or left and right swapped)."""

    scale: float
    rotation: Float[np.ndarray, "3 3"]
    translation: Float[np.ndarray, " 3"]
    leg_scale: Float[np.ndarray, " 6"]
    segment_scale: Float[np.ndarray, "6 4"]
    thorax_motion: float
    mirrored: bool = False


def leg_point_indices(skeleton: Skeleton) -> np.ndarray:
    """``(6, 5)`` the skeleton's point indices of each leg chain (ThC, CTr, FTi, TiTa, claw):
    the limbs ``lf_leg`` ... ``rh_leg`` of five points each, body to claw, in
    :data:`~flylib.neuromechfly.model.LEGS` order; a ConfigError if one is missing or not five
    points long."""
    rows = []
    for leg in LEGS:
        limb = f"{leg.lower()}_leg"
        chain = skeleton.limbs.get(limb)
        if chain is None or len(chain) != 5:
            raise ConfigError(
                f"skeleton.limb_points.{limb}: NeuroMechFly needs each leg as five points "
                "(thorax-coxa, coxa-trochanter, femur-tibia, tibia-tarsus, claw), "
                f"got {chain!r}; set pipeline.do_neuromechfly: false for this skeleton"
            )
        rows.append([skeleton.point_names.index(p) for p in chain])
    return np.array(rows)


def align_to_template(
    legs3d: Float[np.ndarray, "T 6 5 3"],
    *,
    still_tolerance: float = NeuromechflyParams.still_tolerance,
    source: str = "3D",
) -> tuple[Float[np.ndarray, "T 6 5 3"], TemplateAlignment]:
    """Put a recording's leg chains (legs in ``LEGS`` order, NaN = missing) in the model's
    thorax frame: each leg in model mm, rooted at the model's thorax-coxa joint, and the
    :class:`TemplateAlignment`.

    ``still_tolerance``: the largest thorax-coxa motion accepted (95th percentile of the distance
    from the median position, in model leg lengths); ``source``: the file, for messages. A
    ResultsError if fewer than four thorax-coxa points were reconstructed, or they move more
    (an untethered fly)."""
    legs3d = np.asarray(legs3d, dtype=np.float64)
    thc = legs3d[:, :, 0]
    with _quiet_nan_warnings():
        centre = np.nanmedian(thc, axis=0)
    seen = np.isfinite(centre).all(axis=1)
    if seen.sum() < 4:
        missing = ", ".join(leg for leg, ok in zip(LEGS, seen) if not ok)
        raise ResultsError(
            f"{source}: too few thorax-coxa points to align to NeuroMechFly ({missing} never "
            "reconstructed; at least four of six are needed)"
        )
    mirrored = _legs_point_dorsal(legs3d, centre)
    if mirrored:
        logger.warning(
            "%s: the legs hang on the dorsal side of the thorax-coxa points in these "
            "coordinates (a left-handed frame, or left and right swapped): mirrored "
            "before the NeuroMechFly alignment",
            source,
        )
        legs3d = legs3d * _MIRROR
        centre = centre * _MIRROR
        thc = legs3d[:, :, 0]
    fitted = similarity_transform(centre[seen], thorax_coxa_template()[seen])
    if fitted is None:
        raise ResultsError(
            f"{source}: the thorax-coxa points coincide; cannot align to NeuroMechFly"
        )
    scale, rotation, translation = fitted
    mean_leg = float(leg_lengths().mean())
    with _quiet_nan_warnings():
        motion = scale * np.linalg.norm(thc - centre, axis=-1)
        thorax_motion = float(np.nanpercentile(motion, 95)) / mean_leg
    if thorax_motion > still_tolerance:
        raise ResultsError(
            f"{source}: the thorax is not still (thorax-coxa points move {thorax_motion:.2f} "
            f"leg lengths, 95th percentile; tolerance {still_tolerance:.2f}): NeuroMechFly "
            "alignment needs a tethered fly; raise neuromechfly.still_tolerance only if it is one"
        )
    moved = scale * legs3d @ rotation.T + translation
    segments = np.linalg.norm(np.diff(moved, axis=2), axis=-1).sum(axis=-1)
    with _quiet_nan_warnings():
        leg_scale = leg_lengths() / np.nanmedian(segments, axis=0)
    roots = thorax_coxa_template()
    moved_centre = scale * centre @ rotation.T + translation
    aligned = (moved - moved_centre[None, :, None]) * leg_scale[None, :, None, None] + roots[
        None, :, None
    ]
    with _quiet_nan_warnings():
        lengths = np.nanmedian(np.linalg.norm(np.diff(aligned, axis=2), axis=-1), axis=0)
    segment_scale = lengths / np.linalg.norm(segment_offsets(), axis=-1)
    return aligned, TemplateAlignment(
        scale=float(scale),
        rotation=rotation,
        translation=translation,
        leg_scale=leg_scale,
        segment_scale=segment_scale,
        thorax_motion=thorax_motion,
        mirrored=mirrored,
    )


def _legs_point_dorsal(legs3d: np.ndarray, centre: np.ndarray) -> bool:
    # the body frame of flylib.kinematics (x anterior, y left, z = x cross y) from the thorax-coxa
    # points is right-handed only if the legs hang ventrally (-z); the six points are nearly
    # coplanar, so a fit on them alone cannot tell
    with _quiet_nan_warnings():
        front, hind = np.nanmean(centre[[0, 3]], axis=0), np.nanmean(centre[[2, 5]], axis=0)
        left, right = np.nanmean(centre[:3], axis=0), np.nanmean(centre[3:], axis=0)
        reach = np.nanmean(legs3d[:, :, -1] - legs3d[:, :, 0], axis=(0, 1))
    x = front - hind
    y = left - right
    y = y - (y @ x) / (x @ x) * x
    return bool(np.cross(x, y) @ reach > 0)


@contextmanager
def _quiet_nan_warnings():
    # all-NaN slices (a point never reconstructed) are expected and become NaN
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield
