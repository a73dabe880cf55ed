"""The visualization stage: the configured overlay videos of one recording, drawn
over its footage from ``results.h5``.

:class:`VisualizationInputs` is what the stage reads: the ``visualization`` table and
the skeleton's palette (its tracked params), and, untracked by design, where each
view's footage is and what to do with a corrupt frame (see
:class:`VisualizationRuntime`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .inputs import SkeletonSpec, StageInputs, register


@dataclass(frozen=True)
class VisualizationRuntime:
    """What the visualization job reads that is not in its params, by design: each
    of these fixes the 2D the result was made from, so pose2d's params track it, and
    a change re-runs pose2d and, through its artifact, everything after it (this
    stage included).

    Attributes
    ----------
    footage
        ``(view, glob)`` per configured view, in view order: the glob of the source
        that feeds the view (``sources``, ``pose2d.pathways``,
        ``pose2d.output_points``), ``None`` for a view no source feeds.
    on_corrupt_frame
        ``io.on_corrupt_frame``: ``"error"`` or ``"missing"`` (a corrupt image is
        drawn as the background).
    """

    footage: tuple[tuple[str, str | None], ...] = ()
    on_corrupt_frame: str = "error"

    @classmethod
    def from_config(cls, config) -> VisualizationRuntime:
        """Where ``config`` finds each view's footage, and its ``io.on_corrupt_frame``."""
        return cls(footage=footage_globs(config), on_corrupt_frame=config.io.on_corrupt_frame)


@register
@dataclass(frozen=True)
class VisualizationInputs(StageInputs):
    """The visualization stage's inputs: the ``visualization`` table (parsed by
    :func:`flylib.visualization.read_video_specs`) and the skeleton's ``limb_palette``;
    ``runtime`` (:class:`VisualizationRuntime`) is tracked by pose2d's params instead."""

    STAGE = "visualization"

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
    """``(view, glob)`` per view ``config`` feeds from a footage source (``None``: a
    source without a pattern), in view order (:func:`flylib.config.sources.footage_globs`
    as a frozen tuple)."""
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
    """Render the configured videos of one recording (``results.h5`` over the footage in
    ``recording_dir``) as ``<outdir>/<video_name>.mp4``; returns them in config order.

    Points a person corrected (``triangulation/corrected`` in results.h5) are ringed.
    ``speed``: a multiple of the recording's rate when the config sets none (the demo's
    slow motion).
    """
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
