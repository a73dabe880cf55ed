"""From a recording's 3D to NeuroMechFly's leg angles and how well the model reproduces it."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config.neuromechfly import NeuromechflyParams
from .align import TemplateAlignment, align_to_template, leg_point_indices
from .ik import ITERATIONS, solve_leg_angles
from .model import CHAIN_JOINTS, LEGS, forward_kinematics, leg_lengths, segment_offsets

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..skeleton import Skeleton

logger = logging.getLogger(__name__)


@dataclass
class NmfAngles:
    """NeuroMechFly's leg angles of a recording.

    ``angles``: radians, columns :func:`~flylib.neuromechfly.model.dof_names` (flygym's
    ``joint_<leg><dof>``), NaN where a leg was not solved. ``residual``: distance from each joint
    (:data:`~flylib.neuromechfly.model.CHAIN_JOINTS`) of the fitted chain (forward kinematics of
    ``angles`` on the fly's own segment lengths) to the aligned measured joint, in model leg
    lengths; ``model_residual``: the same for the model's own chain (what a replay in flygym
    reproduces), which adds the difference in proportions. ``aligned``: the measured legs in the
    model's thorax frame (mm); ``unsolved``: ``leg -> frames`` left NaN for a missing point."""

    angles: Float[np.ndarray, "T 42"]
    residual: Float[np.ndarray, "T 6 5"]
    model_residual: Float[np.ndarray, "T 6 5"]
    aligned: Float[np.ndarray, "T 6 5 3"]
    alignment: TemplateAlignment
    unsolved: dict[str, int]

    def residual_summary(self, model: bool = False) -> dict[str, dict[str, float]]:
        """``leg_joint -> {median, p95}`` of :attr:`residual` (``model``: of the model's)."""
        residual = self.model_residual if model else self.residual
        out: dict[str, dict[str, float]] = {}
        for k, leg in enumerate(LEGS):
            for j, joint in enumerate(CHAIN_JOINTS):
                values = residual[:, k, j]
                values = values[np.isfinite(values)]
                out[f"{leg}_{joint}"] = {
                    "median": float(np.median(values)) if values.size else float("nan"),
                    "p95": float(np.percentile(values, 95)) if values.size else float("nan"),
                }
        return out


def compute_nmf_angles(
    pts3d: Float[np.ndarray, "T P 3"],
    skeleton: Skeleton,
    *,
    still_tolerance: float = NeuromechflyParams.still_tolerance,
    iterations: int = ITERATIONS,
    source: str = "3D",
) -> NmfAngles:
    """Align ``pts3d`` (NaN = missing) to NeuroMechFly's template and solve each leg's seven
    angles (``iterations`` Levenberg-Marquardt steps per frame and leg).

    The ``skeleton`` names the six legs as limbs ``lf_leg`` ... ``rh_leg`` of five points each
    (else a ConfigError); a thorax that is not still (``still_tolerance``,
    :func:`~flylib.neuromechfly.align.align_to_template`) or too few reconstructed thorax-coxa
    points are a ResultsError naming ``source``."""
    legs3d = np.asarray(pts3d, dtype=np.float64)[:, leg_point_indices(skeleton)]
    aligned, alignment = align_to_template(legs3d, still_tolerance=still_tolerance, source=source)
    own = segment_offsets() * np.nan_to_num(alignment.segment_scale, nan=1.0)[..., None]
    per_leg = solve_leg_angles(aligned, offsets=own, iterations=iterations)
    n_frames = per_leg.shape[0]
    angles = per_leg.reshape(n_frames, -1)
    lengths = leg_lengths()[None, :, None]
    residual = np.linalg.norm(forward_kinematics(angles, own) - aligned, axis=-1) / lengths
    model_residual = np.linalg.norm(forward_kinematics(angles) - aligned, axis=-1) / lengths
    unsolved = {
        leg: int(np.isnan(per_leg[:, k, 0]).sum())
        for k, leg in enumerate(LEGS)
        if np.isnan(per_leg[:, k, 0]).any()
    }
    for leg, count in unsolved.items():
        logger.warning(
            "%s: NeuroMechFly leg %s left NaN in %d of %d frames (too few reconstructed "
            "points: the four beyond the thorax-coxa joint are all needed)",
            source,
            leg,
            count,
            n_frames,
        )
    return NmfAngles(
        angles=angles,
        residual=residual,
        model_residual=model_residual,
        aligned=aligned,
        alignment=alignment,
        unsolved=unsolved,
    )
