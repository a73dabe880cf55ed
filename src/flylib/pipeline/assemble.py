"""The assemble stage: ``results.h5`` from the stage artifacts (groups copied, arrays never
loaded), and the recording's summary beside it (``summary.json``, ``summary.png``,
``calibration.toml``, ``suspects.csv``, the config snapshot)."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ResultsError
from ..paths import atomic_path
from ..results.artifacts import SUMMARY_FILES
from ..stages import FINAL_3D, Stage
from .inputs import RigSpec, SkeletonSpec, StageInputs, register
from .stage_helpers import RigRuntime

log = logging.getLogger(__name__)


RECORD = Stage(
    "assemble",
    default_on=None,
    after=("refinement",),
    outputs=("results.h5", *SUMMARY_FILES),
    memory=(160, 130),
)


@register
@dataclass(frozen=True)
class AssembleInputs(StageInputs):
    """The assemble stage's inputs: ``rig`` is stored in ``results.h5`` as ``config_rig``;
    ``skeleton`` includes palette and name (``results.h5`` and the summary figure carry them)."""

    STAGE = RECORD.name

    rig: RigSpec
    skeleton: SkeletonSpec
    runtime: RigRuntime = RigRuntime()

    @classmethod
    def from_config(cls, config) -> AssembleInputs:
        rig = RigSpec.from_config(config)
        return cls(
            rig=rig,
            skeleton=SkeletonSpec.from_config(config, palette=True, name=True),
            runtime=RigRuntime(rig.config_dir),
        )


def _provenance(inputs: StageInputs, **upstream) -> dict:
    """Provenance meta of ``inputs``' artifact: its params hash and its ``upstream``'s."""
    from ..provenance import stage_provenance

    return stage_provenance(inputs.canonical_params(), inputs.STAGE, upstream)


def run_assemble(
    inputs: AssembleInputs,
    stage_files: Mapping[str, str | Path],
    outdir: str | Path,
    *,
    recording_dir: str | Path | None = None,
    truth_path: str | Path | None = None,
    snapshot_path: str | Path | None = None,
    snapshot_text: str | None = None,
) -> dict:
    """Assemble ``results.h5`` from ``stage_files`` (stage -> artifact; ``pose2d`` required,
    empty entries skipped), then write ``summary.png``, ``calibration.toml`` (the final rig,
    Anipose format), ``suspects.csv`` and ``summary.json`` (returned). With ``truth_path``
    (the demo) the 3D error against the truth goes in the summary.

    ``snapshot_text`` (:meth:`~flylib.config.Config.snapshot_text`, required with
    ``snapshot_path``) is written to ``snapshot_path`` last, atomically, so the snapshot never
    describes a config the results beside it were not made with.
    """
    from ..interop.anipose import write_anipose_toml
    from ..results import FORMAT_VERSION, PoseResult, assemble_results, read_image_sizes
    from ..visualization import summary_figure

    if snapshot_path is not None and snapshot_text is None:
        raise ValueError("run_assemble: snapshot_path needs the config's snapshot_text")
    outdir = Path(outdir)
    stage_files = {k: Path(v) for k, v in stage_files.items() if v}
    if "pose2d" not in stage_files:
        raise ResultsError(
            "assemble: no pose2d artifact given; every result starts from 2D keypoints"
        )
    sizes = read_image_sizes(stage_files["pose2d"])  # the arrays are copied, never loaded, here
    rig = inputs.rig.camera_group(sizes, recording_dir)
    meta = {
        "recording": str(recording_dir) if recording_dir else None,
        # the folder a relative path meant, for readers started from elsewhere (the GUI)
        "recording_abspath": os.path.abspath(recording_dir) if recording_dir else None,
        **_provenance(inputs, **stage_files),
    }
    handedness = _handedness(inputs, stage_files, rig, recording_dir)
    if handedness is not None:
        meta["handedness"] = handedness  # kinematics and neuromechfly read it from results.h5
        if handedness["message"]:
            log.warning("%s", handedness["message"])
    results_path = outdir / "results.h5"
    assemble_results(
        results_path,
        skeleton=inputs.skeleton.skeleton(),
        config_rig=rig,
        stage_files=stage_files,
        meta=meta,
    )
    result = PoseResult.load(results_path)
    summary_figure(result, outdir / "summary.png")
    write_anipose_toml(
        result.cameras,
        outdir / "calibration.toml",
        image_sizes=sizes,
        metadata={"recording": str(recording_dir or "")},
    )
    summary = _summary(result, stage_files, recording_dir, outdir, FORMAT_VERSION)
    if handedness is not None:
        summary["handedness"] = handedness
    accuracy = _accuracy(stage_files)
    if accuracy is not None:
        summary["accuracy"] = accuracy
    summary["suspects"] = _write_suspects(results_path, outdir, result)
    if truth_path:
        summary.update(_errors_vs_truth(result, stage_files, truth_path))
    summary["params_sha256"] = {
        **meta.get("upstream_params_sha256", {}),
        "assemble": meta["params_sha256"],
    }
    _write_json(outdir / "summary.json", summary)
    if snapshot_path is not None:
        write_snapshot(snapshot_text, snapshot_path)
    return summary


def write_snapshot(text: str, path: str | Path) -> Path:
    """Write a config's text (:meth:`~flylib.config.Config.snapshot_text`) atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(text.encode("utf-8"))
    return Path(path)


#: The frames (evenly spaced) the starting rig's handedness is measured on: enough to decide.
START_FRAMES = 200


