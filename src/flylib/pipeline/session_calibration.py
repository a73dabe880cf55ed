"""Session calibration (``bundle_adjustment.session: true``): one bundle adjustment over
frames sampled from every recording of a session (one rig), and the session's summary.

The rig is written as a bundle-adjustment artifact (``session_calibration.h5``, read by each
member's later stages in place of its own solve) and in Anipose format (``calibration.toml``).
The summary judges it against the per-recording rigs by held-out-view error
(``session_summary.json``). Rule-only: no ``pipeline.do_*`` key; sessions are planned by
:func:`flylib.sessions.plan_sessions`.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config.params import TriangulationParams, build_params
from ..errors import ResultsError
from ..paths import atomic_path
from .bundle_adjustment import BundleAdjusted, BundleAdjustmentInputs
from .inputs import StageInputs
from .stage_helpers import image_sizes, solving

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int

    from ..camera.rig import CameraGroup

    # the inherited fields' annotations, which the generated __init__ resolves here
    from ..config.params import BundleAdjustmentParams  # noqa: F401
    from .bundle_adjustment import BundleAdjustmentRuntime  # noqa: F401
    from .inputs import RigSpec, SkeletonSpec  # noqa: F401

log = logging.getLogger(__name__)

__all__ = [
    "SessionCalibrationInputs",
    "SessionSummaryInputs",
    "compute_session_calibration",
    "run_session_calibration",
    "run_session_summary",
]


@dataclass(frozen=True)
class SessionCalibrationInputs(BundleAdjustmentInputs):
    """The bundle-adjustment inputs with ``session: true`` (its params hash tells it apart)."""

    STAGE = "session_calibration"

    @classmethod
    def from_config(cls, config) -> SessionCalibrationInputs:
        base = BundleAdjustmentInputs.from_config(config)
        return cls(
            bundle_adjustment=replace(base.bundle_adjustment, session=True),
            rig=base.rig,
            skeleton=base.skeleton,
            runtime=base.runtime,
        )

    def rule_params(self) -> str:
        """The rule's tracked ``params.stage`` (canonical JSON)."""
        return json.dumps(self.canonical_params(), sort_keys=True)


@dataclass(frozen=True)
class SessionSummaryInputs(StageInputs):
    """What the session summary reads: the triangulation it judges each rig by."""

    STAGE = "session_summary"

    triangulation: TriangulationParams

    @classmethod
    def from_config(cls, config) -> SessionSummaryInputs:
        return cls(build_params(TriangulationParams, config.triangulation.method_params()))

    def rule_params(self) -> str:
        """The rule's tracked ``params.stage`` (canonical JSON)."""
        return json.dumps(self.canonical_params(), sort_keys=True)


def compute_session_calibration(
    inputs: BundleAdjustmentInputs,
    cameras: CameraGroup,
    trials: Sequence[Float[np.ndarray, "V T P 2"]],
    confs: Sequence[Float[np.ndarray, "V T P"] | None] | None = None,
) -> tuple[BundleAdjusted, list[Int[np.ndarray, " F"]]]:
    """One bundle adjustment of ``cameras`` over every trial of a session (no file I/O), its
    ``max_frames`` shared (:func:`~flylib.bundle_adjustment.select_session_frames`). Returns
    the result (``points3d`` over the chosen frames, trial after trial) and each trial's
    chosen frame indices."""
    from ..bundle_adjustment import bundle_adjust_sequence, select_session_frames

    confs = list(confs) if confs is not None else [None] * len(trials)
    params = inputs.bundle_adjustment
    frames = select_session_frames(trials, confs, params.max_frames, params.frame_sampling)
    pts2d = np.concatenate([np.asarray(t)[:, f] for t, f in zip(trials, frames)], axis=1)
    conf = (
        None
        if any(c is None for c in confs)
        else np.concatenate([np.asarray(c)[:, f] for c, f in zip(confs, frames)], axis=1)
    )
    skeleton = inputs.skeleton.skeleton()
    kwargs = params.sequence_kwargs(skeleton.point_names)
    kwargs["max_frames"] = None  # chosen above, trial by trial
    started = time.perf_counter()
    result, refined, pts3d = bundle_adjust_sequence(
        cameras, pts2d, conf, skeleton, **kwargs, **inputs.runtime.solver_options
    )
    summary = {
        "success": bool(getattr(result, "success", True)),
        "message": str(getattr(result, "message", "")),
        "cost": float(getattr(result, "cost", np.nan)),
        "nfev": int(getattr(result, "nfev", 0) or 0),
        "seconds": round(time.perf_counter() - started, 3),
        "frames_per_recording": [int(f.size) for f in frames],
    }
    if hasattr(result, "report"):
        summary["report"] = result.report
    return BundleAdjusted(refined, pts3d, summary, result), frames


