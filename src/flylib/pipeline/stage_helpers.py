"""What the stage homes share: the rig a stage after bundle adjustment runs on
(:func:`rig_for`, :func:`run_inputs`) and the boundary turning a numerical failure on a
recording's data into one line (:func:`solving`)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..errors import FlylibError, ResultsError, StageError, one_line
from ..stages import by_name

log = logging.getLogger(__name__)


def image_sizes(pose2d) -> dict[str, tuple[int, int]]:
    return {str(k): (int(v[0]), int(v[1])) for k, v in (pose2d.image_sizes or {}).items()}


@dataclass(frozen=True)
class RigRuntime:
    """Untracked part of a stage building the config rig: ``config_dir``, where a relative
    calibration path is looked up after the recording's folder (the config file's folder)."""

    config_dir: Path | None = None

    @classmethod
    def from_config(cls, config) -> RigRuntime:
        """The config file's folder (``None`` for a config made from a dict)."""
        return cls(config_dir=Path(config.source).parent if config.source else None)


def tracked_rig(config):
    """The config rig (a :class:`~flylib.pipeline.inputs.RigSpec`) a later stage tracks;
    ``None`` while bundle adjustment is on (the rig is in its artifact)."""
    from .inputs import RigSpec

    return None if config.stage_flags()["bundle_adjustment"] else RigSpec.from_config(config)


def rig_for(rig, pose2d, ba_path: str | Path | None, recording_dir=None, *, stage: str):
    """The bundle-adjusted rig when ``ba_path`` is given, else the config ``rig``
    (ResultsError when that is ``None`` too)."""
    if ba_path:
        from ..results import read_stage

        return read_stage(ba_path, "bundle_adjustment")["cameras"]
    if rig is None:
        raise ResultsError(
            f"{stage.replace('_', ' ')}: bundle adjustment is on, so the rig comes from its "
            "artifact, and none was given; pass it (--bundle-adjustment) or set "
            "pipeline.do_bundle_adjustment: false"
        )
    return rig.camera_group(image_sizes(pose2d), recording_dir)


def run_inputs(config, stage: str, ba_path: str | Path | None = None):
    """``stage``'s inputs with or without a bundle-adjustment artifact (``ba_path``); without
    one, the config rig even while bundle adjustment is on (so the params track it). For a
    stage script run by hand, and tests running a stage on its own."""
    from .inputs import stage_inputs

    return stage_inputs(_rig_source(config, ba_path), stage)


def _rig_source(config, ba_path):
    """``config``, with bundle adjustment off when no artifact is given (see :func:`run_inputs`)."""
    if ba_path or not config.stage_flags()["bundle_adjustment"]:
        return config
    data = dict(config.data)
    data["pipeline"] = {**(data.get("pipeline") or {}), "do_bundle_adjustment": False}
    return type(config)(data, text=config.text, source=config.source, format=config.format)


@contextmanager
def solving(stage: str, recording) -> Iterator[None]:
    """A numerical stage's boundary: any exception its solver raises on the recording's data
    (``LinAlgError``, overflow, NaNs, memory) becomes one :class:`StageError` line naming the
    recording and what to check (cause kept, traceback at DEBUG); flylib's own errors and
    ``OSError`` pass unchanged."""
    try:
        yield
    except (FlylibError, OSError):
        raise  # flylib's own lines; storage errors
    except Exception as exc:
        log.debug("%s failed on %s", stage, recording, exc_info=True)
        raise StageError(
            f"{recording}: {stage.replace('_', ' ')} failed on this recording's data "
            f"({type(exc).__name__}: {one_line(exc, 200) or 'no detail'}); {by_name(stage).hint}"
        ) from exc
