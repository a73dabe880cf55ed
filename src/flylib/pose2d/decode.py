"""Heatmap decoding: arg-max with sub-pixel refinement, confidence, top-K candidates.

Coordinates are heatmap pixels ``(x, y)`` in the pixel-centre convention (pixel
``(row, col)`` is at ``(col, row)``). The refinement fits a parabola through the
peak and its two neighbours along each axis, on the log of the heatmap when all
three are positive (exact for a Gaussian blob, the shape the detector is trained to
produce) and on the values otherwise; the offset is clamped to half a pixel.
"""

from __future__ import annotations

import numpy as np
import torch

_EPS = 1e-12


def _parabola_offset(left: torch.Tensor, centre: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    positive = (left > 0) & (centre > 0) & (right > 0)
    lg = torch.log(torch.where(positive, left, 1.0).clamp_min(_EPS))
    cg = torch.log(torch.where(positive, centre, 1.0).clamp_min(_EPS))
    rg = torch.log(torch.where(positive, right, 1.0).clamp_min(_EPS))
    l_ = torch.where(positive, lg, left)
    c_ = torch.where(positive, cg, centre)
    r_ = torch.where(positive, rg, right)
    curvature = l_ - 2.0 * c_ + r_
    offset = 0.5 * (l_ - r_) / torch.where(curvature < 0, curvature, -1.0)
    offset = torch.where(curvature < 0, offset, torch.zeros_like(offset))
    return offset.clamp(-0.5, 0.5)


def refine_peaks(heatmaps: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sub-pixel ``(x, y)`` of integer peaks.

    Parameters
    ----------
    heatmaps
        ``(M, H, W)`` float tensor.
    rows, cols
        ``(M, K)`` integer peak positions.

    Returns
    -------
    x, y : torch.Tensor
        ``(M, K)`` refined coordinates (no refinement along an axis at the border).
    """
    m, h, w = heatmaps.shape
    flat = heatmaps.reshape(m, h * w)

    def at(r, c):
        return torch.gather(flat, 1, (r.clamp(0, h - 1) * w + c.clamp(0, w - 1)))

    centre = at(rows, cols)
    dx = _parabola_offset(at(rows, cols - 1), centre, at(rows, cols + 1))
    dy = _parabola_offset(at(rows - 1, cols), centre, at(rows + 1, cols))
    dx = torch.where((cols > 0) & (cols < w - 1), dx, torch.zeros_like(dx))
    dy = torch.where((rows > 0) & (rows < h - 1), dy, torch.zeros_like(dy))
    return cols.to(heatmaps.dtype) + dx, rows.to(heatmaps.dtype) + dy


def decode_argmax(heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sub-pixel arg-max of each heatmap channel and its peak value.

    Parameters
    ----------
    heatmaps
        ``(N, C, H, W)`` tensor (any float dtype; decoded in float32).

    Returns
    -------
    xy : torch.Tensor
        ``(N, C, 2)`` float32 heatmap-pixel coordinates.
    conf : torch.Tensor
        ``(N, C)`` float32 peak values.
    """
    n, c, h, w = heatmaps.shape
    hm = heatmaps.float().reshape(n * c, h, w)
    conf, flat_index = hm.reshape(n * c, h * w).max(dim=1)
    rows, cols = (flat_index // w)[:, None], (flat_index % w)[:, None]
    x, y = refine_peaks(hm, rows, cols)
    xy = torch.stack([x[:, 0], y[:, 0]], dim=-1).reshape(n, c, 2)
    return xy, conf.reshape(n, c)


def topk_peaks(
    heatmaps: torch.Tensor, k: int, *, radius: int = 2, threshold: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` strongest local maxima per channel, sub-pixel refined, on the device.

    The torch counterpart of :func:`flylib.pictorial.peak_candidates` (same peak
    test, strongest first), so candidates never leave the GPU as full heatmaps.
    A pixel is a peak when it is the maximum of its ``(2 radius + 1)^2``
    neighbourhood and exceeds ``threshold``.

    Parameters
    ----------
    heatmaps
        ``(N, C, H, W)`` tensor.
    k
        Peaks kept per channel.
    radius
        Non-maximum-suppression half-width in heatmap pixels.
    threshold
        Minimum peak value.

    Returns
    -------
    xy : torch.Tensor
        ``(N, C, K, 2)`` heatmap-pixel coordinates, NaN where fewer than ``k`` peaks.
    score : torch.Tensor
        ``(N, C, K)`` peak values, NaN where padded.
    """
    n, c, h, w = heatmaps.shape
    hm = heatmaps.float()
    pooled = torch.nn.functional.max_pool2d(hm, 2 * radius + 1, stride=1, padding=radius)
    is_peak = (hm == pooled) & (hm > threshold)
    masked = torch.where(is_peak, hm, torch.full_like(hm, -torch.inf)).reshape(n * c, h * w)
    kk = min(k, h * w)
    score, flat_index = masked.topk(kk, dim=1)
    rows, cols = flat_index // w, flat_index % w
    x, y = refine_peaks(hm.reshape(n * c, h, w), rows, cols)
    valid = torch.isfinite(score)
    xy = torch.stack([x, y], dim=-1)
    xy = torch.where(valid[..., None], xy, torch.full_like(xy, torch.nan))
    score = torch.where(valid, score, torch.full_like(score, torch.nan))
    if kk < k:
        xy = torch.cat([xy, xy.new_full((n * c, k - kk, 2), torch.nan)], dim=1)
        score = torch.cat([score, score.new_full((n * c, k - kk), torch.nan)], dim=1)
    return xy.reshape(n, c, k, 2), score.reshape(n, c, k)


def gaussian_heatmap(size: tuple[int, int], centre_xy, sigma: float = 1.5) -> np.ndarray:
    """A unit-peak Gaussian blob on an ``(H, W)`` grid centred at ``(x, y)`` (for tests/benchmarks)."""
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.exp(-((xx - centre_xy[0]) ** 2 + (yy - centre_xy[1]) ** 2) / (2.0 * sigma**2))
