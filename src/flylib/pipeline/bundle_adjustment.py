"""The bundle-adjustment stage: 2D + config rig -> ``<outdir>/stages/bundle_adjustment.h5``."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config.constants import LEAST_SQUARES_PERF
from ..config.params import BundleAdjustmentParams
from ..stages import Stage
from .inputs import RigSpec, SkeletonSpec, StageInputs, register
from .stage_helpers import image_sizes, solving

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float
    from scipy.optimize import OptimizeResult

    from ..camera.rig import CameraGroup
    from ..config import Config

log = logging.getLogger(__name__)

__all__ = [
    "BundleAdjusted",
    "BundleAdjustmentInputs",
    "BundleAdjustmentRuntime",
    "compute_bundle_adjustment",
    "run_bundle_adjustment",
]


RECORD = Stage(
    "bundle_adjustment",
    default_on=True,
    after=("pose2d",),
    params=BundleAdjustmentParams,
    artifact="bundle_adjustment.h5",
    results_group=True,
    hint="check its 2D (are the views' points of one fly, in raw-frame pixels?) "
    "and the starting rig (cameras, calibration.file), or set "
    "pipeline.do_bundle_adjustment: false",
    memory=(380, 30),
)


@dataclass(frozen=True)
class BundleAdjustmentRuntime:
    """Untracked: ``config_dir`` (where a relative calibration path is looked up after the
    recording's folder) and the speed/log-only ``least_squares`` options (``verbose``,
    ``workers``), passed to the solver with the tracked ones."""

    config_dir: Path | None = None
    solver_options: Mapping[str, Any] = field(default_factory=dict)


@register
@dataclass(frozen=True)
class BundleAdjustmentInputs(StageInputs):
    """What the bundle-adjustment stage reads: the ``bundle_adjustment`` table (less the
    runtime's options), the config rig the fit starts from, and the skeleton."""

    STAGE = RECORD.name

    bundle_adjustment: BundleAdjustmentParams
    rig: RigSpec
    skeleton: SkeletonSpec
    runtime: BundleAdjustmentRuntime = BundleAdjustmentRuntime()

    @classmethod
    def from_config(cls, config: Config) -> BundleAdjustmentInputs:
        params = config.bundle_adjustment
        options = params.least_squares
        tracked = {k: v for k, v in options.items() if k not in LEAST_SQUARES_PERF}
        rig = RigSpec.from_config(config)
        return cls(
            # the per-recording solve is the same with or without a session solve
            bundle_adjustment=replace(params, least_squares=tracked, session=False),
            rig=rig,
            skeleton=SkeletonSpec.from_config(config),
            runtime=BundleAdjustmentRuntime(
                config_dir=rig.config_dir,
                solver_options={k: v for k, v in options.items() if k in LEAST_SQUARES_PERF},
            ),
        )


@dataclass(frozen=True)
class BundleAdjusted:
    """The bundle-adjustment result: ``points3d`` of the fitted frames and points (NaN
    elsewhere), ``summary`` (the artifact's attribute: ``success``, ``message``, ``cost``,
    ``nfev``, ``seconds``, ``report``), ``solution`` (the solver's whole result)."""

    cameras: CameraGroup
    points3d: Float[np.ndarray, "T P 3"]
    summary: dict[str, Any]
    solution: OptimizeResult


def compute_bundle_adjustment(
    inputs: BundleAdjustmentInputs,
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None = None,
) -> BundleAdjusted:
    """Refine ``cameras`` against ``pts2d`` with the ``bundle_adjustment`` table (no file I/O)."""
    from ..bundle_adjustment import bundle_adjust_sequence

    skeleton = inputs.skeleton.skeleton()
    started = time.perf_counter()
    result, refined, pts3d = bundle_adjust_sequence(
        cameras,
        pts2d,
        conf,
        skeleton,
        **inputs.bundle_adjustment.sequence_kwargs(skeleton.point_names),
        **inputs.runtime.solver_options,
    )
    summary = {
        "success": bool(getattr(result, "success", True)),
        "message": str(getattr(result, "message", "")),
        "cost": float(getattr(result, "cost", np.nan)),
        "nfev": int(getattr(result, "nfev", 0) or 0),
        "seconds": round(time.perf_counter() - started, 3),
    }
    if hasattr(result, "report"):  # what was free, kept fractions, rounds, warnings
        summary["report"] = result.report
    return BundleAdjusted(refined, pts3d, summary, result)


def run_bundle_adjustment(
    inputs: BundleAdjustmentInputs,
    pose2d_path: str | Path,
    out_path: str | Path,
    *,
    recording_dir: str | Path | None = None,
) -> Path:
    """Refine the config rig against the recording's 2D keypoints."""
    from ..provenance import stage_provenance
    from ..results import Pose2dData, write_stage

    pose2d = Pose2dData.load(pose2d_path)
    cameras = inputs.rig.camera_group(image_sizes(pose2d), recording_dir)
    with solving("bundle_adjustment", recording_dir or pose2d_path):
        result = compute_bundle_adjustment(inputs, cameras, pose2d.pts2d, pose2d.conf)
    write_stage(
        out_path,
        "bundle_adjustment",
        {},
        cameras=result.cameras,
        attrs={"summary": json.dumps(result.summary)},
        meta=stage_provenance(
            inputs.canonical_params(), "bundle_adjustment", {"pose2d": pose2d_path}
        ),
    )
    log.info("bundle adjustment: %s", result.summary)
    return Path(out_path)
