"""One function per workflow stage: read the upstream artifact(s) and the config, call
the library, write the stage's artifact atomically.

These are what the command scripts in ``scripts/`` (and so the Snakemake rules) run,
and what a library user can call to reproduce one step by hand. Every function takes
paths and a :class:`~flylib.config.Config`, and runs on the part of it its rule tracks
(:class:`~flylib.pipeline.tracked.StageConfig`: reading any other key raises); none
decides *whether* it should run (the workflow does, from the rule's params and inputs).

=====================  ==========================================  ===============================
stage                  reads                                       writes
=====================  ==========================================  ===============================
``demo``               config (rig, skeleton, ``demo``)            footage, DLC CSVs, ``truth.h5``
``pose2d``             footage, or another tool's 2D files          ``stages/pose2d.h5`` (and, for
                                                                    PS, ``stages/candidates_k<k>.h5``)
``bundle_adjustment``  ``pose2d.h5``, config rig                    ``stages/bundle_adjustment.h5``
``pictorial``          ``pose2d.h5``, candidates, rig              ``stages/pictorial_structures.h5``
``triangulation``      2D (PS if on, else pose2d), rig              ``stages/triangulation.h5``
``refinement``         triangulation, pose2d, rig                   ``stages/refinement.h5``
``assemble``           the stage artifacts                          ``results.h5``, ``summary.json``,
                                                                    ``summary.png``, ``calibration.toml``,
                                                                    ``suspects.csv``
``visualization``      ``results.h5``, footage                      ``<video_name>.mp4``
``kinematics``         ``results.h5``                               ``kinematics.h5``, ``angles.csv``,
                                                                    ``angles.png``
``neuromechfly``       ``results.h5``                               ``neuromechfly.h5``,
                                                                    ``joint_angles.csv``,
                                                                    ``joint_angles.png``
=====================  ==========================================  ===============================
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FlylibError, ResultsError, StageError, one_line
from ..interop.anipose import config_rig
from ..paths import atomic_path
from .pose2d import run_pose2d  # noqa: F401
from .tracked import StageConfig, UntrackedConfigRead

log = logging.getLogger(__name__)


# -- helpers -------------------------------------------------------------------


def _image_sizes(pose2d) -> dict[str, tuple[int, int]]:
    return {str(k): (int(v[0]), int(v[1])) for k, v in (pose2d.image_sizes or {}).items()}


def _rig_for(config, pose2d, ba_path: str | Path | None, recording_dir=None):
    """The bundle-adjusted rig when that artifact is given, else the config rig."""
    if ba_path:
        from ..results import read_stage

        return read_stage(ba_path, "bundle_adjustment")["cameras"]
    return config_rig(config, _image_sizes(pose2d), recording_dir)


def _rig_source(config, ba_path):
    """``config`` as the stage runs it: without a bundle-adjustment artifact the rig is
    the config's, as with bundle adjustment off (so the params track that rig)."""
    if ba_path or isinstance(config, StageConfig) or not config.stage_flags()["bundle_adjustment"]:
        return config
    data = dict(config.data)
    data["pipeline"] = {**(data.get("pipeline") or {}), "do_bundle_adjustment": False}
    return type(config)(data, text=config.text, source=config.source, format=config.format)


def _provenance(config, stage: str, **upstream) -> dict:
    """The params hash of ``stage`` and those of the artifacts it read (meta entries)."""
    from ..provenance import stage_provenance

    return stage_provenance(config, stage, upstream)


#: What to check when a numerical stage fails on a recording's data, per stage.
_CHECK = {
    "bundle_adjustment": "check its 2D (are the views' points of one fly, in raw-frame pixels?) "
    "and the starting rig (cameras, calibration.file), or set "
    "pipeline.do_bundle_adjustment: false",
    "pictorial_structures": "check the detector's 2D and the rig, or set "
    "pipeline.do_pictorial_structures: false",
    "triangulation": "check its 2D (pose2d, corrections) and the rig (bundle adjustment's "
    "result, cameras, calibration.file)",
    "refinement": "check triangulation's 3D (flylib inspect) and the refinement settings, or "
    "set pipeline.do_refinement: false",
    "kinematics": "check the 3D in results.h5 (flylib inspect), or set "
    "pipeline.do_kinematics: false",
}


