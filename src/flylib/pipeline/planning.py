"""What a run plans from its config before any stage: the recordings it covers, the
params each stage's artifact should carry, and the config rig and its files.

The modules below the pipeline take these as typed values (a ``recordings`` listing
and ``sources`` list, a ``calibration`` table and views, a ``stage -> params``
lookup); this is where a :class:`~flylib.config.Config` is read for them.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from pathlib import Path

from ..config import Config
from ..recordings import Recording, plan_listing
from .demo import demo_import_spec
from .inputs import RigSpec, stage_params

__all__ = ["calibration_inputs", "config_rig", "params_of", "plan_recordings"]


def plan_recordings(
    config: Config, *, check_frames: bool = True, config_dir: Path | None = None
) -> list[Recording]:
    """The recordings a workflow run covers, from the config's ``recordings`` key
    (:func:`flylib.recordings.plan_listing` with the config's ``sources``,
    ``recursive``, ``outdir`` and ``pose2d.import``).

    Parameters
    ----------
    config
        The run config.
    check_frames
        Compare frame counts across sources while resolving.
    config_dir
        The folder of the config file that set ``recordings`` (for messages).

    Returns
    -------
    list of Recording
        As :func:`~flylib.recordings.plan_listing` (which names what it raises).
    """
    data = config.data
    return plan_listing(
        data.get("recordings"),
        data.get("sources"),
        recursive=bool(data.get("recursive", False)),
        outdir=data.get("outdir"),
        default_import=(data.get("pose2d") or {}).get("import"),
        demo_import=lambda: demo_import_spec(config),
        check_frames=check_frames,
        config_dir=config_dir,
    )


def params_of(config: Config, *, run_only: bool = False) -> Callable[[str], dict | None]:
    """``stage -> the params its rule tracks under config`` (each computed once), for
    :func:`flylib.provenance.provenance_report` and :func:`~flylib.provenance.foreign_artifacts`;
    ``session_calibration`` too (a session's rig, :mod:`flylib.sessions`).

    Parameters
    ----------
    config
        The config to compare artifacts with.
    run_only
        ``None`` for a stage the run does not write (``pipeline.do_<stage>`` off, or
        what it needs is off: :meth:`~flylib.config.Config.stage_flags`).
    """
    flags = config.stage_flags() if run_only else {}

    @functools.cache
    def lookup(stage: str) -> dict | None:
        if stage == "session_calibration":  # a session's rig (flylib.sessions)
            if not flags.get("bundle_adjustment", True):
                return None
            from .session_calibration import SessionCalibrationInputs

            return SessionCalibrationInputs.from_config(config).canonical_params()
        if not flags.get(stage, True):
            return None
        return stage_params(config, stage)

    return lookup


def config_rig(
    config: Config,
    image_sizes: Mapping[str, tuple[int, int]] | None = None,
    recording_dir: str | Path | None = None,
):
    """The rig the config describes: its ``calibration`` file when set, else the orbit
    parameters of ``cameras`` (principal points from ``image_sizes`` where not given);
    :meth:`RigSpec.camera_group` of the config's rig.
    """
    return RigSpec.from_config(config).camera_group(image_sizes, recording_dir)


def calibration_inputs(config: Config, recording_dir: str | Path | None = None) -> list[Path]:
    """The files the config's ``calibration`` table reads for one recording
    (:func:`flylib.interop.anipose.calibration_inputs` of the config's table)."""
    from ..interop.anipose import calibration_inputs as calibration_files

    rig = RigSpec.from_config(config)
    return calibration_files(
        rig.calibration, Path(recording_dir) if recording_dir else None, config_dir=rig.config_dir
    )
