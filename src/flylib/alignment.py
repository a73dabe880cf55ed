"""The least-squares similarity between two point sets (Umeyama 1991): how a reconstruction
is compared with a truth or another reconstruction whose gauge (scale, rotation, translation)
is free, and how bundle adjustment puts its result back in the starting frame."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float


def similarity_transform(
    src: Float[np.ndarray, "M 3"],
    dst: Float[np.ndarray, "M 3"],
    *,
    keep: float = 1.0,
    refits: int = 0,
) -> tuple[float, Float[np.ndarray, "3 3"], Float[np.ndarray, " 3"]] | None:
    """``(scale, rot, shift)`` minimising ``sum |scale rot src + shift - dst|^2`` over finite
    ``(M, 3)`` pairs; ``rot`` is proper (det +1); ``None`` when ``src`` has no spread.

    ``refits`` times, the fit is redone on the ``keep`` fraction of best-agreeing pairs (each
    refit needs >= 4), so that a few gross errors do not tilt it.
    """
    fitted = _umeyama(src, dst)
    for _ in range(refits):
        if fitted is None:
            break
        scale, rot, shift = fitted
        resid = np.linalg.norm(scale * src @ rot.T + shift - dst, axis=1)
        best = resid <= np.percentile(resid, 100.0 * keep)
        if best.sum() < 4:
            break
        fitted = _umeyama(src[best], dst[best]) or fitted
    return fitted


def similarity_aligned(
    points: Float[np.ndarray, "*pts 3"],
    target: Float[np.ndarray, "*pts 3"],
    *,
    keep: float = 1.0,
    refits: int = 0,
) -> Float[np.ndarray, "*pts 3"]:
    """``points`` mapped onto ``target`` by the similarity fitted on the pairs both hold; NaN
    stays NaN, and all is NaN when fewer than three pairs (or no spread) leave it undetermined."""
    points = np.asarray(points, float)
    target = np.asarray(target, float)
    ok = np.isfinite(points).all(-1) & np.isfinite(target).all(-1)
    fitted = (
        similarity_transform(points[ok], target[ok], keep=keep, refits=refits)
        if ok.sum() >= 3
        else None
    )
    if fitted is None:
        return np.full_like(points, np.nan)
    scale, rot, shift = fitted
    return scale * points @ rot.T + shift


def _umeyama(src: np.ndarray, dst: np.ndarray):
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    var_s = (a**2).sum() / len(src)
    if var_s <= 0:
        return None
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = np.trace(np.diag(sig) @ d) / var_s
    return scale, rot, mu_d - scale * rot @ mu_s
