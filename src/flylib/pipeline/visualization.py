"""The visualization stage: the configured overlay videos of one recording, drawn over its
footage from ``results.h5``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..stages import Stage
from .inputs import SkeletonSpec, StageInputs, register

RECORD = Stage("visualization", default_on=True, after=("neuromechfly",))


@dataclass(frozen=True)
class VisualizationRuntime:
    """Untracked by design: each fixes the 2D the result was made from, so pose2d's params
    track it and a change re-runs everything after (this stage included). ``footage``:
    ``(view, glob)`` per view in order, the glob of the source feeding it (``None``: none);
    ``on_corrupt_frame``: ``"error"`` or ``"missing"`` (a corrupt image drawn as background)."""

    footage: tuple[tuple[str, str | None], ...] = ()
    on_corrupt_frame: str = "error"

    @classmethod
    def from_config(cls, config) -> VisualizationRuntime:
        """Where ``config`` finds each view's footage, and its ``io.on_corrupt_frame``."""
        return cls(footage=footage_globs(config), on_corrupt_frame=config.io.on_corrupt_frame)


@register
@dataclass(frozen=True)
class VisualizationInputs(StageInputs):
    """The visualization stage's inputs: the ``visualization`` table and the skeleton's
    ``limb_palette``; ``runtime`` is tracked by pose2d's params instead."""

    STAGE = RECORD.name

    visualization: Mapping[str, Any]
    palette: Mapping[str, str]
    runtime: VisualizationRuntime = VisualizationRuntime()

    @classmethod
    def from_config(cls, config) -> VisualizationInputs:
        """The config's ``visualization`` table, palette and footage lookup."""
        return cls(
            visualization=dict(config.visualization),
            palette=SkeletonSpec.from_config(config, palette=True).palette,
            runtime=VisualizationRuntime.from_config(config),
        )


def footage_globs(config) -> tuple[tuple[str, str | None], ...]:
    """:func:`flylib.config.sources.footage_globs` as a frozen ``(view, glob)`` tuple."""
    from ..config.sources import footage_globs as view_globs

    return tuple(view_globs(config).items())


def run_visualization(
    inputs: VisualizationInputs,
    results_path: str | Path,
    recording_dir: str | Path,
    outdir: str | Path,
    *,
    progress: bool = False,
    speed: float | None = None,
) -> list[Path]:
    """Render one recording's configured videos as ``<outdir>/<video_name>.mp4`` (returned in
    config order); corrected points are ringed. ``speed``: a multiple of the recording's rate
    when the config sets none (the demo's slow motion)."""
    from ..corrections import read_corrected
    from ..interop.views import footage_files
    from ..results import PoseResult
    from ..visualization import render_videos

    result = PoseResult.load(results_path)
    return render_videos(
        inputs.visualization,
        result,
        footage_files(inputs.runtime.footage, Path(recording_dir)),
        outdir,
        progress=progress,
        corrected=read_corrected(results_path),
        speed=speed,
        on_corrupt=inputs.runtime.on_corrupt_frame,
    )
