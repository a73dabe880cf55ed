"""Levenberg-Marquardt over a whole recording, chunk by chunk, with banded solves.

:func:`refine_points` is the entry point. Recording-wide unknowns are settled first (one length per
bone, one world position per rigid point: robust medians over the whole starting reconstruction,
left/right bones pooled on request); then the frames are solved in chunks of ``chunk_frames`` with
``overlap_frames`` of context on each side (only the chunk's own frames are kept), so memory does
not grow with the recording, by damped Gauss-Newton steps on the banded normal equations of
:mod:`flylib.refinement.objective` (:meth:`ChunkProblem.solve`). The reprojection term starts from
the triangulation's inlier views (:func:`refine_points`); after half the steps, every observation
within ``outlier_px`` of the refined point is admitted, the rest sit out."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from threadpoolctl import threadpool_limits

from ..camera import model as camera_model
from ..config.postprocessing import RefinementParams
from ..resources import thread_map
from .objective import (
    LOSSES,
    BlockLayout,
    assemble_band,
    band_width,
    chunk_kernel,
    difference_gram,
    from_slots,
    temporal_band,
    to_slots,
)

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float, Int, UInt8

    from ..camera.rig import CameraGroup

log = logging.getLogger(__name__)

#: Bits of the per-point ``flags`` array ``(T, P)`` (documented in the artifact's attrs).
FLAG_BITS: dict[str, tuple[int, str]] = {
    "observed": (1, "at least one view's 2D supports the point in this frame"),
    "filled": (2, "no view supports it; filled by the temporal term (gap <= gap_length)"),
    "missing": (4, "no view supports it for over gap_length frames, or none gives depth: NaN"),
    "single_view": (8, "supported by exactly one view (depth from the priors)"),
    "outlier_views": (16, "one or more of its 2D observations were rejected as outliers"),
    "moved": (
        32,
        "moved from the starting (triangulated) 3D by more than moved_fraction of the median bone",
    ),
    "no_start": (64, "the starting triangulation had no 3D for it in this frame"),
    "kept_triangulation": (
        128,
        "refinement's held-out-view error was not better than triangulation's for this point "
        "(one no held-out view checks: over the points checked), or a person corrected it, so "
        "the output keeps the triangulation's 3D, 2D and errors",
    ),
}


@dataclass
class RefinementResult:
    """What :func:`refine_points` returns: ``points3d`` refined (NaN where no view supports a
    point for more than ``gap_length`` frames); ``reproj_error`` (px) and ``points2d`` of the
    observations the fit kept (NaN elsewhere, rejected outliers included); ``flags``
    (:data:`FLAG_BITS`); ``bone_lengths`` (NaN: bone unconstrained); the rigid group's indices
    and world positions; ``info``: timings and iteration counts."""

    points3d: Float[np.ndarray, "T P 3"]
    reproj_error: Float[np.ndarray, "V T P"]
    points2d: Float[np.ndarray, "V T P 2"]
    flags: UInt8[np.ndarray, "T P"]
    bone_lengths: Float[np.ndarray, " B"]
    rigid_points: Int[np.ndarray, " R"]
    rigid_centres: Float[np.ndarray, "R 3"]
    info: dict[str, Any] = field(default_factory=dict)


# -- recording-wide unknowns ------------------------------------------------------------


def bone_lengths(
    start: Float[np.ndarray, "T P 3"],
    bones: Int[np.ndarray, "B 2"],
    mirror: Int[np.ndarray, " B"] | None = None,
) -> Float[np.ndarray, " B"]:
    """Robust length of every bone: its median over the frames of ``start`` (NaN = missing);
    NaN for a bone never seen whole. ``mirror``: each bone's left/right twin (or itself); twins
    share the median of their pooled lengths."""
    if len(bones) == 0:
        return np.zeros(0)
    lengths = np.linalg.norm(start[:, bones[:, 0]] - start[:, bones[:, 1]], axis=-1)  # (T, B)
    out = np.full(len(bones), np.nan)
    for b in range(len(bones)):
        cols = [b] if mirror is None else sorted({b, int(mirror[b])})
        values = lengths[:, cols].ravel()
        values = values[np.isfinite(values)]
        if values.size:
            out[b] = np.median(values)
    return out


def rigid_centres(
    start: Float[np.ndarray, "T P 3"], rigid: Int[np.ndarray, " R"]
) -> Float[np.ndarray, "R 3"]:
    """World position of each rigid point: the per-coordinate median over frames ``(R, 3)``."""
    out = np.full((len(rigid), 3), np.nan)
    for k, p in enumerate(rigid):
        track = start[:, p]
        track = track[np.isfinite(track).all(-1)]
        if len(track):
            out[k] = np.median(track, axis=0)
    return out


def fill_start(
    start: Float[np.ndarray, "T P 3"], fallback: Float[np.ndarray, "P 3"]
) -> Float[np.ndarray, "T P 3"]:
    """Each point's gaps interpolated linearly (nearest at the ends; never seen: ``fallback``)."""
    out = start.copy()
    t = np.arange(start.shape[0])
    for p in range(start.shape[1]):
        ok = np.isfinite(start[:, p]).all(-1)
        if ok.all():
            continue
        if not ok.any():
            out[:, p] = fallback[p]
            continue
        for c in range(3):
            out[:, p, c] = np.interp(t, t[ok], start[ok, p, c])
    return out


