"""Static summary figure of one recording's result: the first thing to look at after a run.

Four panels (matplotlib Agg, no pyplot): reprojection error per view; per keypoint, the fraction
of frames with 3D (or of views with 2D); median error per frame over time; leg-tip trajectories."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .draw import skeleton_colors

if TYPE_CHECKING:  # pragma: no cover
    from collections.abc import Sequence

    from jaxtyping import Float

    from ..results import PoseResult

#: Leg tips and other chain ends drawn in the trajectory panel, at most this many.
MAX_TRAJECTORIES = 6
#: Consecutive frames of the trajectory panel, around the middle one: more are an unreadable tangle.
MAX_TRAJECTORY_FRAMES = 2000


def summary_figure(result: PoseResult, path: str | Path, *, dpi: int = 100) -> Path:
    """Write the summary PNG of a :class:`flylib.PoseResult` to ``path`` (atomically) and return
    it; ``pts3d`` and ``reproj_error`` are used when present."""
    from matplotlib.figure import Figure

    from ..paths import atomic_path

    path = Path(path)
    fig = Figure(figsize=(14, 9.5), dpi=dpi, layout="constrained")
    grid = fig.add_gridspec(2, 2)
    skeleton = result.skeleton
    point_colors, _ = skeleton_colors(skeleton)
    point_colors = point_colors / 255.0
    names = list(result.cameras.names)
    error = getattr(result, "reproj_error", None)
    pts3d = getattr(result, "pts3d", None)

    error_per_view(fig.add_subplot(grid[0, 0]), error, names)
    _coverage(fig.add_subplot(grid[0, 1]), result.pts2d, pts3d, skeleton, point_colors)
    _error_over_time(fig.add_subplot(grid[1, 0]), error)
    _trajectories(fig.add_subplot(grid[1, 1], projection="3d"), pts3d, skeleton, point_colors)

    n_views, n_frames, n_points = result.pts2d.shape[:3]
    title = f"{n_frames} frames, {n_views} views, {n_points} points"
    empty = views_without_2d(result.pts2d, names)
    if empty:
        title += f" ({', '.join(empty)}: no 2D, left out)"
    if error is not None and np.isfinite(error).any():
        title += f"; median reprojection error {np.nanmedian(error):.2f} px"
    fig.suptitle(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def views_without_2d(pts2d: Float[np.ndarray, "V T P 2"], names: Sequence[str]) -> list[str]:
    """The views with no finite 2D point in any frame (``pts2d`` is ``(V, T, P, 2)``)."""
    seen = np.isfinite(np.asarray(pts2d, float)).all(-1).any(axis=(1, 2))
    return [n for n, s in zip(names, seen) if not s]


def _no_data(ax, message: str) -> None:
    ax.text(0.5, 0.5, message, ha="center", va="center", transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])


def error_per_view(ax, error, names) -> None:
    from matplotlib.ticker import NullLocator

    ax.set_title("Reprojection error per view")
    if error is None or not np.isfinite(error).any():
        _no_data(ax, "no reprojection error (no 3D result)")
        return
    per_view = [e[np.isfinite(e)] for e in error.reshape(error.shape[0], -1)]
    shown = [(n, e) for n, e in zip(names, per_view) if e.size]
    missing = [n for n, e in zip(names, per_view) if not e.size]
    if missing:
        ax.set_title(f"Reprojection error per view ({', '.join(missing)}: none, left out)")
    # each view's median under its name: beside its box it overlaps the next box and outliers
    ax.boxplot(
        [e for _, e in shown],
        tick_labels=[f"{n}\n{np.median(e):.2f} px" for n, e in shown],
        showfliers=True,
        flierprops={"markersize": 2, "alpha": 0.3},
    )
    ax.set_yscale("symlog", linthresh=1.0, linscale=1.0)
    top = max(float(e.max()) for _, e in shown)
    ax.set_yticks(error_ticks(top))
    ax.yaxis.set_major_formatter("{x:g}")
    ax.yaxis.set_minor_locator(NullLocator())
    ax.set_ylim(0, top * 1.15 if top > 0 else 1)
    ax.grid(axis="y", color="0.9", lw=0.6)
    ax.set_axisbelow(True)
    ax.set_ylabel("pixels (linear below 1, log above)")
    ax.set_xlabel("view, median error")


def error_ticks(top: float) -> list[float]:
    """Ticks of an error axis linear to 1, then log: ``0, 0.25, ..., 1, 2, 5, 10, 20, ...``."""
    ticks = [0.0, 0.25, 0.5, 0.75, 1.0]
    decade = 1.0
    while decade * 2 <= top * 1.15:
        ticks += [v for v in (2 * decade, 5 * decade, 10 * decade) if v <= top * 1.15]
        decade *= 10
    return ticks


def _coverage(ax, pts2d, pts3d, skeleton, colors) -> None:
    n_points = pts2d.shape[2]
    if pts3d is not None:
        frac = np.isfinite(pts3d).all(axis=-1).mean(axis=0)
        ax.set_title("Frames with a reconstructed 3D point")
    else:
        frac = np.isfinite(pts2d).all(axis=-1).mean(axis=(0, 1))
        ax.set_title("Fraction of (view, frame) with a 2D detection")
    ax.bar(np.arange(n_points), frac, color=colors)
    ax.set_xticks(np.arange(n_points), skeleton.point_names, rotation=90, fontsize=6)
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("fraction")


def _error_over_time(ax, error) -> None:
    ax.set_title("Median reprojection error per frame")
    if error is None or not np.isfinite(error).any():
        _no_data(ax, "no reprojection error (no 3D result)")
        return
    median = row_nanmedian(error.transpose(1, 0, 2).reshape(error.shape[1], -1))
    ax.plot(np.arange(median.size), median, lw=0.8)
    ax.set_xlabel("frame")
    ax.set_ylabel("pixels")


def row_nanmedian(rows: np.ndarray) -> np.ndarray:
    """``np.nanmedian(rows, axis=1)`` by one sort, without NumPy's slow masked path."""
    ordered = np.sort(rows, axis=1)  # NaN sorts last
    count = np.isfinite(rows).sum(axis=1)
    lo = np.take_along_axis(ordered, np.maximum(count - 1, 0)[:, None] // 2, axis=1)[:, 0]
    hi = np.take_along_axis(ordered, (count // 2)[:, None], axis=1)[:, 0]
    return np.where(count > 0, (lo + hi) / 2, np.nan)


def trajectory_points(skeleton) -> list[int]:
    """The points whose trajectories are drawn: the longest limb chains' tips (the leg tips)."""
    chains = [chain for chain in skeleton.limbs.values() if len(chain) >= 2]
    if not chains:
        return []
    longest = max(len(chain) for chain in chains)
    tips = [skeleton.point_names.index(chain[-1]) for chain in chains if len(chain) == longest]
    if len(tips) > MAX_TRAJECTORIES:
        keep = np.linspace(0, len(tips) - 1, MAX_TRAJECTORIES).round().astype(int)
        tips = [tips[k] for k in keep]
    return tips


def _trajectories(ax, pts3d, skeleton, colors) -> None:
    ax.set_title("3D trajectories of the leg tips")
    if pts3d is None or not np.isfinite(pts3d).any():
        ax.text2D(0.5, 0.5, "no 3D result", ha="center", transform=ax.transAxes)
        return
    valid_frames = np.flatnonzero(np.isfinite(pts3d).any(axis=(1, 2)))
    middle = int(valid_frames[len(valid_frames) // 2])
    mid = pts3d[middle]
    for i, j in np.asarray(skeleton.bones).reshape(-1, 2):
        ax.plot(*zip(mid[i], mid[j]), color="0.6", lw=1)
    start = max(0, min(middle - MAX_TRAJECTORY_FRAMES // 2, len(pts3d) - MAX_TRAJECTORY_FRAMES))
    window = slice(start, start + MAX_TRAJECTORY_FRAMES)
    if len(pts3d) > MAX_TRAJECTORY_FRAMES:
        ax.set_title(
            f"3D trajectories of the leg tips, frames {start}-{start + MAX_TRAJECTORY_FRAMES - 1}"
        )
    for p in trajectory_points(skeleton):
        track = pts3d[window, p]
        ax.plot(
            track[:, 0],
            track[:, 1],
            track[:, 2],
            color=colors[p],
            lw=0.8,
            label=skeleton.point_names[p],
        )
    finite = pts3d[np.isfinite(pts3d).all(axis=-1)]
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-9)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.legend(fontsize=7, loc="upper left")
