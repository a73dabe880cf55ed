"""The triangulation stage: its inputs, the pure compute step, and the run that reads
and writes its files.

``run_triangulation`` loads the 2D (pictorial structures' when that stage ran, else
pose2d's), the rig (the bundle-adjusted one when given, else the config rig) and a
corrections sidecar when there is one, calls :func:`compute_triangulation` and writes
``<outdir>/stages/triangulation.h5``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config.params import TriangulationParams, _build_params
from .inputs import (
    OPTIONAL_RIG,
    SKELETON,
    TRIANGULATION,
    RigSpec,
    SkeletonSpec,
    StageInputs,
    register,
    tracked,
)
from .stage_helpers import RigRuntime, _rig_for, _solving, tracked_rig

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

    from ..camera.rig import CameraGroup
    from ..config import Config
    from ..corrections import Corrections

log = logging.getLogger(__name__)

__all__ = ["Triangulated", "TriangulationInputs", "compute_triangulation", "run_triangulation"]


@register
@dataclass(frozen=True)
class TriangulationInputs(StageInputs):
    """What the triangulation stage reads.

    Attributes
    ----------
    triangulation
        The ``triangulation`` table: the method and the knobs that method reads (the
        others at their defaults: the stage tracks only those).
    skeleton
        Points and limbs (the held-out accuracy's bone spread and left/right figures).
    points_from
        ``"pictorial_structures"`` or ``"pose2d"``: where its 2D comes from.
    rig
        The config rig, or ``None`` while bundle adjustment is on (the rig then comes
        from that stage's artifact).
    runtime
        Untracked: the config file's folder (a relative calibration path).
    """

    STAGE = "triangulation"

    triangulation: TriangulationParams = tracked(TRIANGULATION)
    skeleton: SkeletonSpec = tracked(SKELETON)
    points_from: str
    rig: RigSpec | None = tracked(OPTIONAL_RIG)
    runtime: RigRuntime = RigRuntime()

    @classmethod
    def from_config(cls, config: Config) -> TriangulationInputs:
        """The stage's inputs as ``config`` gives them."""
        flags = config.stage_flags()
        return cls(
            triangulation=_build_params(TriangulationParams, config.triangulation.method_params()),
            skeleton=SkeletonSpec.from_config(config),
            points_from="pictorial_structures" if flags["pictorial_structures"] else "pose2d",
            rig=tracked_rig(config),
            runtime=RigRuntime.from_config(config),
        )


@dataclass(frozen=True)
class Triangulated:
    """The triangulation stage's result.

    Attributes
    ----------
    points3d
        ``(T, P, 3)`` NaN where not reconstructed.
    points
        ``(V, T, P, 2)`` the 2D each point was solved from (outlier views NaN).
    reproj_error
        ``(V, T, P)`` pixels.
    corrected
        ``(T, P)`` bool: the points a manual correction changed.
    accuracy
        The truth-free accuracy (:func:`flylib.accuracy.triangulation_accuracy`).
    """

    points3d: Float[np.ndarray, "T P 3"]
    points: Float[np.ndarray, "V T P 2"]
    reproj_error: Float[np.ndarray, "V T P"]
    corrected: Bool[np.ndarray, "T P"]
    accuracy: dict[str, Any]


def compute_triangulation(
    inputs: TriangulationInputs,
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None = None,
    corrections: Corrections | None = None,
) -> Triangulated:
    """Lift ``pts2d`` to 3D on ``cameras`` as ``inputs.triangulation`` says, with the
    manual ``corrections`` applied (:func:`flylib.corrections.reconstruct_corrected`),
    and judge the triangulation by its held-out-view error (no file is read or written).
    """
    from ..accuracy import triangulation_accuracy
    from ..corrections import reconstruct_corrected

    params = inputs.triangulation
    pts3d, clean, error, corrected = reconstruct_corrected(
        params, cameras, pts2d, conf, corrections
    )
    # truth-free accuracy (flylib.accuracy): each view predicted from the others
    accuracy = triangulation_accuracy(
        params, cameras, inputs.skeleton.skeleton(), pts2d, pts3d, conf
    )
    return Triangulated(pts3d, clean, error, corrected, accuracy)


def run_triangulation(
    inputs: TriangulationInputs,
    pose2d_path: str | Path,
    out_path: str | Path,
    *,
    pictorial_path: str | Path | None = None,
    ba_path: str | Path | None = None,
    recording_dir: str | Path | None = None,
    corrections_path: str | Path | None = None,
) -> Path:
    """Lift the 2D keypoints (pictorial-structures-corrected when given, else pose2d's)
    to 3D with the bundle-adjusted rig when given, else the config rig.

    With ``corrections_path`` (a ``corrections.h5`` sidecar, see
    :mod:`flylib.corrections`) the manual edits are applied first; the artifact then
    also holds ``corrected`` ``(T, P)`` and ``corrected_2d`` ``(V, T, P)`` (bool masks of
    what a person changed) and the sidecar's name and edit count as attribute
    ``corrections``.
    """
    from ..corrections import Corrections
    from ..provenance import stage_provenance
    from ..results import Pose2dData, read_stage, write_stage

    pose2d = Pose2dData.load(pose2d_path)
    pts2d = pose2d.pts2d
    if pictorial_path:
        pts2d = np.asarray(read_stage(pictorial_path, "pictorial_structures")["points"], float)
    cameras = _rig_for(inputs.rig, pose2d, ba_path, recording_dir, stage="triangulation")
    corrections = (
        Corrections.load(
            corrections_path,
            pts2d.shape[:3],
            [pose2d.image_sizes.get(name) for name in pose2d.view_names],
        )
        if corrections_path
        else None
    )
    with _solving("triangulation", recording_dir or pose2d_path):
        result = compute_triangulation(inputs, cameras, pts2d, pose2d.conf, corrections)
    arrays = {
        "points": result.points,
        "points3d": result.points3d,
        "reproj_error": result.reproj_error,
    }
    attrs: dict[str, Any] = {"accuracy": result.accuracy}
    if corrections is not None:
        arrays["corrected"] = result.corrected
        arrays["corrected_2d"] = corrections.touched()
        from ..provenance import file_sha256

        attrs["corrections"] = {
            "file": str(corrections_path),
            "count": corrections.count(),
            "sha256": file_sha256(corrections_path),
        }
        log.info(
            "triangulation: %d manual corrections applied from %s",
            corrections.count(),
            corrections_path,
        )
    upstream = {
        "pose2d": pose2d_path,
        "pictorial_structures": pictorial_path,
        "bundle_adjustment": ba_path,
    }
    write_stage(
        out_path,
        "triangulation",
        arrays,
        attrs=attrs,
        meta=stage_provenance(inputs.canonical_params(), "triangulation", upstream),
    )
    return Path(out_path)
