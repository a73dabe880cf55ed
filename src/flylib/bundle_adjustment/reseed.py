"""Starting-rig repairs before the joint fit: gross cameras, distortion that folds.

A camera aimed off by degrees puts the fly hundreds of pixels from its detections, and a joint
fit from there wanders: it is resected by PnP (``cv2.solvePnPRansac``) from points the other
cameras triangulate, or, with too few trustworthy cameras, first re-aimed about its centre so
that its detections' median falls on the point the rig looks at."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from ..camera.model import pad_dist_numpy, rmat_to_rvec_numpy, rvec_to_rmat_numpy

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

log = logging.getLogger(__name__)


def view_errors(
    table: Float[np.ndarray, "V C"],
    pts: Float[np.ndarray, "N 3"],
    pts2d: Float[np.ndarray, "V N 2"],
    usable: Bool[np.ndarray, "V N"],
) -> Float[np.ndarray, "V N"]:
    """``(V, N)`` reprojection error of every usable observation (NaN elsewhere)."""
    from .problem import project_rows

    n_views, n_cols = usable.shape
    err = np.full((n_views, n_cols), np.nan)
    ok = usable & np.isfinite(pts).all(-1)[None]
    v, n = np.nonzero(ok)
    if v.size:
        err[v, n] = np.linalg.norm(project_rows(pts[n], table[v]) - pts2d[v, n], axis=1)
    return err


def _kmat(row):
    return np.array([[row[6], 0, row[8]], [0, row[7], row[9]], [0, 0, 1.0]])


def _dist(row):
    return pad_dist_numpy(row[10:][None])[0] if row.size > 10 else np.zeros(5)


def rig_target(table: Float[np.ndarray, "V C"]) -> Float[np.ndarray, " 3"]:
    """The point closest (least squares) to every camera's optical axis, ``(3,)``."""
    rmats = rvec_to_rmat_numpy(table[:, 0:3])
    centres = -np.einsum("vji,vj->vi", rmats, table[:, 3:6])
    axes = rmats[:, 2]
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    return np.linalg.lstsq(proj.sum(0), np.einsum("vij,vj->i", proj, centres), rcond=None)[0]


def reaim(
    row: Float[np.ndarray, " C"],
    observed: Float[np.ndarray, "M 2"],
    target: Float[np.ndarray, " 3"],
) -> Float[np.ndarray, " C"]:
    """Turn camera ``row`` about its centre so that ``target`` projects near the median of
    ``observed`` ``(M, 2)`` pixels (distortion ignored: a coarse repair)."""
    import cv2  # only a repair needs OpenCV, not every bundle-adjustment job

    rmat = rvec_to_rmat_numpy(row[0:3])
    centre = -rmat.T @ row[3:6]
    med = np.median(observed, axis=0)
    want = np.linalg.solve(_kmat(row), [med[0], med[1], 1.0])
    want /= np.linalg.norm(want)
    have = rmat @ (target - centre)
    have /= np.linalg.norm(have)
    axis = np.cross(have, want)
    angle = np.arctan2(np.linalg.norm(axis), have @ want)
    delta = cv2.Rodrigues(axis / max(np.linalg.norm(axis), 1e-300) * angle)[0]
    new = row.copy()
    new_rmat = delta @ rmat
    new[0:3] = rmat_to_rvec_numpy(new_rmat)
    new[3:6] = -new_rmat @ centre
    return new


def leave_one_out_errors(
    table: Float[np.ndarray, "V C"],
    pts2d: Float[np.ndarray, "V N 2"],
    usable: Bool[np.ndarray, "V N"],
    triangulate,
) -> Float[np.ndarray, " V"]:
    """``(V,)`` median error of each camera against points only the *other* cameras triangulate."""
    med = np.full(len(table), np.nan)
    for v in np.flatnonzero(usable.any(axis=1)):
        others = usable.copy()
        others[v] = False
        pts = triangulate(table, others)
        err = view_errors(table, pts, pts2d, usable)[v]
        if np.isfinite(err).any():
            med[v] = np.nanmedian(err)
    return med


