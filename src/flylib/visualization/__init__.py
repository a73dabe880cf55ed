"""Visualization: pose-overlay videos composed from panels, and a static summary figure.

- :func:`read_video_specs` parses and validates ``[[visualization.videos]]``.
- :func:`render_videos` streams a recording through every video spec to MP4s.
- :func:`summary_figure` writes the per-recording summary PNG.
"""

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
