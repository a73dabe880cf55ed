"""Spatiotemporal 3D refinement: every frame at once, robust reprojection, smoothness,
bone-length constancy and a rigid (tethered) body.

:func:`refine_points` works on arrays; :func:`refine_from_config` reads the config's
``refinement`` table and the skeleton; :mod:`flylib.refinement.stage` is the workflow
stage (``stages/refinement.h5``).
"""

from .objective import LOSSES, BlockLayout, chunk_kernel, difference_gram
from .setup import (
    default_rigid_points,
    mirror_bones,
    refine_from_config,
    skeleton_terms,
)
from .solver import (
    FLAG_BITS,
    RefinementResult,
    RefineOptions,
    bone_lengths,
    refine_points,
    rigid_centres,
)

__all__ = [
    "FLAG_BITS",
    "LOSSES",
    "BlockLayout",
    "RefineOptions",
    "RefinementResult",
    "bone_lengths",
    "chunk_kernel",
    "default_rigid_points",
    "difference_gram",
    "mirror_bones",
    "refine_from_config",
    "refine_points",
    "rigid_centres",
    "skeleton_terms",
]