def run_session_calibration(
    inputs: SessionCalibrationInputs,
    pose2d_paths: Sequence[str | Path],
    out_path: str | Path,
    calibration_path: str | Path,
    *,
    name: str,
    members: Sequence[str],
    recording_dirs: Sequence[str | Path] | None = None,
) -> Path:
    """Solve a session's rig from its members' 2D (in ``members``' order), starting from the
    first member's config rig, and write it to ``out_path`` (provenance naming the session and
    members) and ``calibration_path`` (Anipose). ResultsError when views or image sizes differ."""
    from ..interop.anipose import write_anipose_toml
    from ..provenance import stage_provenance
    from ..results import Pose2dData, write_stage

    if len(pose2d_paths) != len(members):
        raise ValueError("run_session_calibration: one pose2d artifact per member")
    data = [Pose2dData.load(p) for p in pose2d_paths]
    first_dir = recording_dirs[0] if recording_dirs else None
    views, sizes = list(data[0].view_names), image_sizes(data[0])
    for rec, path, pose2d in zip(members, pose2d_paths, data):
        if list(pose2d.view_names) != views or image_sizes(pose2d) != sizes:
            raise ResultsError(
                f"{path}: recording {rec!r} has views {list(pose2d.view_names)} and image "
                f"sizes {image_sizes(pose2d)}, session {name!r} starts from {views} "
                f"{sizes}; one session is one rig: give this recording its own session"
            )
    cameras = inputs.rig.camera_group(sizes, first_dir)
    with solving("bundle_adjustment", f"session {name}"):
        result, frames = compute_session_calibration(
            inputs, cameras, [d.pts2d for d in data], [d.conf for d in data]
        )
    session = {"name": name, "members": list(members)}
    result.summary["session"] = session
    meta = stage_provenance(
        inputs.canonical_params(),
        "bundle_adjustment",
        {f"pose2d:{rec}": path for rec, path in zip(members, pose2d_paths)},
    )
    write_stage(
        out_path,
        "bundle_adjustment",
        {},
        cameras=result.cameras,
        attrs={"summary": json.dumps(result.summary)},
        meta={**meta, "session": session},
    )
    write_anipose_toml(
        result.cameras,
        Path(calibration_path),
        image_sizes=sizes,
        metadata={"session": name, "recordings": list(members)},
    )
    log.info("session %s (%d recordings): %s", name, len(members), result.summary)
    return Path(out_path)


def run_session_summary(
    inputs: SessionSummaryInputs,
    session_path: str | Path,
    pose2d_paths: Sequence[str | Path],
    trial_paths: Sequence[str | Path],
    out_path: str | Path,
    *,
    name: str,
    members: Sequence[str],
) -> dict[str, Any]:
    """Held-out-view error of each member's 2D triangulated with the session's rig and with its
    own, per recording and pooled, written to ``out_path`` (JSON); ``better`` names the rig
    with the lower pooled median (``session`` or ``per_recording``; ``None`` when equal)."""
    from ..results import Pose2dData, read_stage

    session = read_stage(session_path, "bundle_adjustment")
    rigs = {"session": session["cameras"]}
    per_recording: dict[str, Any] = {}
    pooled: dict[str, list[np.ndarray]] = {"per_recording": [], "session": []}
    trial_seconds = 0.0
    for rec, pose2d_path, trial_path in zip(members, pose2d_paths, trial_paths, strict=True):
        pose2d = Pose2dData.load(pose2d_path)
        trial = read_stage(trial_path, "bundle_adjustment")
        trial_seconds += float(_solve_summary(trial).get("seconds", 0.0))
        row = {}
        for label, cameras in (("per_recording", trial["cameras"]), ("session", rigs["session"])):
            errors = _held_out(inputs, cameras, pose2d, pose2d_path)
            pooled[label].append(errors)
            row[label] = _stats(errors)
        per_recording[rec] = row
    overall = {label: _stats(np.concatenate(parts)) for label, parts in pooled.items()}
    medians = {k: v["median"] for k, v in overall.items()}
    better = (  # None: a median missing, or equal (a session of one recording is its own solve)
        None
        if None in medians.values() or len(set(medians.values())) == 1
        else min(medians, key=lambda k: medians[k])
    )
    summary = {
        "session": name,
        "members": list(members),
        "calibration": str(Path(session_path).with_name("calibration.toml")),
        "held_out_error_px": overall,
        "better": better,
        "recordings": per_recording,
        "seconds": {
            "session_solve": float(_solve_summary(session).get("seconds", 0.0)),
            "per_recording_solves": round(trial_seconds, 3),
        },
        "frames_per_recording": _solve_summary(session).get("frames_per_recording"),
    }
    with atomic_path(out_path) as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    log.info(
        "session %s: held-out-view error median %s px per-recording rigs, %s px session rig",
        name,
        medians["per_recording"],
        medians["session"],
    )
    return summary


def _held_out(inputs: SessionSummaryInputs, cameras, pose2d, where) -> np.ndarray:
    """The finite held-out-view errors (px) of ``pose2d``'s 2D triangulated with ``cameras``."""
    from ..accuracy import held_out_errors
    from .triangulation import triangulation_method

    with solving("triangulation", where):
        errors = held_out_errors(
            cameras,
            pose2d.pts2d,
            triangulation_method(inputs.triangulation, cameras),
            conf=pose2d.conf,
        )["triangulation"]
    return errors[np.isfinite(errors)]


def _solve_summary(stage: dict) -> dict:
    """A bundle-adjustment artifact's ``summary`` attribute (JSON text) as a dict."""
    text = stage["attrs"].get("summary") or "{}"
    return json.loads(text) if isinstance(text, str | bytes) else dict(text)


def _stats(errors: np.ndarray) -> dict[str, float | int | None]:
    if errors.size == 0:
        return {"median": None, "p95": None, "n": 0}
    return {
        "median": round(float(np.median(errors)), 4),
        "p95": round(float(np.percentile(errors, 95)), 4),
        "n": int(errors.size),
    }