def recording_motion(start: Float[np.ndarray, "T P 3"], order: int) -> float:
    """How far the points move per frame: the median length of their ``order``-th differences
    (world units per frame^order; NaN when no point is seen in ``order + 1`` consecutive frames).
    It carries the frame rate and the recording's own motion; the refinement stage tries
    smoothness scales in units of it."""
    if start.shape[0] <= order:
        return float("nan")
    step = np.linalg.norm(np.diff(start, n=order, axis=0), axis=-1)
    step = step[np.isfinite(step)]
    return float(np.median(step)) if step.size else float("nan")


# -- one chunk ----------------------------------------------------------------------------


def _bucket(n: int, largest: int) -> int:
    """Padded frame count for the kernel: powers of two from 32, capped at ``largest``."""
    size = 32
    while size < n:
        size *= 2
    return max(n, min(size, largest))


class Grid:
    """Observations as a dense (slot, view) grid: for every point slot, the views that see it
    anywhere in the recording (at most ``W``; unused cells have weight 0)."""

    def __init__(self, observed: np.ndarray, cameras, layout: BlockLayout):
        seen = observed.any(axis=1)  # (V, P)
        slots = layout.slots
        width = max(int(seen.sum(0).max(initial=1)), 1)
        view = np.zeros((*slots.shape, width), np.int64)
        real = np.zeros((*slots.shape, width), bool)
        for (b, k), p in np.ndenumerate(slots):
            if p < 0:
                continue
            views = np.flatnonzero(seen[:, p])
            view[b, k, : len(views)] = views
            real[b, k, : len(views)] = True
        self.view, self.real = view, real
        self.point = np.broadcast_to(np.where(slots >= 0, slots, 0)[..., None], view.shape)
        rows = _camera_rows(cameras)[view]
        self.arrays = {
            "rmat": camera_model.rvec_to_rmat_numpy(rows[..., 0:3].reshape(-1, 3)).reshape(
                *view.shape, 3, 3
            ),
            "tvec": rows[..., 3:6],
            "intr": rows[..., 6:10],
        }
        if rows.shape[-1] > 10 and np.any(rows[..., 10:]):
            self.arrays["dist"] = camera_model.pad_dist_numpy(
                rows[..., 10:].reshape(-1, rows.shape[-1] - 10)
            ).reshape(*view.shape, 12)

    def gather(self, per_obs: np.ndarray, n_frames: int) -> np.ndarray:
        """``(V, T, P, ...)`` -> ``(n_blocks, m, W, n_frames, ...)`` (0 in unused cells and padding)."""
        picked = per_obs[self.view, :, self.point]  # (nb, m, W, T, ...)
        mask = self.real.reshape(*self.real.shape, *([1] * (picked.ndim - 3)))
        picked = np.where(mask, picked, 0.0)
        if picked.shape[3] < n_frames:
            pad = [(0, 0)] * picked.ndim
            pad[3] = (0, n_frames - picked.shape[3])
            picked = np.pad(picked, pad)
        return picked

    def scatter(self, per_cell: np.ndarray, shape) -> np.ndarray:
        """``(n_blocks, m, W, T)`` -> ``(V, T, P)`` (NaN where no cell)."""
        out = np.full(shape, np.nan)
        real = self.real
        out[self.view[real], :, self.point[real]] = per_cell[real][:, : shape[1]]
        return out


def _bone_incidence(layout: BlockLayout, bones: np.ndarray, lengths: np.ndarray):
    """``(n_blocks, Kb, m)`` incidence rows and ``(n_blocks, Kb)`` lengths (0 = padding)."""
    per_block = [[] for _ in range(layout.n_blocks)]
    for (i, j), length in zip(bones, lengths):
        per_block[layout.block_of[i]].append((layout.slot_of[i], layout.slot_of[j], length))
    kb = max(1, max(len(b) for b in per_block))
    inc = np.zeros((layout.n_blocks, kb, layout.m))
    out = np.zeros((layout.n_blocks, kb))
    for b, items in enumerate(per_block):
        for q, (si, sj, length) in enumerate(items):
            inc[b, q, si] += 1.0
            inc[b, q, sj] -= 1.0
            out[b, q] = length
    return inc, out


