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

    Attributes
    ----------
    angles
        ``(T, 42)`` radians, columns :func:`~flylib.neuromechfly.model.dof_names`
        (flygym's ``joint_<leg><dof>``); NaN where a leg was not solved.
    residual
        ``(T, 6, 5)`` distance from each joint of the fitted chain (forward kinematics
        of ``angles`` on the fly's own segment lengths) to the aligned measured joint,
        in leg lengths of the model's leg; joints
        :data:`~flylib.neuromechfly.model.CHAIN_JOINTS`.
    model_residual
        The same for the model's own chain (what a replay in flygym reproduces): adds
        the difference between the fly's and the model's proportions.
    aligned
        ``(T, 6, 5, 3)`` the measured legs in the model's thorax frame (mm).
    alignment
        The similarity, per-leg scales, thorax motion and mirroring.
    unsolved
        ``leg -> number of frames`` left NaN because a point of the leg is missing.
    """

    angles: Float[np.ndarray, "T 42"]
    residual: Float[np.ndarray, "T 6 5"]
    model_residual: Float[np.ndarray, "T 6 5"]
    aligned: Float[np.ndarray, "T 6 5 3"]
    alignment: TemplateAlignment
    unsolved: dict[str, int]

    def residual_summary(self, model: bool = False) -> dict[str, dict[str, float]]:
        """Per leg and joint: the median and 95th percentile of :attr:`residual`
        (``model``: of :attr:`model_residual`)."""
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
    """Align ``pts3d`` to NeuroMechFly's template and solve each leg's seven angles.

    Parameters
    ----------
    pts3d
        ``(T, P, 3)`` the recording's 3D points, NaN = missing.
    skeleton
        Names the six legs as limbs ``lf_leg`` ... ``rh_leg`` of five points each.
    still_tolerance
        See :func:`~flylib.neuromechfly.align.align_to_template`.
    iterations
        Levenberg-Marquardt steps per (frame, leg).
    source
        The file the points came from, for messages.

    Raises
    ------
    ConfigError
        If the skeleton does not name the six legs.
    ResultsError
        If the thorax is not still or too few thorax-coxa points were reconstructed.
    """
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