@contextmanager
def _solving(stage: str, recording) -> Iterator[None]:
    """The stage boundary of a numerical stage: any exception its solver raises on the
    recording's data (``LinAlgError``, overflow, a NaN-filled system, memory) becomes one
    :class:`StageError` line naming the recording and what to check. flylib's own errors,
    storage errors (``OSError``) and :class:`UntrackedConfigRead` (a bug in the stage,
    not the data) pass unchanged; the original is kept as the error's cause and its
    traceback logged at DEBUG."""
    try:
        yield
    except (FlylibError, OSError, UntrackedConfigRead):
        raise  # flylib's own lines; storage errors; a stage reading a key it does not track
    except Exception as exc:
        log.debug("%s failed on %s", stage, recording, exc_info=True)
        raise StageError(
            f"{recording}: {stage.replace('_', ' ')} failed on this recording's data "
            f"({type(exc).__name__}: {one_line(exc, 200) or 'no detail'}); {_CHECK[stage]}"
        ) from exc


# -- stages --------------------------------------------------------------------


def run_demo(config, directory: str | Path):
    """Generate the embedded demo recording into ``directory`` (see :mod:`flylib.demo`)."""
    from ..demo import make_demo

    return make_demo(config, directory)


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


def run_bundle_adjustment(
    config,
    pose2d_path: str | Path,
    out_path: str | Path,
    *,
    recording_dir: str | Path | None = None,
) -> Path:
    """Refine the config rig against the recording's 2D keypoints."""
    from ..bundle_adjustment import bundle_adjust_from_config
    from ..results import Pose2dData, write_stage

    config = StageConfig.for_stage(config, "bundle_adjustment")
    pose2d = Pose2dData.load(pose2d_path)
    cameras = config_rig(config, _image_sizes(pose2d), recording_dir)
    started = time.perf_counter()
    with _solving("bundle_adjustment", recording_dir or pose2d_path):
        result, refined, _ = bundle_adjust_from_config(config, cameras, pose2d.pts2d, pose2d.conf)
    summary = {
        "success": bool(getattr(result, "success", True)),
        "message": str(getattr(result, "message", "")),
        "cost": float(getattr(result, "cost", np.nan)),
        "nfev": int(getattr(result, "nfev", 0) or 0),
        "seconds": round(time.perf_counter() - started, 3),
    }
    if hasattr(result, "report"):  # what was free, kept fractions, rounds, warnings
        summary["report"] = result.report
    write_stage(
        out_path,
        "bundle_adjustment",
        {},
        cameras=refined,
        attrs={"summary": json.dumps(summary)},
        meta=_provenance(config, "bundle_adjustment", pose2d=pose2d_path),
    )
    log.info("bundle adjustment: %s", summary)
    return Path(out_path)


def run_pictorial_structures(
    config,
    pose2d_path: str | Path,
    out_path: str | Path,
    *,
    candidates_path: str | Path | None = None,
    ba_path: str | Path | None = None,
    recording_dir: str | Path | None = None,
) -> Path:
    """Peak recovery over the detector's candidate peaks (pictorial structures).

    The peaks come from ``candidates_path`` (what the pose2d stage writes), else from
    the 2D artifact itself (a :class:`~flylib.results.Pose2dData` saved with them).

    Raises
    ------
    ResultsError
        If there are no candidate peaks (2D imported from another tool).
    """
    from ..pictorial import reconstruct_from_config
    from ..results import Pose2dData, write_stage

    config = StageConfig.for_stage(_rig_source(config, ba_path), "pictorial_structures")
    pose2d = Pose2dData.load(pose2d_path)
    candidates = _load_candidates(candidates_path, pose2d, pose2d_path)
    cameras = _rig_for(config, pose2d, ba_path, recording_dir)
    with _solving("pictorial_structures", recording_dir or pose2d_path):
        pts3d, pts2d, error = reconstruct_from_config(config, cameras, candidates)
    write_stage(
        out_path,
        "pictorial_structures",
        {"points": pts2d, "points3d": pts3d, "reproj_error": error},
        meta=_provenance(
            config,
            "pictorial_structures",
            pose2d=pose2d_path,
            candidates=candidates_path,
            bundle_adjustment=ba_path,
        ),
    )
    return Path(out_path)


