"""What the images tie together: parts of a rig that share no view.

Two cameras are tied when they observe the same 3D unknowns; the cameras tied to one another,
directly or through others, and the points they see form one *part*. Images fix each part's
cameras and points only up to a similarity of their own (7 directions): with the front camera
blind on a DeepFly3D rig, the left and the right side are two parts, placed, turned and scaled
against each other by nothing in the images (a length joining two parts would place them,
unchecked by the data). So ``bundle_adjust`` uses no length row when the cameras form several
parts (:func:`crossing_bones`), holds one similarity per part during the fit and maps each part
back onto where the starting rig put it (:func:`align_parts`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components

from .gauge import align_gauge

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float, Int

__all__ = ["MIN_SHARED_POINTS", "align_parts", "camera_parts", "crossing_bones", "point_parts"]

#: two cameras are tied when both observe at least this many 3D unknowns (fewer cannot fix a
#: similarity between them, and a stray outlier must not tie two sides)
MIN_SHARED_POINTS = 3


def camera_parts(
    usable: Bool[np.ndarray, "V N"], ids: Int[np.ndarray, " N"], n_unknown: int
) -> Int[np.ndarray, " V"]:
    """Part label per camera ``(V,)``: ``0, 1, ...`` (ordered by first camera), ``-1`` for one
    that sees none of the points. ``usable`` ``(V, N)``: which observations exist; ``ids``
    ``(N,)``: the 3D unknown each column observes."""
    n_views = usable.shape[0]
    seen = np.zeros((n_views, n_unknown), bool)
    v, c = np.nonzero(usable)
    seen[v, ids[c]] = True
    counts = seen.astype(np.int64) @ seen.T.astype(np.int64)  # (V, V) shared unknowns
    observed = seen.any(axis=1)
    tie = (counts >= MIN_SHARED_POINTS) & observed[:, None] & observed[None, :]
    _, label = connected_components(scipy.sparse.csr_matrix(tie), directed=False)
    out = np.full(n_views, -1)
    order = {}
    for cam in np.flatnonzero(observed):
        out[cam] = order.setdefault(int(label[cam]), len(order))
    return out


def point_parts(
    usable: Bool[np.ndarray, "V N"],
    ids: Int[np.ndarray, " N"],
    n_unknown: int,
    cam_part: Int[np.ndarray, " V"],
) -> Int[np.ndarray, " U"]:
    """Part label per 3D unknown ``(U,)``: the part of the cameras that see it (the
    part seeing it most often when stray observations reach another), ``-1`` if unseen."""
    n_parts = int(cam_part.max()) + 1 if cam_part.size else 0
    votes = np.zeros((max(n_parts, 1), n_unknown))
    v, c = np.nonzero(usable & (cam_part >= 0)[:, None])
    np.add.at(votes, (cam_part[v], ids[c]), 1.0)
    out = np.argmax(votes, axis=0)
    out[votes.max(axis=0) == 0] = -1
    return out


def crossing_bones(
    bone_i: Int[np.ndarray, " B"],
    bone_j: Int[np.ndarray, " B"],
    pt_part: Int[np.ndarray, " U"],
) -> int:
    """How many bone rows ``(B,)`` join two parts (no image can check them)."""
    return int((pt_part[bone_i] != pt_part[bone_j]).sum())


def align_parts(
    table0: Float[np.ndarray, "V C"],
    table: Float[np.ndarray, "V C"],
    pts: Float[np.ndarray, "U 3"],
    pts0: Float[np.ndarray, "U 3"],
    cam_part: Int[np.ndarray, " V"],
    pt_part: Int[np.ndarray, " U"],
    movable: Bool[np.ndarray, " V"],
) -> tuple[Float[np.ndarray, "V C"], Float[np.ndarray, "U 3"]]:
    """Each part's cameras and points mapped by the similarity that puts its refined points back
    onto its starting ones (:func:`~flylib.bundle_adjustment.gauge.align_gauge`). A part with a
    camera whose extrinsics are not all ``movable`` ``(V,)`` is anchored: left as fitted."""
    table, pts = table.copy(), pts.copy()
    for part in range(int(cam_part.max()) + 1 if cam_part.size else 0):
        cams = cam_part == part
        if not movable[cams].all():
            continue
        mine = pt_part == part
        table[cams], pts[mine] = align_gauge(table0[cams], table[cams], pts[mine], pts0[mine])
    return table, pts
