"""flylib.bundle_adjustment's names and the modules they come from.

``flylib/bundle_adjustment/__init__.py`` reads this file (``lazy_loader.attach_stub``)
and loads each module on first use of one of its names.
"""

from .adjust import bundle_adjust as bundle_adjust, camera_table as camera_table
from .sampling import (
    FRAME_SAMPLING as FRAME_SAMPLING,
    select_frames as select_frames,
    select_session_frames as select_session_frames,
)
from .sequence import bundle_adjust_sequence as bundle_adjust_sequence