def _device(value):
    """A NumPy array as a JAX array (scalars as they are)."""
    if isinstance(value, np.ndarray):
        import jax

        return jax.device_put(value)
    return value


class ChunkProblem:
    """One chunk's objective, padded to ``padded`` frames (no term reaches a padded frame)."""

    def __init__(
        self,
        tracks: Grid,
        xy,
        weight,
        layout: BlockLayout,
        bones,
        lengths,
        rigid,
        centres,
        opts: RefinementParams,
        padded: int,
    ):
        self.opts = opts
        self.tracks = tracks
        self.layout = layout
        self.n_views, self.n_frames, self.n_points = weight.shape
        self.padded = padded
        self.weight = weight
        self.u = band_width(layout.m, opts.smooth_order)
        self.kernel = chunk_kernel(opts.loss, opts.smooth_order, layout.m)
        bone_ok = np.isfinite(lengths) & (lengths > 0) & (opts.bone_weight > 0)
        bones, lengths = bones[bone_ok], lengths[bone_ok]
        rigid_ok = np.isfinite(centres).all(-1) & (opts.rigid_weight > 0)
        rigid, centres = rigid[rigid_ok], centres[rigid_ok]
        incidence, slot_lengths = _bone_incidence(layout, bones, lengths)
        live = (np.arange(padded) < self.n_frames).astype(np.float64)
        gram = np.zeros((opts.smooth_order + 1, padded))
        gram[:, : self.n_frames] = difference_gram(self.n_frames, opts.smooth_order)
        rigid_mask = np.zeros(layout.slots.shape)
        centre = np.zeros((*layout.slots.shape, 3))
        rigid_mask[layout.block_of[rigid], layout.slot_of[rigid]] = 1.0
        centre[layout.block_of[rigid], layout.slot_of[rigid]] = centres.reshape(-1, 3)
        self.data = {
            **tracks.arrays,
            "xy": np.moveaxis(tracks.gather(np.nan_to_num(xy, nan=0.0), padded), -1, 0),
            "inv_s2": 1.0 / opts.scale_px**2,
            "incidence": incidence,
            "length": slot_lengths,
            "bone_w": opts.bone_weight / opts.bone_scale**2,
            "rigid_mask": rigid_mask,
            "centre": centre,
            "rigid_w": opts.rigid_weight / opts.rigid_scale**2,
            "gram": gram,
            "smooth_w": opts.smooth_weight / opts.smooth_scale**2,
            "live": live,
        }
        self.temporal = temporal_band(layout, opts.smooth_order, gram, self.data["smooth_w"], live)
        self._buffer = None  # the band, rebuilt and factorized in place at every step
        # on the device once, not at every evaluation
        self.data = {k: _device(v) for k, v in self.data.items()}
        self.set_active(weight > 0)

    def set_active(self, active: np.ndarray) -> None:
        """Use only the observations ``active`` ``(V, T, P)``."""
        self.active = active
        self.data["w"] = _device(
            self.tracks.gather(np.where(active, self.weight, 0.0), self.padded)
        )

    def to_slots(self, x: np.ndarray) -> np.ndarray:
        """``(T, P, 3)`` -> padded, slotted ``(n_blocks, padded, m, 3)``."""
        if x.shape[0] < self.padded:
            x = np.concatenate([x, np.repeat(x[-1:], self.padded - x.shape[0], axis=0)])
        return to_slots(x, self.layout.slots)

    def from_slots(self, xs: np.ndarray) -> np.ndarray:
        return from_slots(xs, self.layout.slots, self.n_points)[: self.n_frames]

    def evaluate(self, xs: np.ndarray):
        """The objective at slotted ``xs``: :func:`~flylib.refinement.objective.chunk_kernel`'s
        ``(cost, rows, grad, err)`` as NumPy arrays (:meth:`band` makes the whole matrix)."""
        cost, rows, grad, err = self.kernel(xs, self.data)
        return np.asarray(cost), np.asarray(rows), np.asarray(grad), np.asarray(err)

    def band(self, rows: np.ndarray, columns: np.ndarray | None = None) -> np.ndarray:
        """The Gauss-Newton matrix ``(u + 1, n)`` in LAPACK's upper band storage (Fortran-ordered)
        from :meth:`evaluate`'s ``rows``; only ``columns`` ``(n,)`` bool (whole blocks) if given."""
        return assemble_band(rows, self.temporal, 3 * self.layout.m, self.u, columns)

    def errors(self, err: np.ndarray) -> np.ndarray:
        """Cell errors ``(n_blocks, m, W, padded)`` -> ``(V, T, P)``."""
        return self.tracks.scatter(err, (self.n_views, self.n_frames, self.n_points))

    def step(
        self,
        rows: np.ndarray,
        grad: np.ndarray,
        mu: np.ndarray,
        floor: float,
        columns: np.ndarray | None = None,
    ) -> np.ndarray:
        """The damped step ``(n,)``: solves ``(A + diag(mu * diag(A) + floor)) d = -grad`` over
        ``columns`` (zero elsewhere) by one banded Cholesky; ``mu`` ``(n,)`` or scalar.
        ``LinAlgError`` if the matrix is not positive definite."""
        from scipy.linalg import cho_solve_banded, cholesky_banded  # not for FLAG_BITS' readers

        if self._buffer is None:
            self._buffer = np.empty((grad.size, self.u + 1))
        ab = assemble_band(
            rows, self.temporal, 3 * self.layout.m, self.u, columns, mu, floor, self._buffer
        )
        factor = cholesky_banded(ab, lower=False, overwrite_ab=True, check_finite=False)
        step = np.zeros(grad.shape)
        rhs = -grad if columns is None else -grad[columns]
        solved = cho_solve_banded((factor, False), rhs, overwrite_b=True, check_finite=False)
        if columns is None:
            return solved
        step[columns] = solved
        return step

    def solve(
        self, xs: np.ndarray, max_iterations: int, ftol: float = 1e-3, trace: list | None = None
    ):
        """Levenberg-Marquardt from slotted ``xs``; returns ``(xs, steps, err)``.

        The blocks share no unknown, so each keeps its own damping and takes or refuses its part
        of a step on its own cost. A block stops once its cost falls by less than ``ftol`` of
        itself (or its damping runs away), and leaves the factorization. A step is one banded
        factorization of the live blocks and one evaluation of the chunk. ``trace``, when given,
        receives ``(cost, mu)`` (per-block arrays) after every evaluation."""
        n_blocks = xs.shape[0]
        per_block = xs[0].size  # unknowns of one block (block-major ordering)
        cost, rows, grad, err = self.evaluate(xs)
        mu = np.full(n_blocks, 1e-4)
        if trace is not None:
            trace.append((cost, np.zeros(n_blocks)))
        # a ridge far below any real curvature: keeps unknowns only the temporal term sees (a
        # point unobserved in the whole chunk) well posed, the factorization free of denormals
        diag = rows[0] + self.temporal[0]
        floor = 1e-6 * float(np.median(diag[diag > 0])) if (diag > 0).any() else 1.0
        live = np.ones(n_blocks, bool)
        steps = 0
        while steps < max_iterations and live.any():
            columns = None if live.all() else np.repeat(live, per_block)
            try:
                step = self.step(rows, grad, np.repeat(mu, per_block), floor, columns)
            except np.linalg.LinAlgError:  # scipy.linalg's is NumPy's
                mu = np.where(live, mu * 10.0, mu)
                live &= mu < 1e8
                continue
            steps += 1
            trial = xs + step.reshape(xs.shape)
            new_cost, new_rows, new_grad, new_err = self.evaluate(trial)
            better = live & (new_cost <= cost)
            settled = better & (cost - new_cost <= ftol * np.maximum(new_cost, 1e-12))
            if better.all():
                xs, cost, rows, grad, err = trial, new_cost, new_rows, new_grad, new_err
            elif better.any():
                took = np.repeat(better, per_block)
                xs = np.where(better[:, None, None, None], trial, xs)
                cost = np.where(better, new_cost, cost)
                rows = np.where(took, new_rows, rows)
                grad = np.where(took, new_grad, grad)
                err = np.where(better[:, None, None, None], new_err, err)
            mu = np.where(better, np.maximum(mu / 5.0, 1e-10), np.where(live, mu * 8.0, mu))
            live &= ~settled & (mu < 1e8)
            if trace is not None:
                trace.append((new_cost, mu.copy()))
        return xs, steps, err


