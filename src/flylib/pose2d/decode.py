"""Heatmap decoding: arg-max with sub-pixel refinement, confidence, top-K candidates.

Coordinates are heatmap cells ``(x, y) = (column, row)`` with fractional offsets;
:meth:`flylib.pose2d.plan.Pathway.heatmap_to_raw` maps them to raw-frame pixels
with DeepFly2D's convention (cell ``c`` is the normalized point ``c / W_hm``). The
confidence is the raw peak value. The sub-pixel refinement of the peak cell is one of
:data:`SUBPIXEL_METHODS`:

- ``weighted`` (default, the seed system's and DeepFly2D's): the intensity-weighted
  centroid of the ``(2 radius + 1)^2`` window around the peak cell (``radius = 2``),
  negative values clipped to zero and cells outside the heatmap ignored;
- ``argmax``: the peak cell itself;
- ``taylor``: one Newton step on the log-heatmap (exact for a Gaussian blob),
  clamped to the window;
- ``parabola``: a parabola through the peak and its two neighbours along each axis,
  on the log of the heatmap when all three are positive and on the values
  otherwise, clamped to half a cell.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from ..errors import ConfigError
from .plan import DEFAULT_SUBPIXEL, SUBPIXEL_METHODS

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int

_EPS = 1e-12

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


def _gather(
    flat: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, h: int, w: int
) -> torch.Tensor:
    """``flat (M, H*W)`` at integer ``rows, cols`` of any shape ``(M, ...)`` (clamped into the grid)."""
    index = rows.clamp(0, h - 1) * w + cols.clamp(0, w - 1)
    return torch.gather(flat, 1, index.reshape(flat.shape[0], -1)).reshape(index.shape)


def _weighted_offsets(flat, rows, cols, h, w, radius):
    offsets = torch.arange(-radius, radius + 1, device=flat.device)
    r = rows[..., None, None] + offsets[:, None]  # (M, K, S, 1)
    c = cols[..., None, None] + offsets[None, :]  # (M, K, 1, S)
    r, c = torch.broadcast_tensors(r, c)
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    weight = torch.where(inside, _gather(flat, r, c, h, w).clamp_min(0.0), 0.0)
    total = weight.sum(dim=(-1, -2))
    safe = torch.where(total > 0, total, 1.0)
    off = offsets.to(flat.dtype)
    dy = (weight * off[:, None]).sum(dim=(-1, -2)) / safe
    dx = (weight * off[None, :]).sum(dim=(-1, -2)) / safe
    return torch.where(total > 0, dx, 0.0), torch.where(total > 0, dy, 0.0)


def _taylor_offsets(flat, rows, cols, h, w, radius):
    inner = (rows >= 1) & (rows < h - 1) & (cols >= 1) & (cols < w - 1)

    def at(dr: int, dc: int) -> torch.Tensor:
        return torch.log(_gather(flat, rows + dr, cols + dc, h, w).clamp_min(1e-10))

    centre = at(0, 0)
    gx = 0.5 * (at(0, 1) - at(0, -1))
    gy = 0.5 * (at(1, 0) - at(-1, 0))
    hxx = at(0, 1) - 2 * centre + at(0, -1)
    hyy = at(1, 0) - 2 * centre + at(-1, 0)
    hxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
    det = hxx * hyy - hxy * hxy
    ok = inner & (det > _EPS) & (hxx < 0)
    safe = torch.where(ok, det, 1.0)
    dx = (-(hyy * gx - hxy * gy) / safe).clamp(-radius, radius)
    dy = (-(hxx * gy - hxy * gx) / safe).clamp(-radius, radius)
    return torch.where(ok, dx, 0.0), torch.where(ok, dy, 0.0)


def _parabola_offsets(flat, rows, cols, h, w):
    centre = _gather(flat, rows, cols, h, w)
    dx = _parabola_offset(
        _gather(flat, rows, cols - 1, h, w), centre, _gather(flat, rows, cols + 1, h, w)
    )
    dy = _parabola_offset(
        _gather(flat, rows - 1, cols, h, w), centre, _gather(flat, rows + 1, cols, h, w)
    )
    dx = torch.where((cols > 0) & (cols < w - 1), dx, torch.zeros_like(dx))
    dy = torch.where((rows > 0) & (rows < h - 1), dy, torch.zeros_like(dy))
    return dx, dy


def check_subpixel(method: str, where: str = "pose2d.models[].subpixel") -> str:
    """``method`` if it is one of :data:`SUBPIXEL_METHODS`, else a :class:`~flylib.errors.ConfigError`."""
    if method not in SUBPIXEL_METHODS:
        raise ConfigError(
            f"{where}: unknown sub-pixel method {method!r}; use one of {', '.join(SUBPIXEL_METHODS)}"
        )
    return method


def refine_peaks(
    heatmaps: Float[torch.Tensor, "M H W"],
    rows: Int[torch.Tensor, "M K"],
    cols: Int[torch.Tensor, "M K"],
    method: str = DEFAULT_SUBPIXEL,
    radius: int = SUBPIXEL_RADIUS,
) -> tuple[Float[torch.Tensor, "M K"], Float[torch.Tensor, "M K"]]:
    """Sub-pixel ``(x, y)`` of integer peaks, in heatmap cells.

    Parameters
    ----------
    heatmaps
        ``(M, H, W)`` float tensor.
    rows, cols
        ``(M, K)`` integer peak positions.
    method
        One of :data:`SUBPIXEL_METHODS`.
    radius
        Half-width of the ``weighted`` window, and the ``taylor`` step's bound, in cells.

    Returns
    -------
    x, y : torch.Tensor
        ``(M, K)`` refined coordinates (``column + dx``, ``row + dy``).
    """
    check_subpixel(method)
    m, h, w = heatmaps.shape
    flat = heatmaps.reshape(m, h * w)
    if method == "argmax":
        dx = dy = torch.zeros(rows.shape, dtype=heatmaps.dtype, device=heatmaps.device)
    elif method == "weighted":
        dx, dy = _weighted_offsets(flat, rows, cols, h, w, radius)
    elif method == "taylor":
        dx, dy = _taylor_offsets(flat, rows, cols, h, w, radius)
    else:
        dx, dy = _parabola_offsets(flat, rows, cols, h, w)
    return cols.to(heatmaps.dtype) + dx, rows.to(heatmaps.dtype) + dy


def decode_argmax(
    heatmaps: Float[torch.Tensor, "N C H W"],
    method: str = DEFAULT_SUBPIXEL,
    radius: int = SUBPIXEL_RADIUS,
) -> tuple[Float[torch.Tensor, "N C 2"], Float[torch.Tensor, "N C"]]:
    """Sub-pixel arg-max of each heatmap channel and its peak value.

    Parameters
    ----------
    heatmaps
        ``(N, C, H, W)`` tensor (any float dtype; decoded in float32).
    method, radius
        The sub-pixel refinement (:func:`refine_peaks`).

    Returns
    -------
    xy : torch.Tensor
        ``(N, C, 2)`` float32 heatmap-cell coordinates ``(x, y)``.
    conf : torch.Tensor
        ``(N, C)`` float32 peak values.
    """
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
    method, refine_radius
        The sub-pixel refinement (:func:`refine_peaks`); the same as the arg-max
        decoder's, so candidate 0 is the arg-max point.

    Returns
    -------
    xy : torch.Tensor
        ``(N, C, K, 2)`` heatmap-cell coordinates, NaN where fewer than ``k`` peaks.
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
