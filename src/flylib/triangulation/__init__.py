"""Triangulation of whole recordings: DLT, exhaustive-pair RANSAC and greedy view dropping.

Every function takes the rig first, ``(cameras, pts2d, ...)``, view-leading ``(V, *pts, 2)``
pixels with NaN = missing, and returns ``(*pts, 3)``. :func:`reconstruct` runs the method a
``triangulation`` table names (its knobs, its confidence weighting) and returns the 3D, the
2D it was solved from and the errors. DLT: :meth:`flylib.camera.rig.CameraGroup.triangulate`."""

from __future__ import annotations

from .methods import (
    DEFAULT_CHUNK_POINTS,
    RANSAC_CHUNK_POINTS,
    reconstruct,
    reprojection_error,
    triangulate,
    triangulate_ransac,
)

__all__ = [
    "DEFAULT_CHUNK_POINTS",
    "RANSAC_CHUNK_POINTS",
    "reconstruct",
    "reprojection_error",
    "triangulate",
    "triangulate_ransac",
]
