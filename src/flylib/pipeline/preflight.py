"""Everything the workflow can check before it builds its DAG.

:func:`flylib.config.validate_config` checks each key on its own; this module checks
what needs the whole config or the planned recordings, and would otherwise fail
minutes or hours later inside a job: the camera rig, bundle adjustment's ``fixed`` /
``shared`` references, each recording's 2D-import spec and the files it names,
the detection plan and its weights (only where the detector runs), the output videos,
the calibration format, and footage for recordings the detector must read. Every
problem is one ``"<key>: <what is wrong; the fix>"`` line; the workflow names the
user's file that set the key (:meth:`flylib.config.layers.ConfigLayers.report`).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from ..errors import FlylibError


def _problem(exc: FlylibError, prefix: str | None = None) -> str:
    text = " ".join(str(exc).split())
    return f"{prefix}: {text}" if prefix else text


def preflight_problems(
    config: Any, recordings: Iterable[Any], flags: dict[str, bool], *, check_weights: bool = True
) -> list[str]:
    """Problems the planned run would hit inside a job, found from the config alone.

    Parameters
    ----------
    config
        The validated :class:`flylib.config.Config`.
    recordings
        The planned :class:`flylib.recordings.Recording` objects.
    flags
        ``Config.stage_flags()``.
    check_weights
        Check that every detector model's checkpoint is cached or downloadable (may
        wait :data:`flylib.pose2d.published.PROBE_TIMEOUT_S` for the weights host).

    Returns
    -------
    list of str
        One line per problem, each starting with the config key it concerns.
    """
    recordings = list(recordings)
    problems: list[str] = []
    data = config.data

    if data.get("cameras") and any(k != "defaults" for k in data["cameras"]):
        try:  # principal points default to the image centre: any size checks the rest
            config.camera_group(image_sizes={v: (2, 2) for v in config.view_names()})
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

    if any(rec.demo for rec in recordings):
        from ..demo import demo_settings

        try:
            demo_settings(config.data.get("demo"))
        except FlylibError as exc:
            problems.append(_problem(exc))

    if flags.get("pose2d", True):
        problems += _pose2d_problems(config, recordings, check_weights)

    if flags.get("visualization", True):
        try:
            config.videos  # noqa: B018 -- parsing is the check
        except FlylibError as exc:
            problems.append(_problem(exc))
    return list(dict.fromkeys(problems))


def load_run_config(layers: Any, *, check_frames: bool = True) -> tuple[Any, list[Any]]:
    """Validate a run's config and plan its recordings, as the workflow does before its DAG.

    Parameters
    ----------
    layers
        The run's :class:`flylib.config.layers.ConfigLayers`.
    check_frames
        Compare footage frame counts across cameras while planning, and check the
        detector's checkpoints (off in a cluster job re-reading the config: the run's
        main process checked both, and a compute node may have no network).

    Returns
    -------
    config, recordings
        The :class:`flylib.config.Config` (its ``text``: the one file's exact text, or a
        YAML dump of the merged layers) and the planned recordings.

    Raises
    ------
    ConfigError
        Every problem, one line each, naming the user's file that set the key.
    """
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
        recordings = plan_recordings(config, check_frames=check_frames)
        problems = preflight_problems(
            config, recordings, config.stage_flags(), check_weights=check_frames
        )
    except FlylibError as exc:
        problems = [" ".join(str(exc).split())]
    if problems:
        raise ConfigError(layers.report(problems))
    return config, recordings


def _pose2d_problems(config: Any, recordings: list[Any], check_weights: bool) -> list[str]:
    from ..interop import import_spec
    from ..interop.importer import import_files
    from ..pose2d.published import checkpoint_problem
    from ..recordings import find_recording
    from .pose2d import import_target

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
                import_files(target, spec, rec.path)
        except FlylibError as exc:
            text = _problem(exc)
            if not text.startswith("pose2d.import"):
                text = f"pose2d.import.files: {text}"
            if where:
                text = text.replace("pose2d.import", where)
            problems.append(text)
        if not rec.demo and not rec.sources:
            # planning kept it without footage; what it has (frame sizes and counts)
            # must still be footage: a pipe, a device, a gap in an image sequence
            try:
                (target or import_target(config)).footage(rec.path)
            except FlylibError as exc:
                problems.append(f"{rec.extra.get('where', 'recordings')}: {_problem(exc)}")
    if not detector:
        return problems

    try:
        plan = config.detection_plan()
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
