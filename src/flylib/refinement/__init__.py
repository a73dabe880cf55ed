"""Spatiotemporal 3D refinement: every frame at once, robust reprojection, smoothness,
bone-length constancy and a rigid (tethered) body.

:func:`refine_points` works on arrays and takes the ``refinement`` table's params
(:class:`~flylib.config.postprocessing.RefinementParams`); :func:`skeleton_terms` makes its
skeleton arguments; :mod:`flylib.refinement.held_out` keeps a recording from getting worse by the
held-out-view yardstick; :mod:`flylib.pipeline.refinement` is the stage (``stages/refinement.h5``).
"""

from .objective import LOSSES, BlockLayout, chunk_kernel, difference_gram
from .setup import default_rigid_points, mirror_bones, skeleton_terms
from .solver import (
    FLAG_BITS,
    RefinementResult,
    bone_lengths,
    refine_points,
    rigid_centres,
)

__all__ = [
    "FLAG_BITS",
    "LOSSES",
    "BlockLayout",
    "RefinementResult",
    "bone_lengths",
    "chunk_kernel",
    "default_rigid_points",
    "difference_gram",
    "mirror_bones",
    "refine_points",
    "rigid_centres",
    "skeleton_terms",
]
