"""Everything the workflow can check before it builds its DAG, beyond each key on its own
(:func:`flylib.config.validate_config`): the rig, imports and their files, the detection plan and
its weights, footage, a DeepFly3D calibration's handedness, and outputs that would land on inputs
(:mod:`flylib.pipeline.user_files`). One ``"<key>: <problem; fix>"`` line each; the workflow names
the user's file that set the key (:meth:`flylib.config.layers.ConfigLayers.report`).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..errors import FlylibError


def _problem(exc: FlylibError, prefix: str | None = None) -> str:
    text = " ".join(str(exc).split())
    return f"{prefix}: {text}" if prefix else text


def preflight_problems(
    config: Any,
    recordings: Iterable[Any],
    flags: dict[str, bool],
    *,
    check_weights: bool = True,
    import_files: dict[str, tuple[Path, ...]] | None = None,
) -> list[str]:
    """Problems the planned run would hit inside a job, one line each, starting with its key.
    ``flags``: ``Config.stage_flags()``; ``check_weights``: every detector checkpoint cached or
    downloadable (may wait :data:`flylib.pose2d.published.PROBE_TIMEOUT_S`); ``import_files`` is
    filled with ``recording id -> its imported 2D's files`` (the workflow reads them once)."""
    recordings = list(recordings)
    problems: list[str] = []
    data = config.data

    if data.get("cameras") and any(k != "defaults" for k in data["cameras"]):
        from ..camera.rig import CameraGroup

        try:  # principal points default to the image centre: any size checks the rest
            CameraGroup.from_config(config, image_sizes={v: (2, 2) for v in config.view_names()})
        except FlylibError as exc:
            problems.append(_problem(exc))

    if flags.get("bundle_adjustment", True) and config.view_names():
        from ..bundle_adjustment.params import build_layout
        from ..camera.model import N_DIST_COEFFS

        ba = config.bundle_adjustment
        try:  # every distortion slot allowed: the job pads to the rig's own count
            build_layout(config.view_names(), N_DIST_COEFFS, ba.fixed, ba.shared)
        except FlylibError as exc:
            problems.append(_problem(exc))

    calibration = data.get("calibration")
    if isinstance(calibration, dict) and calibration.get("format") is not None:
        from ..interop.anipose import CALIBRATION_FORMATS

        if calibration["format"] not in CALIBRATION_FORMATS:
            problems.append(
                f"calibration.format: unknown format {calibration['format']!r}; "
                f"use one of {', '.join(CALIBRATION_FORMATS)}"
            )
    mirror = calibration.get("mirror", False) if isinstance(calibration, dict) else False
    if not isinstance(mirror, bool):
        problems.append(
            f"calibration.mirror: expected true or false, got {mirror!r} "
            "(true mirrors the calibration file's world; see docs/how-it-works/handedness.md)"
        )
    elif mirror and not {"file", "index"} & set(calibration):
        from ..handedness import MIRROR_OFF

        problems.append(
            "calibration.mirror: true mirrors a calibration file's world, but calibration names "
            f"no file (the rig is the cameras table); set {MIRROR_OFF}, or give calibration.file"
        )

    if any(rec.demo for rec in recordings):
        from ..demo import demo_settings

        try:
            demo_settings(config.data.get("demo"))
        except FlylibError as exc:
            problems.append(_problem(exc))

    found = {} if import_files is None else import_files
    if flags.get("pose2d", True):
        problems += _pose2d_problems(config, recordings, check_weights, found)
    # a mirror-image calibration (its first recording's), decided as `flylib init` does
    where = recordings[0].path if recordings else None
    if isinstance(calibration, dict) and "mirror" not in calibration:
        verdict = calibration_handedness(config, where)
        if verdict is not None and verdict.mirrored:
            from ..handedness import DOCS_PAGE
            from .planning import calibration_inputs

            key = "file" if "file" in calibration else "index"
            problems.append(
                f"calibration: {calibration_inputs(config, where)[-1]} is the mirror image of the "
                f"fly's world: {verdict.reason}; set calibration: {{{key}: {calibration[key]}, "
                f"mirror: true}}, or mirror: false to run it as it is ({DOCS_PAGE})"
            )

    if flags.get("visualization", True):
        from ..visualization.specs import video_specs

        try:
            video_specs(config)  # parsing is the check
        except FlylibError as exc:
            problems.append(_problem(exc))
    problems += path_problems(config, recordings)
    return list(dict.fromkeys(problems))