# -- the recording ----------------------------------------------------------------------


class ArraySource:
    """In-memory inputs of :func:`refine_stream`: ``pts2d (V, T, P, 2)``, ``conf (V, T, P)`` or
    None, ``start (T, P, 3)``, ``inliers (V, T, P)`` or None (anything sliceable along T works)."""

    def __init__(self, pts2d, start, conf=None, inliers=None):
        self.pts2d, self.start, self.conf, self.inliers = pts2d, start, conf, inliers
        self.n_views, self.n_frames, self.n_points = pts2d.shape[:3]

    def read(self, lo: int, hi: int):
        """``(pts2d, conf, start, inliers)`` of frames ``lo:hi`` as float64 / bool arrays."""
        conf = None if self.conf is None else np.asarray(self.conf[:, lo:hi], np.float64)
        inl = None if self.inliers is None else np.asarray(self.inliers[:, lo:hi], bool)
        return (
            np.asarray(self.pts2d[:, lo:hi], np.float64),
            conf,
            np.asarray(self.start[lo:hi], np.float64),
            inl,
        )


#: The bits of :data:`FLAG_BITS` that follow from which 2D and 3D a point holds.
NAN_BITS = ("observed", "filled", "missing", "single_view")


def flags_from_nan(
    flags: UInt8[np.ndarray, "T P"],
    points2d: Float[np.ndarray, "V T P 2"],
    points3d: Float[np.ndarray, "T P 3"],
) -> UInt8[np.ndarray, "T P"]:
    """``flags`` with the :data:`NAN_BITS` set from the 2D and 3D a point holds: ``observed`` (a
    view's 2D kept), ``single_view`` (exactly one), ``missing`` (no 3D), ``filled`` (3D with no
    view's 2D); the other bits as they were."""
    bit = {k: np.uint8(FLAG_BITS[k][0]) for k in NAN_BITS}
    views = np.isfinite(points2d).all(-1).sum(0)
    has3d = np.isfinite(points3d).all(-1)
    out = np.asarray(flags, np.uint8) & ~np.uint8(sum(bit.values()))
    out |= np.where(views > 0, bit["observed"], 0).astype(np.uint8)
    out |= np.where(views == 1, bit["single_view"], 0).astype(np.uint8)
    out |= np.where(~has3d, bit["missing"], 0).astype(np.uint8)
    out |= np.where(has3d & (views == 0), bit["filled"], 0).astype(np.uint8)
    return out.astype(np.uint8)


