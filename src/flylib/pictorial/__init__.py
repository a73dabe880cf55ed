"""Pictorial structures: recover joints whose detector arg-max landed on the wrong peak.

Where RANSAC triangulation can only veto a bad detection, this stage reconsiders the detector's
top-K heatmap peaks per (view, point) (DeepFly3D, Gunel et al. 2019):

1. :mod:`.peaks`: :func:`peak_candidates` turns heatmaps into the top-K local maxima with sub-pixel
   refinement (the detector calls it; :class:`Candidates` holds them in raw pixels).
2. :mod:`.hypotheses`: per joint and frame, every pair of candidate peaks (the ``SEED_K``
   strongest per view) from two views is triangulated; each view then contributes its strongest
   candidate within ``inlier_px`` of the hypothesis' reprojection, the hypothesis is refitted from
   those inliers and its evidence is the summed peak score. Hypotheses with the same inlier set are
   merged, the rest thinned by non-maximum suppression at a fraction of the bone scale, and the
   ``max_hyp`` strongest kept.
3. :mod:`.chains`: one hypothesis (or none) per joint is chosen by exact dynamic programming along
   each limb chain: unary ``-evidence`` (with ``temporal``, plus ``mu * (jump / scale)^2`` against
   the previous frame) and a Huber bone-length term ``lam * huber((|Xi - Xj| - L_ij) / scale) /
   huber`` between neighbouring joints.

Geometry runs in NumPy on undistorted, intrinsics-free coordinates of the rig; every step is
vectorized over frames and joints, only the optional temporal DP walks frames. :mod:`.solver` runs
the steps per frame and over a sequence."""

from .chains import bone_length_targets, skeleton_chains
from .hypotheses import DEFAULT_INLIER_PX, DEFAULT_MAX_HYP, DEFAULT_NMS, SEED_K
from .peaks import (
    DEFAULT_K,
    DEFAULT_PEAK_RADIUS,
    DEFAULT_PEAK_THRESHOLD,
    DEFAULT_SUBPIXEL,
    SUBPIXEL_METHODS,
    Candidates,
    peak_candidates,
)
from .solver import (
    DEFAULT_HUBER,
    DEFAULT_LAMBDA,
    DEFAULT_MU,
    reconstruct,
    solve_frame,
    solve_frames,
)

__all__ = [
    "Candidates",
    "bone_length_targets",
    "peak_candidates",
    "reconstruct",
    "skeleton_chains",
    "solve_frame",
    "solve_frames",
    "DEFAULT_HUBER",
    "DEFAULT_INLIER_PX",
    "DEFAULT_K",
    "DEFAULT_LAMBDA",
    "DEFAULT_MAX_HYP",
    "DEFAULT_MU",
    "DEFAULT_NMS",
    "DEFAULT_PEAK_RADIUS",
    "DEFAULT_PEAK_THRESHOLD",
    "DEFAULT_SUBPIXEL",
    "SEED_K",
    "SUBPIXEL_METHODS",
]