def calibration_handedness(config, recording_dir: Path | None = None):
    """:func:`flylib.handedness.rig_handedness` of the config's DeepFly3D calibration (for
    ``recording_dir``) against its ``cameras``; ``None`` for another rig or one not built."""
    from ..camera.rig import CameraGroup
    from ..handedness import rig_handedness
    from .planning import config_rig

    calibration = config.data.get("calibration") or {}
    pkl = str(calibration.get("file")).lower().endswith((".pkl", ".pickle"))
    if (calibration.get("format") or ("deepfly3d" if pkl else "")) != "deepfly3d":
        return None
    try:
        typed = CameraGroup.from_config(config, {v: (2, 2) for v in config.view_names()})
        return rig_handedness(config_rig(config, recording_dir=recording_dir), typed)
    except FlylibError:
        return None


# A Snakemake wildcard: "{name}" or "{name,constraint}". Snakemake has no escape for braces in
# a file path (input functions' paths are formatted too), so such a path cannot be a rule's.
_WILDCARD = re.compile(r"\{\s*[.\w]+\s*[,}]")


def path_problems(config: Any, recordings: Iterable[Any]) -> list[str]:
    """Paths of the planned run no job could use, one ``"<key>: <path>: <problem>; <fix>"``
    line each: a brace group Snakemake reads as a wildcard (``fly{1}``) in a recording's
    folder, footage, calibration or outdir, and each :func:`outdir_problem`."""
    from .planning import calibration_inputs

    problems: list[str] = []
    for rec in recordings:
        where = rec.extra.get("where", "recordings")
        try:
            calibration = calibration_inputs(config, rec.path)
        except FlylibError:
            calibration = []  # the rig's own check names it
        named = [
            (where, rec.path, "the recording folder"),
            *((where, f, "a footage file") for f in rec.footage),
            *(("calibration", f, "the calibration file") for f in calibration),
            ("outdir", rec.outdir, "the output folder"),
        ]
        for key, path, what in named:
            match = _WILDCARD.search(str(path))
            if match:
                problems.append(
                    f"{key}: {path}: {what}'s path holds {match.group(0).rstrip(',')}"
                    f"{'' if match.group(0).endswith('}') else '...}'}, which Snakemake reads "
                    "as a wildcard in a file path (there is no escape for it); rename it "
                    "without braces, e.g. ( ) or _"
                )
                break  # the folder's name, not each file under it
        problem = outdir_problem(rec.outdir)
        if problem:
            problems.append(f"outdir: {problem}")
    return problems


