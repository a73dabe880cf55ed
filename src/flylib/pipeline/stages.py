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
from pathlib import Path

import numpy as np

from ..errors import FlylibError, ResultsError, StageError, one_line
from ..interop.anipose import config_rig

# the stages with their own home, importable from here as before
from .assemble import run_assemble, write_snapshot  # noqa: F401
from .demo import run_demo  # noqa: F401
from .tracked import StageConfig, UntrackedConfigRead
from .visualization import run_visualization  # noqa: F401

log = logging.getLogger(__name__)


# -- helpers -------------------------------------------------------------------


def _image_sizes(pose2d) -> dict[str, tuple[int, int]]:
    return {str(k): (int(v[0]), int(v[1])) for k, v in (pose2d.image_sizes or {}).items()}


# Imported 2D may stray a little past the frame (a detector's edge peaks, sub-pixel
# refinement); this much of a view's points beyond its frame by more than this fraction
# of its size says the 2D was made on footage of another resolution.
_OUTSIDE_MARGIN = 0.02
_OUTSIDE_FRACTION = 0.01


def _check_inside_frames(pose2d, recording_dir: Path) -> None:
    """Refuse imported 2D whose points lie outside the footage they claim to be on.

    Raises
    ------
    FootageError
        Naming the view, its footage size and the extent of its points.
    """
    from ..errors import FootageError

    sizes = _image_sizes(pose2d)
    for v, view in enumerate(pose2d.view_names):
        if view not in sizes:
            continue
        height, width = sizes[view]
        xy = pose2d.pts2d[v].reshape(-1, 2)
        xy = xy[np.isfinite(xy).all(axis=1)]
        if not len(xy):
            continue
        limit = np.array([width, height], dtype=np.float64)
        outside = ((xy < -_OUTSIDE_MARGIN * limit) | (xy > (1 + _OUTSIDE_MARGIN) * limit)).any(
            axis=1
        )
        if outside.mean() > _OUTSIDE_FRACTION:
            top = np.max(xy, axis=0)
            raise FootageError(
                f"{recording_dir}: camera {view}: footage is {width}x{height} px but "
                f"{outside.mean():.0%} of its imported 2D lies outside that frame (up to "
                f"x={top[0]:.0f}, y={top[1]:.0f}); the 2D was made on footage of another size: "
                "use the footage it was made on, or re-run the 2D tool on this footage"
            )


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


def run_pose2d(
    config,
    recording_dir: str | Path,
    out_path: str | Path,
    *,
    import_spec: Mapping | None = None,
    progress: bool = False,
    candidates_path: str | Path | None = None,
) -> Path:
    """2D keypoints of one recording: the detector over its footage, or another
    tool's files when an import spec is in force (``import_spec``, else
    ``pose2d.import``).

    With ``candidates_path`` (pictorial structures on) the detector's top-K peaks
    (``pictorial_structures.k``) are written there too, as a ``candidates`` stage.

    Raises
    ------
    FootageError
        The recording's footage is missing, unreadable or inconsistent (naming it).
    ResultsError
        If candidates are asked for but the 2D is imported (other tools keep no peaks).
    """
    config = StageConfig.for_stage(config, "pose2d")
    recording_dir = Path(recording_dir)
    spec = dict(import_spec) if import_spec else config.import_spec
    if spec:
        if candidates_path is not None:
            raise ResultsError(
                f"{recording_dir}: pictorial structures needs the detector's candidate peaks, "
                f"but this recording's 2D is imported ({spec.get('format', 'another tool')}), "
                "which keeps none; set pipeline.do_pictorial_structures: false"
            )
        from ..interop import import_points2d

        data = import_points2d(config, recording_dir, spec)
        _check_inside_frames(data, recording_dir)
    else:
        from ..pose2d import detect_recording
        from ..recordings import find_recording

        sources = find_recording(recording_dir, config, strict=True)
        data = detect_recording(
            config, sources, want_candidates=candidates_path is not None, progress=progress
        )
    from ..provenance import stage_provenance

    provenance = stage_provenance(config, "pose2d")
    candidates, data.candidates = data.candidates, None
    if candidates is not None:
        from ..results import save_candidates

        save_candidates(
            candidates_path, candidates, meta={**provenance, "k": int(config.pictorial.k)}
        )
    data.save(out_path, config.skeleton(), meta=provenance)
    return Path(out_path)


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
