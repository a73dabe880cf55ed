"""Top-K heatmap peaks with sub-pixel refinement, and the :class:`Candidates` container."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config.params import PictorialParams
from ..errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

log = logging.getLogger(__name__)

DEFAULT_K = PictorialParams.k
DEFAULT_PEAK_RADIUS = 2
DEFAULT_PEAK_THRESHOLD = 0.05
DEFAULT_SUBPIXEL = "taylor"
SUBPIXEL_METHODS = ("argmax", "weighted", "taylor")


@dataclass(frozen=True)
class Candidates:
    """Top-K detector peaks per (view, point) for a sequence, in raw-frame pixels.

    Attributes
    ----------
    xy
        ``(V, T, P, K, 2)`` peak positions ``(x, y)``, NaN where padded / unseen.
    score
        ``(V, T, P, K)`` peak values, 0 where padded; ``K = 0`` is the arg-max.
    """

    xy: Float[np.ndarray, "V T P K 2"]
    score: Float[np.ndarray, "V T P K"]

    def __post_init__(self):
        xy = np.asarray(self.xy, dtype=np.float64)
        score = np.asarray(self.score, dtype=np.float64)
        if xy.ndim != 5 or xy.shape[-1] != 2 or score.shape != xy.shape[:-1]:
            raise ValueError(
                f"Candidates need xy (V, T, P, K, 2) and score (V, T, P, K), "
                f"got {xy.shape} and {score.shape}"
            )
        score = np.where(np.isfinite(xy).all(-1), np.nan_to_num(score), 0.0)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "score", score)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(V, T, P, K)``."""
        return self.score.shape

    def frame(self, t: int) -> tuple[Float[np.ndarray, "V P K 2"], Float[np.ndarray, "V P K"]]:
        """Candidates of one frame: ``(V, P, K, 2)`` and ``(V, P, K)``."""
        return self.xy[:, t], self.score[:, t]

    def argmax(self) -> Float[np.ndarray, "V T P 2"]:
        """The strongest peak per (view, frame, point): ``(V, T, P, 2)``."""
        return self.xy[..., 0, :]

    @classmethod
    def from_points(
        cls, pts2d: Float[np.ndarray, "V T P 2"], conf: Float[np.ndarray, "V T P"] | None = None
    ) -> Candidates:
        """Single-peak candidates (``K = 1``) from plain detections ``(V, T, P, 2)``."""
        pts2d = np.asarray(pts2d, float)
        score = np.ones(pts2d.shape[:-1]) if conf is None else np.asarray(conf, float)
        return cls(pts2d[..., None, :], score[..., None])


# -- heatmap peaks -----------------------------------------------------------------


