"""Visualization: pose-overlay videos composed from panels (:func:`read_video_specs`,
:func:`render_videos`), and the per-recording summary PNG (:func:`summary_figure`)."""

import lazy_loader as _lazy

# Names and modules are listed in ``__init__.pyi``: OpenCV loads with the compositor, not with
# the summary figure (assemble) or the video specs (planning).
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