def outdir_problem(outdir: str | Path) -> str | None:
    """Why ``outdir`` cannot hold a run's outputs (``"<outdir>: <problem>; <fix>"``), or
    ``None``: each name must fit its filesystem's limit, and the folder (or its nearest
    existing parent) must be a writable folder."""
    outdir = Path(os.path.abspath(outdir))
    existing = outdir
    while not os.path.lexists(existing) and existing != existing.parent:
        existing = existing.parent
    try:
        limit = os.pathconf(existing if existing.is_dir() else existing.parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for name in outdir.parts[1:]:
        if len(os.fsencode(name)) > limit:
            return (
                f"{outdir}: the folder name {name[:40]}... is {len(os.fsencode(name))} bytes, "
                f"longer than its filesystem allows ({limit}); choose a shorter outdir "
                "(e.g. outdir: results/{id})"
            )
    if not existing.is_dir():
        return f"{outdir}: {existing} is a file, not a folder; choose another outdir"
    if not os.access(existing, os.W_OK | os.X_OK):
        try:
            read_only = bool(os.statvfs(existing).f_flag & os.ST_RDONLY)
        except OSError:
            read_only = False
        why = "is on a read-only filesystem" if read_only else "is not writable by you"
        action = "write into" if existing == outdir else "create the output folder in"
        return f"{outdir}: cannot {action} {existing}: it {why}; set outdir to a writable folder"
    return None


def load_run_config(layers: Any, *, check_frames: bool = True) -> tuple[Any, list[Any]]:
    """Validate a run's config and plan its recordings, as the workflow does before its DAG:
    the :class:`flylib.config.Config` (``text``: the one file's, or the merged layers as YAML) and
    the recordings, else a ConfigError naming each problem's file. ``check_frames``: footage frame
    counts and detector checkpoints (off in a cluster job: checked already; maybe no network)."""
    import yaml

    from ..config import Config, validate_config
    from ..errors import ConfigError
    from .planning import plan_recordings

    problems = validate_config(layers.data)
    if problems:
        raise ConfigError(layers.report(problems))
    text = layers.single_text()
    if text is None:
        text = yaml.safe_dump(layers.data, sort_keys=False, default_flow_style=None)
    try:
        config = Config(layers.data, text=text, format="yaml")
        recordings = plan_recordings(
            config, check_frames=check_frames, config_dir=layers.config_dir("recordings")
        )
        found: dict[str, tuple[Path, ...]] = {}
        problems = preflight_problems(
            config,
            recordings,
            config.stage_flags(),
            check_weights=check_frames,
            import_files=found,
        )
        # the import files, found once, for the output check and the pose2d rule's inputs
        recordings = [
            replace(rec, import_files=found[rec.id]) if rec.id in found else rec
            for rec in recordings
        ]
        if check_frames and not problems:  # the main process, every path usable
            from .user_files import output_problems

            problems += output_problems(config, recordings, layers.texts)
            problems += session_problems(config, recordings)
    except FlylibError as exc:
        problems = [" ".join(str(exc).split())]
    if problems:
        raise ConfigError(layers.report(problems))
    return config, recordings


def session_problems(config: Any, recordings: list[Any]) -> list[str]:
    """A session whose recordings' frames differ in size (a session is one rig), one line each;
    the sizes pose2d will give: each view's footage header, else ``image_size``."""
    from ..interop.views import read_frame_size
    from ..sessions import plan_sessions
    from .pose2d import import_target

    if not (config.stage_flags()["bundle_adjustment"] and config.bundle_adjustment.session):
        return []
    try:
        sessions = plan_sessions(recordings)
    except FlylibError:
        return []  # RunPlan names it
    target = import_target(config)

    def sizes(rec) -> dict[str, tuple[int, ...]]:
        footage = target.footage(Path(rec.path))
        fallback = (rec.import_spec or {}).get("image_size")
        found = {
            v: read_frame_size(footage[v][0]) if footage.get(v) else fallback for v in target.views
        }
        return {v: tuple(map(int, size)) for v, size in found.items() if size is not None}

    def wxh(size: dict) -> str:
        return "/".join(dict.fromkeys(f"{w}x{h}" for h, w in size.values()))

    problems = []
    for session in sessions:
        first, *rest = session.members
        own = sizes(first)
        for rec in rest:
            other = sizes(rec)
            if any(other[v] != own[v] for v in other.keys() & own.keys()):
                problems.append(
                    f"{rec.extra.get('where', 'recordings')}: session {session.name!r} is one "
                    f"rig, but {first.id}'s frames are {wxh(own)} and {rec.id}'s {wxh(other)} "
                    f"(width x height); give {rec.id} another session (its session key or "
                    "sheet column), or footage of one size"
                )
                break
    return problems


def _pose2d_problems(
    config: Any,
    recordings: list[Any],
    check_weights: bool,
    resolved: dict[str, tuple[Path, ...]],
) -> list[str]:
    from ..interop import import_spec
    from ..interop.importer import footage_problem
    from ..pose2d.published import checkpoint_problem
    from ..recordings import find_recording
    from .pose2d import Pose2dInputs, import_inputs, import_target

    problems: list[str] = []
    detector = []
    target = None
    for rec in recordings:
        if rec.import_spec is None:
            if not rec.demo:
                detector.append(rec)
            continue
        own = rec.extra.get("own_import") and not rec.demo
        where = f"{rec.extra.get('where', 'recordings')}.import" if own else None
        try:
            spec = import_spec(rec.import_spec)
            if not rec.demo:  # the demo's files are written by its own rule
                target = target or import_target(config)
                resolved[rec.id] = tuple(import_inputs(target, rec.import_spec, rec.path))
                problem = footage_problem(target, spec, rec.path)
                if problem is not None:
                    problems.append(f"{where or 'pose2d.import'}: {problem}")
        except FlylibError as exc:
            text = _problem(exc)
            if not text.startswith("pose2d.import"):
                text = f"pose2d.import.files: {text}"
            if where:
                text = text.replace("pose2d.import", where)
            problems.append(text)
        if not rec.demo and not rec.sources:
            # kept without footage; what it has must still be footage (not a pipe, a device,
            # an image sequence with a gap)
            try:
                (target or import_target(config)).footage(rec.path)
            except FlylibError as exc:
                problems.append(f"{rec.extra.get('where', 'recordings')}: {_problem(exc)}")
    if not detector:
        return problems

    try:
        plan = Pose2dInputs.from_config(config).detection_plan()
    except FlylibError as exc:
        return [*problems, _problem(exc)]
    own_weights = (config.data.get("pose2d") or {}).get("weights") or {}
    used = dict.fromkeys(p.model for p in plan.active_pathways()) if check_weights else {}
    for name in used:
        key = f"pose2d.weights.{name}" if name in own_weights else f"pose2d.models.{name}.weights"
        problem = checkpoint_problem(plan.models[name], key)
        if problem:
            problems.append(problem)
    for rec in detector:
        if rec.sources:
            continue
        where = rec.extra.get("where", "recordings")
        try:
            find_recording(rec.path, config.source_patterns(), check_frames=False, strict=True)
        except FlylibError as exc:
            problems.append(
                f"{where}: {_problem(exc)}; or read 2D from another tool with pose2d.import"
            )
    return problems