def reseed_gross_cameras(
    table: Float[np.ndarray, "V C"],
    names,
    pts2d: Float[np.ndarray, "V N 2"],
    usable: Bool[np.ndarray, "V N"],
    gross_px: float,
    triangulate,
    movable: Bool[np.ndarray, " V"] | None = None,
) -> tuple[Float[np.ndarray, "V C"], list[str], Float[np.ndarray, " V"]]:
    """Resect (or re-aim) every camera whose median error from the start is gross. A camera is gross
    when the median reprojection error of its observations against points triangulated by the other
    cameras exceeds ``gross_px``. ``triangulate``: ``(table, usable) -> pts (N, 3)``, robust, NaN
    where impossible; ``movable``: cameras whose extrinsics may change (default all). Returns
    ``(table, reseeded, median_px)``: the repaired table, ``"<camera>: pnp"`` /
    ``"<camera>: re-aimed"`` per repaired camera, and the ``(V,)`` per-camera median error before
    the repair."""
    table = table.copy()
    has_obs = usable.any(axis=1)
    med = leave_one_out_errors(table, pts2d, usable, triangulate)
    # no consensus among the others within the RANSAC radius: as bad as gross; a camera none of
    # whose points two others see cannot be judged, and is left as configured
    judged = (usable & (usable.sum(axis=0) - usable >= 2)).any(axis=1)
    gross = judged & (np.nan_to_num(med, nan=np.inf) > gross_px)
    if movable is not None:
        gross &= np.asarray(movable, bool)
    reseeded: list[str] = []
    if not gross.any():
        return table, reseeded, med
    good = ~gross & has_obs
    if good.sum() < 2:
        target = rig_target(table)
        for v in np.flatnonzero(gross):
            table[v] = reaim(table[v], pts2d[v][usable[v]], target)
            reseeded.append(f"{names[v]}: re-aimed")
        good = np.zeros_like(good)
        # the re-aimed rig is roughly consistent: judge again, resect what is still off
        after = leave_one_out_errors(table, pts2d, usable, triangulate)
        gross = judged & (np.nan_to_num(after, nan=np.inf) > gross_px)
        if movable is not None:
            gross &= np.asarray(movable, bool)
        good = ~gross & has_obs
    for v in np.flatnonzero(gross):
        if good.sum() < 2:
            break
        pts_good = triangulate(table, usable & good[:, None])
        ok = usable[v] & np.isfinite(pts_good).all(-1)
        if ok.sum() < 8:
            continue
        row = table[v]
        # EPnP inside RANSAC without an extrinsic guess (the guess is what is wrong), then LM
        obj, img = pts_good[ok], pts2d[v][ok]
        import cv2  # only a repair needs OpenCV, not every bundle-adjustment job

        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj,
            img,
            _kmat(row),
            _dist(row),
            iterationsCount=200,
            reprojectionError=8.0,
            confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not found or inliers is None or len(inliers) < 6:
            continue
        inl = np.asarray(inliers).ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], _kmat(row), _dist(row), rvec, tvec)
        candidate = row.copy()
        candidate[0:3], candidate[3:6] = np.ravel(rvec), np.ravel(tvec)
        trial = table.copy()
        trial[v] = candidate
        before = np.nanmedian(view_errors(table, pts_good, pts2d, usable)[v][ok])
        after = np.nanmedian(view_errors(trial, pts_good, pts2d, usable)[v][ok])
        if after < before:
            table = trial
            reseeded = [r for r in reseeded if not r.startswith(f"{names[v]}:")]
            reseeded.append(f"{names[v]}: pnp")
    if reseeded:
        log.info(
            "bundle adjustment: cameras with a gross start (median error > %.0f px) repaired: %s",
            gross_px,
            ", ".join(reseeded),
        )
    return table, reseeded, med


def radial_folds(dist: Float[np.ndarray, " K"], r_max: float, n: int = 256) -> bool:
    """True when ``r * radial(r)`` is not increasing on ``[0, r_max]`` (the image would fold)."""
    d = pad_dist_numpy(np.asarray(dist, float)[None])[0]
    k1, k2, k3, k4, k5, k6 = d[0], d[1], d[4], d[5], d[6], d[7]
    r = np.linspace(0.0, r_max, n)
    r2 = r * r
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    mapped = r * num / den
    return bool(np.any(den <= 0) or np.any(np.diff(mapped) <= 0))


def image_radius(row: Float[np.ndarray, " C"]) -> float:
    """Normalized radius of the farthest image corner, taking the image as twice the principal
    point (plus a margin): where the distortion model must stay monotonic."""
    return 1.25 * float(np.hypot(row[8] / row[6], row[9] / row[7]))