def peak_candidates(
    heatmaps: Float[np.ndarray, "*batch H W"],
    k: int = DEFAULT_K,
    *,
    radius: int = DEFAULT_PEAK_RADIUS,
    threshold: float = DEFAULT_PEAK_THRESHOLD,
    method: str = DEFAULT_SUBPIXEL,
) -> tuple[Float[np.ndarray, "*batch k 2"], Float[np.ndarray, "*batch k"]]:
    """Top-``k`` local-maximum peaks of each heatmap, sub-pixel refined.

    A pixel is a peak when it is the maximum of its ``(2 radius + 1)^2`` neighbourhood
    and exceeds ``threshold``; the ``k`` strongest are returned strongest first.

    Parameters
    ----------
    heatmaps
        ``(..., H, W)`` float array.
    k
        Peaks kept per heatmap.
    radius
        Neighbourhood half-width for the local-maximum test and the ``weighted``
        refinement window, in heatmap pixels.
    threshold
        Peaks at or below this value are ignored.
    method
        ``"argmax"`` (integer pixel), ``"weighted"`` (score-weighted centroid of the
        window) or ``"taylor"`` (Newton step on the log-heatmap: exact for a Gaussian
        blob).

    Returns
    -------
    xy : np.ndarray
        ``(..., k, 2)`` peak ``(x, y)`` in heatmap pixel coordinates (x = column,
        y = row, pixel centres at integers); NaN where fewer than ``k`` peaks exist.
    score : np.ndarray
        ``(..., k)`` heatmap value at the peak pixel, 0 where padded.
    """
    from scipy.ndimage import maximum_filter

    if method not in SUBPIXEL_METHODS:
        raise ConfigError(
            f"pictorial_structures: unknown sub-pixel method {method!r}; "
            f"use one of {', '.join(SUBPIXEL_METHODS)}"
        )
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    hm = np.asarray(heatmaps, dtype=np.float64)
    if hm.ndim < 2:
        raise ValueError(f"heatmaps must be (..., H, W), got shape {hm.shape}")
    lead, (height, width) = hm.shape[:-2], hm.shape[-2:]
    flat_hm = hm.reshape(-1, height, width)
    local_max = maximum_filter(
        flat_hm, size=(1, 2 * radius + 1, 2 * radius + 1), mode="constant", cval=-np.inf
    )
    is_peak = (flat_hm == local_max) & (flat_hm > threshold)
    values = np.where(is_peak, flat_hm, -np.inf).reshape(len(flat_hm), -1)
    kk = min(k, values.shape[1])
    top = np.argpartition(-values, kk - 1, axis=1)[:, :kk]
    top_val = np.take_along_axis(values, top, axis=1)
    order = np.argsort(-top_val, axis=1, kind="stable")
    top, top_val = np.take_along_axis(top, order, 1), np.take_along_axis(top_val, order, 1)
    rows, cols = top // width, top % width
    dx, dy = _refine(flat_hm, rows, cols, method, radius)
    valid = np.isfinite(top_val)
    xy = np.where(valid[..., None], np.stack([cols + dx, rows + dy], axis=-1), np.nan)
    score = np.where(valid, top_val, 0.0)
    if kk < k:  # fewer pixels than k: pad
        xy = np.concatenate([xy, np.full((len(xy), k - kk, 2), np.nan)], axis=1)
        score = np.concatenate([score, np.zeros((len(score), k - kk))], axis=1)
    return xy.reshape(*lead, k, 2), score.reshape(*lead, k)


def _refine(hm: np.ndarray, rows: np.ndarray, cols: np.ndarray, method: str, radius: int):
    """Sub-pixel offsets ``(dx, dy)`` of peaks at ``(rows, cols)`` of ``hm`` ``(M, H, W)``."""
    n, height, width = hm.shape
    if method == "argmax":
        return np.zeros(rows.shape), np.zeros(rows.shape)
    chan = np.arange(n)[:, None]
    if method == "weighted":
        offsets = np.arange(-radius, radius + 1)
        r = rows[..., None, None] + offsets[:, None]
        c = cols[..., None, None] + offsets[None, :]
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
        w = hm[chan[..., None, None], np.clip(r, 0, height - 1), np.clip(c, 0, width - 1)]
        w = np.where(inside, np.maximum(w, 0.0), 0.0)
        total = w.sum(axis=(-1, -2))
        safe = np.where(total > 0, total, 1.0)
        dy = (w * offsets[:, None]).sum(axis=(-1, -2)) / safe
        dx = (w * offsets[None, :]).sum(axis=(-1, -2)) / safe
        return np.where(total > 0, dx, 0.0), np.where(total > 0, dy, 0.0)
    # taylor: one Newton step on log(h) with central differences
    inner = (rows >= 1) & (rows < height - 1) & (cols >= 1) & (cols < width - 1)
    r, c = np.clip(rows, 1, height - 2), np.clip(cols, 1, width - 2)

    def at(dr, dc):
        return np.log(np.maximum(hm[chan, r + dr, c + dc], 1e-10))

    centre = at(0, 0)
    gx = 0.5 * (at(0, 1) - at(0, -1))
    gy = 0.5 * (at(1, 0) - at(-1, 0))
    hxx = at(0, 1) - 2 * centre + at(0, -1)
    hyy = at(1, 0) - 2 * centre + at(-1, 0)
    hxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
    det = hxx * hyy - hxy * hxy
    ok = inner & (det > 1e-12) & (hxx < 0)
    safe = np.where(ok, det, 1.0)
    dx = -(hyy * gx - hxy * gy) / safe
    dy = -(hxx * gy - hxy * gx) / safe
    ok &= (np.abs(dx) <= 1.0) & (np.abs(dy) <= 1.0)
    return np.where(ok, dx, 0.0), np.where(ok, dy, 0.0)
