"""The unknowns of a flattened problem beyond the cameras: shared 3D points, bone rows.

A column of the observations is one (frame, point); columns sharing an id are one 3D unknown
(a rigid point seen in every frame). Bone rows ``(i, j, target[, group])`` join two columns;
a group (a bone in every frame, or its left/right pair) has one unknown length."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int

__all__ = [
    "bones_on_unknowns",
    "lengths_per_row",
    "start_lengths",
    "unknowns_from_columns",
    "valid_bones",
]


def unknowns_from_columns(
    cols: Float[np.ndarray, "N 3"], ids: Int[np.ndarray, " N"], n_unknown: int
) -> Float[np.ndarray, "U 3"]:
    """Per-unknown start: the column's point, or the median over the columns sharing it."""
    pts = np.full((n_unknown, 3), np.nan)
    pts[ids] = cols
    shared = np.flatnonzero(np.bincount(ids, minlength=n_unknown) > 1)
    for u in shared:
        rows = cols[ids == u]
        rows = rows[np.isfinite(rows).all(axis=1)]
        pts[u] = np.median(rows, axis=0) if len(rows) else np.nan
    return pts


def bones_on_unknowns(bones, ids):
    """Bone rows re-indexed onto the 3D unknowns. A pair of rigid points keeps one row per
    frame (not one in all), so a length weighs the same whether or not the body was found
    still; rows whose ends became one unknown are dropped."""
    bi, bj, bt, bg = bones
    if bi.size == 0:
        return bi, bj, bt, bg
    ui, uj = ids[bi], ids[bj]
    ok = ui != uj
    return ui[ok], uj[ok], bt[ok], None if bg is None else bg[ok]


def lengths_per_row(problem, x, bone_i, bone_j, bone_t, bone_g, keep, previous):
    """Each bone row's current length (the fitted unknown), to restart the next round."""
    if bone_g is None or not problem.n_len or bone_i.size == 0:
        return previous
    ok = keep[bone_i] & keep[bone_j]
    fitted = x[problem.n_cam + 3 * problem.n_points :]
    out = (bone_t if previous is None else previous).copy()
    _, group_compact = np.unique(bone_g[ok], return_inverse=True)
    out[ok] = fitted[group_compact]
    return out


def start_lengths(pts, bone_i, bone_j, target, group):
    """Each row's group median of the starting 3D lengths (the target where none)."""
    length = np.linalg.norm(pts[bone_i] - pts[bone_j], axis=1)
    out = target.copy()
    for g in np.unique(group):
        rows = group == g
        ok = rows & np.isfinite(length) & (length > 0)
        if ok.any():
            out[rows] = np.median(length[ok])
    return out


def valid_bones(bones):
    if bones is None:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), None
    i, j, t = (np.asarray(a) for a in bones[:3])
    group = np.asarray(bones[3]).astype(int) if len(bones) > 3 and bones[3] is not None else None
    ok = np.isfinite(t) & (t > 0)
    return (
        i[ok].astype(int),
        j[ok].astype(int),
        t[ok].astype(float),
        None if group is None else group[ok],
    )