class ArraySink:
    """Collects :func:`refine_stream`'s output in memory."""

    def __init__(self, n_views: int, n_frames: int, n_points: int):
        self.points3d = np.full((n_frames, n_points, 3), np.nan)
        self.reproj_error = np.full((n_views, n_frames, n_points), np.nan)
        self.points2d = np.full((n_views, n_frames, n_points, 2), np.nan)
        self.flags = np.zeros((n_frames, n_points), np.uint8)

    def write(
        self,
        lo: int,
        hi: int,
        points3d: Float[np.ndarray, "T P 3"],
        reproj_error: Float[np.ndarray, "V T P"],
        points2d: Float[np.ndarray, "V T P 2"],
        flags: UInt8[np.ndarray, "T P"],
    ) -> None:
        self.points3d[lo:hi] = points3d
        self.reproj_error[:, lo:hi] = reproj_error
        self.points2d[:, lo:hi] = points2d
        self.flags[lo:hi] = flags

    def mark_missing(self, lo: int, hi: int, missing: Bool[np.ndarray, "T P"]) -> None:
        """Points ``missing`` (of frames ``lo:hi``) become NaN with their 2D and errors, flagged
        missing (read, modify, write back: the same code serves arrays and HDF5 datasets)."""
        p3, p2, err = self.points3d[lo:hi], self.points2d[:, lo:hi], self.reproj_error[:, lo:hi]
        p3[missing], p2[:, missing], err[:, missing] = np.nan, np.nan, np.nan
        self.points3d[lo:hi], self.points2d[:, lo:hi], self.reproj_error[:, lo:hi] = p3, p2, err
        self.flags[lo:hi] = flags_from_nan(self.flags[lo:hi], p2, p3)


def _weights(pts2d, conf, opts):
    observed = np.isfinite(pts2d).all(-1)
    if conf is not None and opts.weigh_by_confidence:
        weight = np.where(observed & np.isfinite(conf) & (conf > 0), np.nan_to_num(conf), 0.0)
    else:
        weight = observed.astype(np.float64)
    return observed & (weight > 0), weight


#: Frames (at most) the recording-wide medians are taken over: evenly spread, so the
#: memory they need does not grow with the recording.
GLOBAL_SAMPLE_FRAMES = 20000


