"""The pictorial-structures stage: the detector's candidate peaks + rig ->
``<outdir>/stages/pictorial_structures.h5``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..config.params import PictorialParams
from ..errors import ResultsError
from ..stages import Stage
from .inputs import RigSpec, SkeletonSpec, StageInputs, register
from .stage_helpers import RigRuntime, rig_for, solving, tracked_rig

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np
    from jaxtyping import Float

    from ..camera.rig import CameraGroup
    from ..config import Config
    from ..pictorial import Candidates

__all__ = [
    "PictorialStructuresInputs",
    "Recovered",
    "compute_pictorial_structures",
    "run_pictorial_structures",
]


RECORD = Stage(
    "pictorial_structures",
    default_on=False,
    after=("bundle_adjustment",),
    params=PictorialParams,
    artifact="pictorial_structures.h5",
    results_group=True,
    solves_3d=True,
    hint="check the detector's 2D and the rig, or set pipeline.do_pictorial_structures: false",
)


@register
@dataclass(frozen=True)
class PictorialStructuresInputs(StageInputs):
    """What the PS stage reads: ``skeleton`` gives the prior's chains and bones; ``rig`` is
    ``None`` while bundle adjustment is on (the rig comes from its artifact)."""

    STAGE = RECORD.name

    pictorial_structures: PictorialParams
    skeleton: SkeletonSpec
    rig: RigSpec | None
    runtime: RigRuntime = RigRuntime()

    @classmethod
    def from_config(cls, config: Config) -> PictorialStructuresInputs:
        """The stage's inputs as ``config`` gives them."""
        return cls(
            pictorial_structures=config.pictorial_structures,
            skeleton=SkeletonSpec.from_config(config),
            rig=tracked_rig(config),
            runtime=RigRuntime.from_config(config),
        )


@dataclass(frozen=True)
class Recovered:
    """The PS result: ``points3d`` the DLT triangulation of the committed 2D; ``points`` the
    committed candidate per (view, frame, point), NaN where no view was kept (what
    triangulation reads next); ``reproj_error`` in pixels."""

    points3d: Float[np.ndarray, "T P 3"]
    points: Float[np.ndarray, "V T P 2"]
    reproj_error: Float[np.ndarray, "V T P"]


def compute_pictorial_structures(
    inputs: PictorialStructuresInputs,
    cameras: CameraGroup,
    candidates: Candidates,
    pts2d_argmax: Float[np.ndarray, "V T P 2"] | None = None,
) -> Recovered:
    """Choose one candidate peak per (view, frame, point) on ``cameras`` (no file I/O). The
    bone-length prior is triangulated from the arg-max detections ``pts2d_argmax`` where given
    (the one-shot passes its ``pts2d``), else from the candidates' strongest peaks."""
    from ..pictorial import reconstruct

    pts3d, pts2d, error = reconstruct(
        cameras,
        inputs.skeleton.skeleton(),
        candidates,
        pts2d_argmax,
        **inputs.pictorial_structures.solver_kwargs(),
    )
    return Recovered(pts3d, pts2d, error)


def _load_candidates(candidates_path: str | Path | None, pose2d, pose2d_path):
    if candidates_path is not None:
        from ..results import load_candidates

        return load_candidates(candidates_path)
    if pose2d.candidates is None:
        raise ResultsError(
            f"{pose2d_path}: holds no candidate peaks, which pictorial structures needs; "
            "they come only from the detector (set pipeline.do_pictorial_structures: false "
            "for 2D imported from another tool)"
        )
    return pose2d.candidates


def run_pictorial_structures(
    inputs: PictorialStructuresInputs,
    pose2d_path: str | Path,
    out_path: str | Path,
    *,
    candidates_path: str | Path | None = None,
    ba_path: str | Path | None = None,
    recording_dir: str | Path | None = None,
) -> Path:
    """Peak recovery over the detector's candidate peaks, from ``candidates_path`` (pose2d's)
    else the 2D artifact itself; ResultsError without any (2D imported from another tool)."""
    from ..provenance import stage_provenance
    from ..results import Pose2dData, write_stage

    pose2d = Pose2dData.load(pose2d_path)
    candidates = _load_candidates(candidates_path, pose2d, pose2d_path)
    cameras = rig_for(inputs.rig, pose2d, ba_path, recording_dir, stage="pictorial_structures")
    with solving("pictorial_structures", recording_dir or pose2d_path):
        result = compute_pictorial_structures(inputs, cameras, candidates)
    upstream = {
        "pose2d": pose2d_path,
        "candidates": candidates_path,
        "bundle_adjustment": ba_path,
    }
    write_stage(
        out_path,
        "pictorial_structures",
        {"points": result.points, "points3d": result.points3d, "reproj_error": result.reproj_error},
        meta=stage_provenance(inputs.canonical_params(), "pictorial_structures", upstream),
    )
    return Path(out_path)
