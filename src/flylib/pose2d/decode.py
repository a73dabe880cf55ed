"""Heatmap decoding: arg-max with sub-pixel refinement, confidence, top-K candidates.

Coordinates are heatmap cells ``(x, y) = (column, row)`` with fractional offsets;
:meth:`flylib.pose2d.plan.Pathway.heatmap_to_raw` maps them to raw-frame pixels with DeepFly2D's
convention (cell ``c`` is the normalized point ``c / W_hm``). The confidence is the raw peak
value. The sub-pixel refinement of the peak cell (:func:`flylib.pictorial.peaks.subpixel_offsets`)
is one of :data:`SUBPIXEL_METHODS`:

- ``weighted`` (default, the seed system's and DeepFly2D's): the intensity-weighted centroid of
  the ``(2 radius + 1)^2`` window around the peak cell (``radius = 2``), negative values clipped
  to zero and cells outside the heatmap ignored;
- ``argmax``: the peak cell itself;
- ``taylor``: one Newton step on the log-heatmap (exact for a Gaussian blob), clamped to the window;
- ``parabola``: a parabola through the peak and its two neighbours along each axis, on the log of
  the heatmap when all three are positive and on the values otherwise, clamped to half a cell.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from ..pictorial.peaks import subpixel_offsets
from .plan import DEFAULT_SUBPIXEL, SUBPIXEL_METHODS, check_subpixel

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int

#: Half-width of the refinement window in heatmap cells (5x5).
SUBPIXEL_RADIUS = 2

__all__ = [
    "DEFAULT_SUBPIXEL",
    "SUBPIXEL_METHODS",
    "SUBPIXEL_RADIUS",
    "check_subpixel",
    "decode_argmax",
    "gaussian_heatmap",
    "refine_peaks",
    "topk_peaks",
]


def refine_peaks(
    heatmaps: Float[torch.Tensor, "M H W"],
    rows: Int[torch.Tensor, "M K"],
    cols: Int[torch.Tensor, "M K"],
    method: str = DEFAULT_SUBPIXEL,
    radius: int = SUBPIXEL_RADIUS,
) -> tuple[Float[torch.Tensor, "M K"], Float[torch.Tensor, "M K"]]:
    """Sub-pixel ``(x, y)`` = ``(column + dx, row + dy)`` of integer peaks, in heatmap cells;
    ``radius`` is the half-width of the ``weighted`` window and the ``taylor`` step's bound."""
    dx, dy = subpixel_offsets(heatmaps, rows, cols, check_subpixel(method), radius)
    return cols.to(heatmaps.dtype) + dx, rows.to(heatmaps.dtype) + dy


def decode_argmax(
    heatmaps: Float[torch.Tensor, "N C H W"],
    method: str = DEFAULT_SUBPIXEL,
    radius: int = SUBPIXEL_RADIUS,
) -> tuple[Float[torch.Tensor, "N C 2"], Float[torch.Tensor, "N C"]]:
    """Sub-pixel arg-max (:func:`refine_peaks`) of each heatmap channel and its peak value:
    ``(N, C, 2)`` heatmap-cell ``(x, y)`` and ``(N, C)``, float32 whatever the heatmaps' dtype."""
    n, c, h, w = heatmaps.shape
    hm = heatmaps.float().reshape(n * c, h, w)
    conf, flat_index = hm.reshape(n * c, h * w).max(dim=1)
    rows, cols = (flat_index // w)[:, None], (flat_index % w)[:, None]
    x, y = refine_peaks(hm, rows, cols, method, radius)
    xy = torch.stack([x[:, 0], y[:, 0]], dim=-1).reshape(n, c, 2)
    return xy, conf.reshape(n, c)


def topk_peaks(
    heatmaps: Float[torch.Tensor, "N C H W"],
    k: int,
    *,
    radius: int = 2,
    threshold: float = 0.0,
    method: str = DEFAULT_SUBPIXEL,
    refine_radius: int = SUBPIXEL_RADIUS,
) -> tuple[Float[torch.Tensor, "N C K 2"], Float[torch.Tensor, "N C K"]]:
    """The ``k`` strongest local maxima per channel, sub-pixel refined, on the device.

    The torch counterpart of :func:`flylib.pictorial.peak_candidates` (same peak test, strongest
    first), so candidates never leave the GPU as full heatmaps. A pixel is a peak when it is the
    maximum of its ``(2 radius + 1)^2`` neighbourhood and exceeds ``threshold``. ``method`` and
    ``refine_radius`` are the arg-max decoder's refinement (:func:`refine_peaks`), so candidate 0
    is the arg-max point. Returns ``(N, C, K, 2)`` heatmap-cell coordinates and ``(N, C, K)`` peak
    values, NaN where fewer than ``k`` peaks.
    """
    n, c, h, w = heatmaps.shape
    hm = heatmaps.float()
    pooled = torch.nn.functional.max_pool2d(hm, 2 * radius + 1, stride=1, padding=radius)
    is_peak = (hm == pooled) & (hm > threshold)
    masked = torch.where(is_peak, hm, torch.full_like(hm, -torch.inf)).reshape(n * c, h * w)
    kk = min(k, h * w)
    score, flat_index = masked.topk(kk, dim=1)
    rows, cols = flat_index // w, flat_index % w
    x, y = refine_peaks(hm.reshape(n * c, h, w), rows, cols, method, refine_radius)
    valid = torch.isfinite(score)
    xy = torch.stack([x, y], dim=-1)
    xy = torch.where(valid[..., None], xy, torch.full_like(xy, torch.nan))
    score = torch.where(valid, score, torch.full_like(score, torch.nan))
    if kk < k:
        xy = torch.cat([xy, xy.new_full((n * c, k - kk, 2), torch.nan)], dim=1)
        score = torch.cat([score, score.new_full((n * c, k - kk), torch.nan)], dim=1)
    return xy.reshape(n, c, k, 2), score.reshape(n, c, k)


def gaussian_heatmap(
    size: tuple[int, int],
    centre_xy: tuple[float, float] | Float[np.ndarray, " 2"],
    sigma: float = 1.5,
) -> Float[np.ndarray, "H W"]:
    """A unit-peak Gaussian blob on an ``(H, W)`` grid centred at cell ``(x, y)`` (for tests/benchmarks)."""
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.exp(-((xx - centre_xy[0]) ** 2 + (yy - centre_xy[1]) ** 2) / (2.0 * sigma**2))
