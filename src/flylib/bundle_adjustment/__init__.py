"""Bundle adjustment: refine the camera rig against the fly's own detected joints.

Modules
-------
adjust
    :func:`bundle_adjust` on one flattened problem (outlier rounds, distortion policy).
messages
    Its warnings in plain words (the poorly-determined rig, moved cameras), the logged
    summary and the ``report``.
sequence
    :func:`bundle_adjust_sequence` on a recording's ``(V, T, P, 2)`` detections (frames,
    bone lengths, rigid points).
unknowns
    Shared 3D unknowns (rigid points) and bone rows of a flattened problem.
params
    The ``fixed`` / ``shared`` parameter grammar.
sampling
    ``frame_sampling``: which frames the fit uses (one recording's, or a session's).
problem
    Residuals, the JAX Jacobian as a sparse matrix, the ``scipy`` path.
lm
    Levenberg-Marquardt on the reduced camera system (Schur complement).
reseed
    PnP re-seeding of grossly-off cameras, the radial-fold check.
gauge
    The similarity gauge held during a fit and the frame the result is reported in.
"""

from .adjust import bundle_adjust, camera_table
from .sampling import FRAME_SAMPLING, select_frames, select_session_frames
from .sequence import bundle_adjust_sequence

__all__ = [
    "FRAME_SAMPLING",
    "bundle_adjust",
    "bundle_adjust_sequence",
    "camera_table",
    "select_frames",
    "select_session_frames",
]