def refine_stream(
    source,
    cameras,
    sink,
    *,
    bones=None,
    chains=None,
    mirror=None,
    rigid=(),
    options: RefinementParams | None = None,
) -> dict[str, Any]:
    """:func:`refine_points` reading chunks from ``source`` and writing them to ``sink``; memory
    is bounded by the chunk size (plus one byte per frame and point for the gap bookkeeping).

    ``source`` has ``n_views``, ``n_frames``, ``n_points`` and ``read(lo, hi) -> (pts2d, conf,
    start, inliers)`` (:class:`ArraySource`); ``sink`` has ``write(lo, hi, points3d,
    reproj_error, points2d, flags)`` and ``mark_missing(lo, hi, missing)`` (:class:`ArraySink`).
    Returns ``bone_lengths``, ``rigid_points``, ``rigid_centres`` and ``info``."""
    opts = options or RefinementParams()
    if opts.loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {opts.loss!r}")
    if opts.smooth_order not in (1, 2):
        raise ValueError(f"smooth_order must be 1 or 2, got {opts.smooth_order}")
    n_frames, n_points = source.n_frames, source.n_points
    bones = (
        np.zeros((0, 2), np.int64) if bones is None else np.asarray(bones, np.int64).reshape(-1, 2)
    )
    rigid = np.asarray(rigid, np.int64).ravel()
    layout = _chain_layout(n_points, bones, chains)
    chunk = max(int(opts.chunk_frames), 1)
    overlap = max(int(opts.overlap_frames), 0)

    # -- pass 1: which views see which points, and a frame sample for the medians
    seen, twice, sample = _first_pass(source, chunk, opts)
    lengths = bone_lengths(sample, bones, mirror if opts.symmetric_bones else None)
    # a point no two views see at once, nor a rigid centre or measured bone places, has no depth
    centres = rigid_centres(sample, rigid)
    twice[rigid[np.isfinite(centres).all(-1)]], twice[bones[np.isfinite(lengths)]] = True, True
    fallback = _fallback_points(sample, rigid, centres, n_points)
    grid = Grid(seen[:, None, :], cameras, layout)
    scale = np.nanmedian(lengths) if np.isfinite(lengths).any() else np.inf

    # -- pass 2: the chunks, two at a time (the JAX kernel and LAPACK release the GIL);
    # results are written in order by this thread
    largest = chunk + 2 * overlap
    solve_chunk = _ChunkSolver(
        source,
        grid,
        layout,
        bones,
        lengths,
        rigid,
        centres,
        opts,
        fallback,
        scale,
        overlap,
        largest,
    )
    supported = np.zeros((n_frames, n_points), bool)
    started = time.perf_counter()
    iterations, kept_total, rejected_total = _solve_chunks(
        solve_chunk, _chunk_bounds(n_frames, chunk, largest), sink, supported
    )
    solve_seconds = time.perf_counter() - started

    # -- gaps longer than gap_length, and points without depth: NaN
    long_gap = _runs_longer_than(~supported, int(opts.gap_length)) | ~twice
    for lo in range(0, n_frames, chunk):
        hi = min(lo + chunk, n_frames)
        if long_gap[lo:hi].any():
            sink.mark_missing(lo, hi, long_gap[lo:hi])
    info = {
        "frames": n_frames,
        "chunks": len(iterations),
        "iterations": iterations[:64],
        "seconds": round(solve_seconds, 3),
        "observations_kept": kept_total,
        "observations_rejected": rejected_total,
        "bone_sample_frames": len(sample),
        "smooth_scale": opts.smooth_scale,
    }
    log.info(
        "refinement: %d frames in %d chunk(s), %.2f s, iterations %s",
        n_frames,
        len(iterations),
        solve_seconds,
        iterations[:8],
    )
    return {"bone_lengths": lengths, "rigid_points": rigid, "rigid_centres": centres, "info": info}


def _chain_layout(n_points: int, bones: np.ndarray, chains) -> BlockLayout:
    """The limb chains' block layout (default: one per bone); a bone must join chain neighbours."""
    chains = (
        [list(map(int, c)) for c in chains]
        if chains is not None
        else [list(map(int, b)) for b in bones]
    )
    layout = BlockLayout.from_chains(n_points, chains)
    for i, j in bones:
        if (
            layout.block_of[i] != layout.block_of[j]
            or abs(layout.slot_of[i] - layout.slot_of[j]) != 1
        ):
            raise ValueError(
                f"bone ({i}, {j}) does not join neighbouring points of one chain; "
                "give the limb chains the bones run along"
            )
    return layout


