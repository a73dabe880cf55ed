"""Top-K heatmap peaks with sub-pixel refinement, and the :class:`Candidates` container."""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config.params import PictorialParams
from ..errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int
    from torch import Tensor

log = logging.getLogger(__name__)

DEFAULT_K = PictorialParams.k
DEFAULT_PEAK_RADIUS = 2
DEFAULT_PEAK_THRESHOLD = 0.05
DEFAULT_SUBPIXEL = "taylor"
SUBPIXEL_METHODS = ("argmax", "weighted", "taylor")
_EPS = 1e-12


@dataclass(frozen=True)
class Candidates:
    """Top-K detector peaks per (view, point) for a sequence, in raw-frame pixels: ``xy`` ``(x,
    y)`` (NaN where padded / unseen) and ``score`` (0 where padded); ``K = 0`` is the arg-max."""

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


def peak_candidates(
    heatmaps: Float[np.ndarray, "*batch H W"],
    k: int = DEFAULT_K,
    *,
    radius: int = DEFAULT_PEAK_RADIUS,
    threshold: float = DEFAULT_PEAK_THRESHOLD,
    method: str = DEFAULT_SUBPIXEL,
) -> tuple[Float[np.ndarray, "*batch k 2"], Float[np.ndarray, "*batch k"]]:
    """Top-``k`` local-maximum peaks of each heatmap, sub-pixel refined, strongest first.

    A pixel is a peak when it is the maximum of its ``(2 radius + 1)^2`` neighbourhood (also the
    ``weighted`` window, heatmap pixels) and exceeds ``threshold``; ``method``: one of
    :data:`SUBPIXEL_METHODS` (:func:`subpixel_offsets`). Returns ``xy`` ``(..., k, 2)`` in heatmap
    pixels (x = column, y = row, pixel centres at integers; NaN where fewer than ``k`` peaks exist)
    and ``score`` ``(..., k)``, the heatmap value at the peak pixel (0 where padded)."""
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
    dx, dy = subpixel_offsets(flat_hm, rows, cols, method, 2 if method == "taylor" else radius)
    if method == "taylor":  # a step beyond one cell is dropped (the detector clamps it)
        far = (np.abs(dx) > 1.0) | (np.abs(dy) > 1.0)
        dx, dy = np.where(far, 0.0, dx), np.where(far, 0.0, dy)
    valid = np.isfinite(top_val)
    xy = np.where(valid[..., None], np.stack([cols + dx, rows + dy], axis=-1), np.nan)
    score = np.where(valid, top_val, 0.0)
    if kk < k:  # fewer pixels than k: pad
        xy = np.concatenate([xy, np.full((len(xy), k - kk, 2), np.nan)], axis=1)
        score = np.concatenate([score, np.zeros((len(score), k - kk))], axis=1)
    return xy.reshape(*lead, k, 2), score.reshape(*lead, k)


def subpixel_offsets(
    heatmaps: Float[np.ndarray, "M H W"] | Float[Tensor, "M H W"],
    rows: Int[np.ndarray, "M K"] | Int[Tensor, "M K"],
    cols: Int[np.ndarray, "M K"] | Int[Tensor, "M K"],
    method: str,
    radius: int,
):
    """Sub-pixel offsets ``(dx, dy)`` in cells of integer peaks at ``(rows, cols)`` of
    ``heatmaps``: NumPy arrays or torch tensors alike (the detector's decoder shares it).

    ``method`` is ``"argmax"`` (0), ``"weighted"`` (the centroid of the ``(2 radius + 1)^2``
    window, negatives clipped to zero, cells outside ignored), ``"taylor"`` (one Newton step on
    the log-heatmap, clamped to ``radius``) or ``"parabola"`` (per axis through the peak and its
    two neighbours, on the log when all three are positive, clamped to half a cell); each is 0
    where it does not apply."""
    xp = np if isinstance(heatmaps, np.ndarray) else sys.modules["torch"]  # else a tensor
    n, height, width = heatmaps.shape
    device = heatmaps.device
    if method == "argmax":
        zero = xp.zeros(rows.shape, dtype=heatmaps.dtype, device=device)
        return zero, zero

    def at(r, c):  # the heatmap at integer (r, c) of any shape (M, ...), clipped into it
        m = xp.arange(n, device=device).reshape((n,) + (1,) * (r.ndim - 1))
        return heatmaps[m, r.clip(0, height - 1), c.clip(0, width - 1)]

    if method == "weighted":
        offsets = xp.arange(-radius, radius + 1, device=device)
        r = rows[..., None, None] + offsets[:, None]
        c = cols[..., None, None] + offsets[None, :]
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
        w = xp.where(inside, at(r, c).clip(0.0), 0.0)
        total = w.sum(axis=(-1, -2))
        safe = xp.where(total > 0, total, 1.0)
        offsets = xp.asarray(offsets, dtype=heatmaps.dtype, device=device)
        dy = (w * offsets[:, None]).sum(axis=(-1, -2)) / safe
        dx = (w * offsets[None, :]).sum(axis=(-1, -2)) / safe
        return xp.where(total > 0, dx, 0.0), xp.where(total > 0, dy, 0.0)
    if method == "parabola":
        centre = at(rows, cols)
        dx = _parabola(xp, at(rows, cols - 1), centre, at(rows, cols + 1))
        dy = _parabola(xp, at(rows - 1, cols), centre, at(rows + 1, cols))
        dx = xp.where((cols > 0) & (cols < width - 1), dx, 0.0)
        return dx, xp.where((rows > 0) & (rows < height - 1), dy, 0.0)
    # taylor: one Newton step on log(h) with central differences
    inner = (rows >= 1) & (rows < height - 1) & (cols >= 1) & (cols < width - 1)

    def log_at(dr, dc):
        return xp.log(at(rows + dr, cols + dc).clip(1e-10))

    centre = log_at(0, 0)
    gx = 0.5 * (log_at(0, 1) - log_at(0, -1))
    gy = 0.5 * (log_at(1, 0) - log_at(-1, 0))
    hxx = log_at(0, 1) - 2 * centre + log_at(0, -1)
    hyy = log_at(1, 0) - 2 * centre + log_at(-1, 0)
    hxy = 0.25 * (log_at(1, 1) - log_at(1, -1) - log_at(-1, 1) + log_at(-1, -1))
    det = hxx * hyy - hxy * hxy
    ok = inner & (det > _EPS) & (hxx < 0)
    safe = xp.where(ok, det, 1.0)
    dx = (-(hyy * gx - hxy * gy) / safe).clip(-radius, radius)
    dy = (-(hxx * gy - hxy * gx) / safe).clip(-radius, radius)
    return xp.where(ok, dx, 0.0), xp.where(ok, dy, 0.0)


def _parabola(xp, left, centre, right):
    """The parabola vertex's offset through three samples (``subpixel_offsets``)."""
    positive = (left > 0) & (centre > 0) & (right > 0)
    left, centre, right = (
        xp.where(positive, xp.log(xp.where(positive, v, 1.0).clip(_EPS)), v)
        for v in (left, centre, right)
    )
    curvature = left - 2.0 * centre + right
    offset = 0.5 * (left - right) / xp.where(curvature < 0, curvature, -1.0)
    return xp.where(curvature < 0, offset, 0.0).clip(-0.5, 0.5)