def run_triangulation(
    config,
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
    from ..accuracy import triangulation_accuracy
    from ..corrections import Corrections, reconstruct_corrected
    from ..results import Pose2dData, read_stage, write_stage

    config = StageConfig.for_stage(_rig_source(config, ba_path), "triangulation")
    pose2d = Pose2dData.load(pose2d_path)
    pts2d = pose2d.pts2d
    if pictorial_path:
        pts2d = np.asarray(read_stage(pictorial_path, "pictorial_structures")["points"], float)
    cameras = _rig_for(config, pose2d, ba_path, recording_dir)
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
        pts3d, pts2d_clean, error, corrected = reconstruct_corrected(
            config, cameras, pts2d, pose2d.conf, corrections
        )
    arrays = {"points": pts2d_clean, "points3d": pts3d, "reproj_error": error}
    # truth-free accuracy (flylib.accuracy): each view predicted from the others
    attrs = {"accuracy": triangulation_accuracy(config, cameras, pts2d, pts3d, pose2d.conf)}
    if corrections is not None:
        arrays["corrected"] = corrected
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
    write_stage(
        out_path,
        "triangulation",
        arrays,
        attrs=attrs,
        meta=_provenance(
            config,
            "triangulation",
            pose2d=pose2d_path,
            pictorial_structures=pictorial_path,
            bundle_adjustment=ba_path,
        ),
    )
    return Path(out_path)


def run_refinement(
    config, pose2d_path, triangulation_path, out_path, *, ba_path=None, recording_dir=None
) -> Path:
    """Refine the triangulated 3D (see :func:`flylib.refinement.stage.run_refinement`)."""
    from ..refinement.stage import run_refinement as run

    with _solving("refinement", recording_dir or triangulation_path):
        return run(
            StageConfig.for_stage(_rig_source(config, ba_path), "refinement"),
            pose2d_path,
            triangulation_path,
            out_path,
            ba_path=ba_path,
            recording_dir=recording_dir,
        )


def run_kinematics(config, results_path, outdir) -> dict:
    """Body frame and joint angles (see :func:`flylib.kinematics.stage.run_kinematics`)."""
    from ..kinematics.stage import run_kinematics as run

    with _solving("kinematics", results_path):
        return run(StageConfig.for_stage(config, "kinematics"), results_path, outdir)


def run_neuromechfly(config, results_path, outdir) -> dict:
    """NeuroMechFly leg angles (see :func:`flylib.neuromechfly.stage.run_neuromechfly`)."""
    from ..neuromechfly.stage import run_neuromechfly as run

    return run(StageConfig.for_stage(config, "neuromechfly"), results_path, outdir)


def run_assemble(
    config,
    stage_files: Mapping[str, str | Path],
    outdir: str | Path,
    *,
    recording_dir: str | Path | None = None,
    truth_path: str | Path | None = None,
    snapshot_path: str | Path | None = None,
) -> dict:
    """Assemble ``results.h5`` from the stage artifacts, then write the recording's
    summary: ``summary.png``, ``calibration.toml`` (the final rig, Anipose format) and
    ``summary.json``. With ``truth_path`` (the demo) the 3D error against the truth is
    computed, logged and stored in the summary.

    With ``snapshot_path`` the config's text is written there last, atomically, so
    the snapshot never describes a config the results beside it were not made with
    (the workflow's assemble rule is its only writer).

    Returns
    -------
    dict
        The summary written to ``summary.json``.
    """
    from ..interop.anipose import write_anipose_toml
    from ..results import FORMAT_VERSION, PoseResult, assemble_results, read_image_sizes
    from ..visualization import summary_figure

    snapshot = config.snapshot_text() if snapshot_path is not None else None
    config = StageConfig.for_stage(config, "assemble")
    outdir = Path(outdir)
    stage_files = {k: Path(v) for k, v in stage_files.items() if v}
    if "pose2d" not in stage_files:
        raise ResultsError(
            "assemble: no pose2d artifact given; every result starts from 2D keypoints"
        )
    sizes = read_image_sizes(stage_files["pose2d"])  # the arrays are copied, never loaded, here
    rig = config_rig(config, sizes, recording_dir)
    meta = {
        "recording": str(recording_dir) if recording_dir else None,
        **_provenance(config, "assemble", **stage_files),
    }
    results_path = outdir / "results.h5"
    assemble_results(
        results_path, skeleton=config.skeleton(), config_rig=rig, stage_files=stage_files, meta=meta
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
    accuracy = _accuracy(stage_files)
    if accuracy is not None:
        summary["accuracy"] = accuracy
    summary["suspects"] = _write_suspects(results_path, outdir, result)
    if truth_path:
        from ..demo import demo_error, load_truth

        truth = load_truth(truth_path)
        if result.pts3d is not None:
            summary["error_vs_truth"] = demo_error(result.pts3d, truth["points3d"])
        if "refinement" in stage_files and "triangulation" in stage_files:
            from ..results import read_stage

            tri3d = read_stage(stage_files["triangulation"], "triangulation")["points3d"]
            summary["error_vs_truth_triangulation"] = demo_error(tri3d, truth["points3d"])
    summary["params_sha256"] = {
        **meta.get("upstream_params_sha256", {}),
        "assemble": meta["params_sha256"],
    }
    _write_json(outdir / "summary.json", summary)
    if snapshot is not None:
        write_snapshot(snapshot, snapshot_path)
    return summary


def write_snapshot(text: str, path: str | Path) -> Path:
    """Write a config's text (:meth:`~flylib.config.Config.snapshot_text`) to ``path``
    atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(text.encode("utf-8"))
    return Path(path)


def _summary(result, stage_files, recording_dir, outdir, version) -> dict:
    pts2d = np.asarray(result.pts2d, float)
    summary: dict[str, Any] = {
        "recording": str(recording_dir) if recording_dir else None,
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
    """The truth-free accuracy (:mod:`flylib.accuracy`) the 3D stages recorded:
    refinement's (triangulation, refinement as solved, and the output side by side)
    when it ran, else triangulation's (``output`` is then the triangulation)."""
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
    """``suspects.csv`` (see :mod:`flylib.suspects`); returns their number (``None``
    and a header-only file when the result holds no 3D)."""
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


def run_visualization(
    config,
    results_path: str | Path,
    recording_dir: str | Path,
    outdir: str | Path,
    *,
    progress: bool = False,
    speed: float | None = None,
) -> list[Path]:
    """Render the configured videos of one recording into ``outdir`` (points a person
    corrected, ``triangulation/corrected`` in results.h5, are ringed; ``speed``: a
    multiple of the recording's rate when the config sets none, the demo's slow motion)."""
    from ..config.sources import footage_globs
    from ..corrections import read_corrected
    from ..interop.views import footage_files
    from ..results import PoseResult
    from ..visualization import render_videos

    config = StageConfig.for_stage(config, "visualization")
    result = PoseResult.load(results_path)
    footage = footage_files(footage_globs(config), Path(recording_dir))
    return render_videos(
        config,
        result,
        footage,
        outdir,
        progress=progress,
        corrected=read_corrected(results_path),
        speed=speed,
    )
