"""Visualization: pose-overlay videos composed from panels (:func:`read_video_specs`,
:func:`render_videos`), and the per-recording summary PNG (:func:`summary_figure`)."""

from __future__ import annotations

from .compose import Compositor, render_videos
from .specs import PanelSpec, VideoSpec, read_video_specs, resolve_output_fps
from .summary import summary_figure

__all__ = [
    "Compositor",
    "PanelSpec",
    "VideoSpec",
    "read_video_specs",
    "render_videos",
    "resolve_output_fps",
    "summary_figure",
]
