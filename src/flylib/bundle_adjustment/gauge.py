"""The similarity gauge of bundle adjustment: what to hold during a fit, how to report.

With no extrinsic parameter fixed, a similarity of the whole scene (rotation, translation,
scale: 7 directions) changes no image. Levenberg-Marquardt converges only linearly along such
directions, so the fit holds one camera's pose and one translation entry (:func:`gauge_refs`);
afterwards the result is mapped into the similarity frame where the starting rig put the fly
(:func:`align_gauge`), independent of which were held. :func:`open_gauge_directions` counts
what held and tied entries leave open."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..alignment import similarity_transform
from ..camera.model import rmat_to_rvec_numpy, rvec_to_rmat_numpy

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float


def untied_extrinsics(layout) -> bool:
    ext = layout.var_index[:, :6].ravel()
    return np.unique(ext).size == ext.size


def gauge_refs(
    table: Float[np.ndarray, "V C"], names, observed: Bool[np.ndarray, " V"] | None = None
) -> list[str]:
    """References pinning the similarity gauge: the first observed camera's pose and, for scale,
    the translation entry that scaling moves most of the observed camera farthest from it."""
    seen = np.flatnonzero(np.ones(len(table), bool) if observed is None else observed)
    if seen.size == 0:
        return []
    rmats = rvec_to_rmat_numpy(table[:, 0:3])
    centres = -np.einsum("vji,vj->vi", rmats, table[:, 3:6])
    first = int(seen[0])
    far = int(seen[np.argmax(np.linalg.norm(centres[seen] - centres[first], axis=1))])
    refs = [f"{names[first]}.rvec", f"{names[first]}.tvec"]
    if far == first:
        return refs
    d_tvec = -rmats[far] @ (centres[far] - centres[first])
    return [*refs, f"{names[far]}.tvec[{int(np.argmax(np.abs(d_tvec)))}]"]


def _camera_anchors(table: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """``(2V, 3)``: each camera's centre, then the point ``depths[v]`` ahead on its axis."""
    rmats = rvec_to_rmat_numpy(table[:, 0:3])
    centres = -np.einsum("vji,vj->vi", rmats, table[:, 3:6])
    targets = centres + depths[:, None] * rmats[:, 2]
    return np.concatenate([centres, targets])


def align_gauge(
    table0: Float[np.ndarray, "V C"],
    table: Float[np.ndarray, "V C"],
    pts: Float[np.ndarray, "N 3"],
    pts0: Float[np.ndarray, "N 3"] | None = None,
) -> tuple[Float[np.ndarray, "V C"], Float[np.ndarray, "N 3"]]:
    """Map the refined rig + points ``(N, 3)`` into the similarity frame of the start. With ``pts0``
    (the starting points ``(N, 3)``, NaN where none): the similarity that best maps the refined
    points onto them (Umeyama, refitted without the 20 % worst), so the fly stays where the starting
    rig put it (points pin the frame far better than distant cameras). Else (or below four such
    points) the camera centres *and* viewing targets (a point at the initial camera distance on each
    optical axis): centres alone leave a near-gauge free (the fly moving sideways while every camera
    turns to follow). ``X' = s R X + t`` for points, and per camera ``R_c' = R_c R^T``,
    ``t_c' = s t_c - R_c' t`` (projections are unchanged)."""
    fitted = None
    if pts0 is not None:
        ok = np.isfinite(pts).all(axis=1) & np.isfinite(pts0).all(axis=1)
        if ok.sum() >= 4:
            fitted = similarity_transform(pts[ok], pts0[ok], keep=0.8, refits=1)
    if fitted is None and len(table) >= 2:
        depths = np.linalg.norm(table0[:, 3:6], axis=1)
        fitted = similarity_transform(
            _camera_anchors(table, depths), _camera_anchors(table0, depths)
        )
    if fitted is None:
        return table, pts
    scale, rot, shift = fitted
    return similarity_table(table, scale, rot, shift), (scale * pts @ rot.T + shift)


def similarity_table(
    table: np.ndarray, scale: float, rot: np.ndarray, shift: np.ndarray
) -> np.ndarray:
    """The camera table after mapping the world by ``X' = scale rot X + shift``."""
    out = table.copy()
    for v, rmat in enumerate(rvec_to_rmat_numpy(table[:, 0:3])):
        rc = rmat @ rot.T
        out[v, 0:3] = rmat_to_rvec_numpy(rc)
        out[v, 3:6] = scale * table[v, 3:6] - rc @ shift
    return out


def open_gauge_directions(
    table: Float[np.ndarray, "V C"], layout, observed: Bool[np.ndarray, " V"] | None = None
) -> int:
    """How many of the 7 similarity directions the held and tied entries leave open. Each direction
    (3 rotations, 3 translations, scale) moves every camera's ``[rvec, tvec]``; a held entry must
    not move and tied entries must move alike. The directions that obey both change no image and
    stay undetermined in a fit. Cameras not ``observed`` ``(V,)`` are left out."""
    eps = 1e-6
    columns = []
    for k in range(7):
        rot, shift, scale = np.eye(3), np.zeros(3), 1.0
        if k < 3:
            rot = rvec_to_rmat_numpy(eps * np.eye(3)[k][None])[0]
        elif k < 6:
            shift = eps * np.eye(3)[k - 3]
        else:
            scale = 1.0 + eps
        moved = similarity_table(table, scale, rot, shift)
        # near a half turn rvec can come back on its other branch (|r| - 2 pi): take the nearer
        r = moved[:, 0:3]
        norm = np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-300)
        other = r * (1.0 - 2.0 * np.pi / norm)
        flip = np.linalg.norm(other - table[:, 0:3], axis=1) < np.linalg.norm(
            r - table[:, 0:3], axis=1
        )
        moved[flip, 0:3] = other[flip]
        columns.append(((moved - table)[:, :6] / eps).ravel())
    keep = np.ones(len(table), bool) if observed is None else np.asarray(observed, bool)
    motion = np.stack(columns, axis=1).reshape(len(table), 6, 7)[keep].reshape(-1, 7)
    var = layout.var_index[keep, :6].ravel()
    rows = [motion[var < 0]]
    for v in np.unique(var[var >= 0]):
        members = np.flatnonzero(var == v)
        rows.append(motion[members[1:]] - motion[members[0]])
    held = np.concatenate(rows)
    if held.size == 0:
        return 7
    held = held / np.maximum(np.linalg.norm(motion, axis=0), 1e-300)
    sig = np.linalg.svd(held, compute_uv=False)
    return 7 - int((sig > 1e-6 * max(sig.max(initial=0.0), 1e-300)).sum())