def _first_pass(source, chunk: int, opts: RefinementParams):
    """Which views see which points anywhere ``(V, P)``, which points two views see in some frame
    ``(P,)``, and an even sample of ``start``."""
    n_frames, n_points = source.n_frames, source.n_points
    seen, twice = np.zeros((source.n_views, n_points), bool), np.zeros(n_points, bool)
    stride = max(1, -(-n_frames // GLOBAL_SAMPLE_FRAMES))
    sample = []
    for lo in range(0, n_frames, chunk):
        hi = min(lo + chunk, n_frames)
        pts2d, conf, start, _ = source.read(lo, hi)
        observed = _weights(pts2d, conf, opts)[0]
        seen, twice = seen | observed.any(axis=1), twice | (observed.sum(0) > 1).any(0)
        sample.append(start[(-lo) % stride :: stride])
    sample = np.concatenate(sample) if sample else np.zeros((0, n_points, 3))
    return seen, twice, sample


def _fallback_points(sample, rigid, centres, n_points: int) -> Float[np.ndarray, "P 3"]:
    """Where a point starts when the triangulation never had it: its median over the sample
    (the rigid centre for rigid points), else the centre of all points."""
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            fallback = (
                np.nanmedian(sample, axis=0) if len(sample) else np.full((n_points, 3), np.nan)
            )
    centre_all = np.nanmean(fallback, axis=0) if np.isfinite(fallback).any() else np.zeros(3)
    fallback = np.where(np.isfinite(fallback), fallback, centre_all)
    if len(rigid):
        ok = np.isfinite(centres).all(-1)
        fallback[rigid[ok]] = centres[ok]
    return fallback


def _chunk_bounds(n_frames: int, chunk: int, largest: int) -> list[tuple[int, int]]:
    """The chunks' ``(lo, hi)`` frames: one chunk when the recording fits one window.

    Every chunk is solved over a window of one length (``largest``, or the whole recording if
    shorter): the first and last windows reach further into the recording instead of being
    shorter, so the kernel compiles once per recording and no window is padded."""
    if n_frames <= largest:
        return [(0, n_frames)] if n_frames else []
    return [(lo, min(lo + chunk, n_frames)) for lo in range(0, n_frames, chunk)]


def _solve_chunks(solve_chunk, bounds, sink, supported) -> tuple[list[int], int, int]:
    """Solve the chunks, writing each to ``sink`` in order and marking the frames and points
    some view supports in ``supported`` ``(T, P)``; ``(iterations per chunk, observations kept,
    observations rejected)``."""
    iterations, kept_total, rejected_total = [], 0, 0
    # One BLAS thread for the whole solve (process-wide, so set once, not per chunk: threads
    # entering and leaving it would undo each other): the banded factorization's kernels are
    # tiny, and spinning OpenBLAS threads slow them many times over. Two chunk workers at most,
    # each at most one chunk ahead of the writer (memory flat); inline under one thread.
    with threadpool_limits(1, user_api="blas"):
        for lo, hi, its, active, rejected, points3d, err, clean, flags in thread_map(
            lambda bound: solve_chunk(*bound), bounds, 2
        ):
            iterations.append(its)
            supported[lo:hi] = active.any(axis=0)
            kept_total += int(active.sum())
            rejected_total += rejected
            sink.write(lo, hi, points3d, err, clean, flags)
    return iterations, kept_total, rejected_total


@dataclass(frozen=True, eq=False)
class _ChunkSolver:
    """Pass 2 of :func:`refine_stream`: one chunk's frames solved over its window."""

    source: Any
    grid: Grid
    layout: BlockLayout
    bones: np.ndarray
    lengths: np.ndarray
    rigid: np.ndarray
    centres: np.ndarray
    opts: RefinementParams
    fallback: np.ndarray
    scale: float
    overlap: int
    largest: int

    def __call__(self, lo: int, hi: int):
        """``(lo, hi, iterations, active, rejected, points3d, err, clean, flags)`` of ``lo:hi``."""
        opts = self.opts
        n_frames = self.source.n_frames
        window = min(self.largest, n_frames)
        a = min(max(lo - self.overlap, 0), n_frames - window)
        b = a + window
        pts2d, conf, start, inliers = self.source.read(a, b)
        observed, weight = _weights(pts2d, conf, opts)
        problem = ChunkProblem(
            self.grid,
            pts2d,
            weight,
            self.layout,
            self.bones,
            self.lengths,
            self.rigid,
            self.centres,
            opts,
            _bucket(b - a, self.largest),
        )
        first = observed.copy()
        if inliers is not None:
            first &= inliers | ~np.isfinite(start).all(-1)[None]
        problem.set_active(first)
        xs = problem.to_slots(fill_start(start, self.fallback))
        half = max(opts.max_iterations // 2, 1)
        xs, it1, err = problem.solve(xs, half)
        problem.set_active(observed & (problem.errors(err) < opts.outlier_px))
        xs, it2, err = problem.solve(xs, max(opts.max_iterations - it1, 1))
        keep = slice(lo - a, hi - a)
        active = problem.active[:, keep]
        points3d = problem.from_slots(xs)[keep]
        flags = _chunk_flags(points3d, start[keep], observed[:, keep], active, self.scale, opts)
        return (
            lo,
            hi,
            it1 + it2,
            active,
            int((observed[:, keep] & ~active).sum()),
            points3d,
            np.where(active, problem.errors(err)[:, keep], np.nan),
            np.where(active[..., None], pts2d[:, keep], np.nan),
            flags,
        )


def refine_points(
    pts2d: Float[np.ndarray, "V T P 2"],
    cameras: CameraGroup,
    start: Float[np.ndarray, "T P 3"],
    *,
    conf: Float[np.ndarray, "V T P"] | None = None,
    inliers: Bool[np.ndarray, "V T P"] | None = None,
    bones: Int[np.ndarray, "B 2"] | None = None,
    chains: list[list[int]] | None = None,
    mirror: Int[np.ndarray, " B"] | None = None,
    rigid: list[int] | Int[np.ndarray, " R"] = (),
    options: RefinementParams | None = None,
) -> RefinementResult:
    """Refine a whole recording's 3D jointly over frames and the skeleton.

    ``pts2d`` in raw-frame pixels, NaN = missing; ``start`` the triangulation, NaN = not
    reconstructed; ``conf`` weights when ``weigh_by_confidence``; ``inliers`` the views the
    triangulation kept, which the first pass uses alone (plus every view of points it left NaN;
    ``None``: every observation). ``bones``: point-index pairs of constant length, along the limb
    ``chains`` (every bone joins neighbouring points of one chain; default: each bone its own
    chain); ``mirror``: each bone's left/right twin, for ``symmetric_bones``; ``rigid``: points
    held at one world position (the tethered thorax); ``options``: the ``refinement`` table."""
    pts2d = np.asarray(pts2d, np.float64)
    start = np.asarray(start, np.float64)
    n_views, n_frames, n_points, _ = pts2d.shape
    if start.shape != (n_frames, n_points, 3):
        raise ValueError(f"start must be (T={n_frames}, P={n_points}, 3), got {start.shape}")
    sink = ArraySink(n_views, n_frames, n_points)
    out = refine_stream(
        ArraySource(pts2d, start, conf, inliers),
        cameras,
        sink,
        bones=bones,
        chains=chains,
        mirror=mirror,
        rigid=rigid,
        options=options,
    )
    return RefinementResult(
        sink.points3d,
        sink.reproj_error,
        sink.points2d,
        sink.flags,
        out["bone_lengths"],
        out["rigid_points"],
        out["rigid_centres"],
        out["info"],
    )


def _camera_rows(cameras) -> np.ndarray:
    """``(V, 10 + K)`` stacked ``[rvec, tvec, fx, fy, cx, cy, dist]`` (what the kernel reads)."""
    intrs = np.asarray(cameras.intrs, np.float64)
    if intrs.shape[1] == 3:
        intrs = np.stack([intrs[:, 0], intrs[:, 0], intrs[:, 1], intrs[:, 2]], axis=1)
    dists = np.asarray(cameras.dists, np.float64).reshape(len(intrs), -1)
    return np.concatenate(
        [
            np.asarray(cameras.rvecs, np.float64),
            np.asarray(cameras.tvecs, np.float64),
            intrs,
            dists,
        ],
        axis=1,
    )


def _runs_longer_than(mask: np.ndarray, length: int) -> np.ndarray:
    """``(T, P)`` bool: the frames inside runs of ``mask`` longer than ``length``."""
    out = np.zeros_like(mask)
    n = mask.shape[0]
    for p in range(mask.shape[1]):
        col = mask[:, p]
        if not col.any():
            continue
        edges = np.diff(np.concatenate([[0], col.astype(np.int8), [0]]))
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        for s, e in zip(starts, stops):
            if e - s > length:
                out[s : min(e, n), p] = True
    return out


def _chunk_flags(points3d, start, observed, kept, scale, opts: RefinementParams) -> np.ndarray:
    """Per-point flags of one chunk; an unsupported point is flagged ``filled`` until the
    recording-wide gap pass turns long gaps into ``missing``."""
    bit = {k: np.uint8(v[0]) for k, v in FLAG_BITS.items()}
    views = kept.sum(0)
    flags = np.where(views > 0, bit["observed"], bit["filled"]).astype(np.uint8)
    flags |= np.where(views == 1, bit["single_view"], 0).astype(np.uint8)
    flags |= np.where((observed & ~kept).any(0), bit["outlier_views"], 0).astype(np.uint8)
    started = np.isfinite(start).all(-1)
    flags |= np.where(~started, bit["no_start"], 0).astype(np.uint8)
    with np.errstate(invalid="ignore"):
        moved = np.linalg.norm(points3d - start, axis=-1) > opts.moved_fraction * scale
    flags |= np.where(started & moved, bit["moved"], 0).astype(np.uint8)
    return flags
