"""flylib.visualization's names and the modules they come from.

``flylib/visualization/__init__.py`` reads this file (``lazy_loader.attach_stub``) and
loads each module on first use of one of its names.
"""

from .compose import Compositor as Compositor, render_videos as render_videos
from .specs import (
    PanelSpec as PanelSpec,
    VideoSpec as VideoSpec,
    read_video_specs as read_video_specs,
    resolve_output_fps as resolve_output_fps,
)
from .summary import summary_figure as summary_figure