def _handedness(inputs: AssembleInputs, stage_files, rig, recording_dir) -> dict | None:
    """The handedness entry (:func:`flylib.handedness.rig_check`) of the result's 3D (``None``
    without one). After bundle adjustment, a 3D that is not a fly's is also triangulated
    through the starting rig, so a mirror image is blamed on the rig it came from."""
    from ..handedness import RIGHT_HANDED, handedness, rig_check
    from ..results import read_stage

    stage = next((s for s in FINAL_3D if s in stage_files), None)
    if stage is None:
        return None
    arrays = read_stage(stage_files[stage], stage)
    skeleton = inputs.skeleton.skeleton()
    final = handedness(arrays["points3d"], skeleton)
    adjusted = "bundle_adjustment" in stage_files
    start = None
    # only to say why a 3D is not a fly (else every assemble job pays a JAX trace)
    if adjusted and final.verdict != RIGHT_HANDED:
        pts2d = arrays.get("points")
        if pts2d is None:
            pts2d = read_stage(stage_files["pose2d"], "pose2d")["points"]
        frames = np.unique(np.linspace(0, pts2d.shape[1] - 1, START_FRAMES).round().astype(int))
        start = handedness(rig.triangulate(np.asarray(pts2d, float)[:, frames]), skeleton)
    calibration = inputs.rig.calibration
    if calibration:
        from ..interop.anipose import calibration_file

        where = calibration_file(
            dict(calibration),
            Path(recording_dir) if recording_dir else None,
            inputs.rig.config_dir,
        )
        name = f"the calibration file {where}"
    else:
        name = "the config's cameras table"
    return rig_check(
        final,
        rig=name,
        from_file=bool(calibration),
        mirror_set=bool(calibration and calibration.get("mirror")),
        adjusted=adjusted,
        start=start,
    )


def _errors_vs_truth(result, stage_files: Mapping[str, Path], truth_path) -> dict:
    """The demo's 3D error against its truth (and the triangulation's, when refinement ran)."""
    from ..demo import demo_error, load_truth

    truth = load_truth(truth_path)
    out = {}
    if result.pts3d is not None:
        out["error_vs_truth"] = demo_error(result.pts3d, truth["points3d"])
    if "refinement" in stage_files and "triangulation" in stage_files:
        from ..results import read_stage

        tri3d = read_stage(stage_files["triangulation"], "triangulation")["points3d"]
        out["error_vs_truth_triangulation"] = demo_error(tri3d, truth["points3d"])
    return out


def _summary(result, stage_files, recording_dir, outdir, version) -> dict:
    pts2d = np.asarray(result.pts2d, float)
    summary: dict[str, Any] = {
        "recording": str(recording_dir) if recording_dir else None,
        "recording_abspath": os.path.abspath(recording_dir) if recording_dir else None,
        "outdir": str(outdir),
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "format_version": version,
        "stages": sorted(stage_files),
        "views": list(result.cameras.names),
        "frames": int(pts2d.shape[1]),
        "points": int(pts2d.shape[2]),
        "observed_2d_fraction": float(np.isfinite(pts2d).all(-1).mean()),
    }
    if result.pts3d is not None:
        pts3d = np.asarray(result.pts3d, float)
        summary["reconstructed_3d_fraction"] = float(np.isfinite(pts3d).all(-1).mean())
    error = getattr(result, "reproj_error", None)
    if error is not None and np.isfinite(error).any():
        error = np.asarray(error, float)
        summary["reprojection_error_px"] = {
            "median": float(np.nanmedian(error)),
            "p95": float(np.nanpercentile(error, 95)),
            "per_view_median": {
                name: (float(np.nanmedian(e)) if np.isfinite(e).any() else None)
                for name, e in zip(result.cameras.names, error)
            },
        }
    return summary


def _accuracy(stage_files: Mapping[str, Path]) -> dict | None:
    """The truth-free accuracy (:mod:`flylib.accuracy`) recorded by refinement when it ran,
    else by triangulation (``output`` is then the triangulation)."""
    from ..results import open_checked

    for stage in ("refinement", "triangulation"):
        if stage not in stage_files:
            continue
        with open_checked(stage_files[stage], f"re-run the {stage} stage") as f:
            text = f[stage].attrs.get("accuracy") if stage in f else None
        if text is None:
            continue
        found = json.loads(text.decode() if isinstance(text, bytes) else text)
        if stage == "triangulation":
            found["output"] = found["triangulation"]
        found["output_stage"] = stage
        return found
    return None


def _write_suspects(results_path: Path, outdir: Path, result) -> int | None:
    """Write ``suspects.csv`` (:mod:`flylib.suspects`); their number, ``None`` without 3D."""
    from ..suspects import SUSPECTS_FILE, Suspects, suspects_from_results

    if result.pts3d is None or result.reproj_error is None:
        empty = np.zeros(0, int)
        Suspects(empty, empty, np.zeros(0), [], [], np.zeros(result.n_frames)).to_csv(
            outdir / SUSPECTS_FILE
        )
        return None
    suspects = suspects_from_results(results_path)
    suspects.to_csv(outdir / SUSPECTS_FILE)
    log.info(
        "%d suspect (frame, point) pairs in %d frames, %d items to review: %s",
        len(suspects),
        len(suspects.frames),
        suspects.n_items,
        outdir / SUSPECTS_FILE,
    )
    return len(suspects)


def _write_json(path: Path, payload: Mapping) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(payload, indent=2, sort_keys=False) + "\n")
