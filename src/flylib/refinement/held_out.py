"""Refinement that never makes a recording worse by the held-out-view yardstick
(:class:`HeldOutCheck`), nor overrides a person's corrections (:func:`keep_corrected`). Every
array here may be an h5py dataset (read and written window by window) or a NumPy array."""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from .setup import skeleton_terms
from .solver import FLAG_BITS, refine_points

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

    from ..accuracy import Refine, Triangulate
    from ..camera.rig import CameraGroup
    from ..config.postprocessing import RefinementParams
    from ..skeleton import Skeleton

log = logging.getLogger(__name__)

#: The refinement output's arrays (sink attributes), the triangulation's of the same layout,
#: and the axis time runs along.
_KEPT_ARRAYS = (
    ("points3d", "points3d", 0),
    ("reproj_error", "reproj_error", 1),
    ("points2d", "points", 1),
)


def refinement_method(params: RefinementParams, cameras: CameraGroup, skeleton: Skeleton) -> Refine:
    """The refinement stage's 3D method as :func:`flylib.accuracy.held_out_errors` calls it
    (the ``refinement`` table and the skeleton's bones and rigid points)."""
    terms = skeleton_terms(skeleton, params.rigid_points)

    def refine(pts2d, conf, start, kept):
        return refine_points(
            pts2d, cameras, start, conf=conf, inliers=kept, options=params, **terms
        ).points3d

    return refine


class HeldOutCheck:
    """The held-out-view check around the refinement solve.

    Before the solve it judges, on :func:`~flylib.accuracy.evaluation_windows`, the triangulation
    (``triangulate``, the stage's method; ``start`` its 3D) and the refinement (``refine_at``:
    ``smooth_scale -> Refine``, :func:`refinement_method`) at each candidate smoothness scale
    (``options``' ``smooth_scale``, and ``motion_scales`` times the recording's own motion) with
    each view held out, and picks the scale of lowest held-out error (:attr:`options`); after the
    solve, :meth:`apply` keeps the triangulation where that refinement lost. ``terms``:
    :func:`~flylib.refinement.skeleton_terms` (its ``bones`` and ``mirror`` make the summaries'
    bone figures)."""

    def __init__(
        self,
        cameras: CameraGroup,
        pts2d: Float[np.ndarray, "V T P 2"],
        conf: Float[np.ndarray, "V T P"] | None,
        start: Float[np.ndarray, "T P 3"],
        triangulate: Triangulate,
        refine_at: Callable[[float], Refine],
        options: RefinementParams,
        motion_scales: Sequence[float],
        terms: Mapping[str, Any],
        point_names: Sequence[str],
    ):
        from ..accuracy import evaluation_windows, held_out_errors
        from .solver import recording_motion

        self.cameras, self.terms, self.point_names = cameras, terms, list(point_names)
        self.n_frames, self.n_points = start.shape[0], start.shape[1]
        self.windows = evaluation_windows(self.n_frames)
        motions = [
            recording_motion(np.asarray(start[lo:hi], np.float64), options.smooth_order)
            for lo, hi in self.windows
        ]
        motions = [m for m in motions if np.isfinite(m) and m > 0]
        self.motion = float(np.median(motions)) if motions else None
        scales = {float(options.smooth_scale)}
        if self.motion:
            scales |= {float(k * self.motion) for k in motion_scales}
        variants = {scale: refine_at(scale) for scale in sorted(scales)}
        self.held = held_out_errors(
            cameras, pts2d, triangulate, conf=conf, refine=variants, windows=self.windows
        )
        common = np.isfinite(self.held["triangulation"])
        for err in self.held["refinement"].values():
            common &= np.isfinite(err)
        self.tried: dict[float, tuple[float, float]] = {}
        for scale, err in self.held["refinement"].items():
            values = err[common]
            self.tried[scale] = (
                (float(np.median(values)), float(np.percentile(values, 95)))
                if values.size
                else (np.inf, np.inf)
            )
        # lowest held-out median, then p95; on a tie the configured scale
        self.scale = min(self.tried, key=lambda k: (*self.tried[k], k != options.smooth_scale))
        self.options = replace(options, smooth_scale=self.scale)
        log.info(
            "refinement: smoothness scale %.4g (motion %s per frame^%d; held-out median px "
            "by scale %s)",
            self.scale,
            f"{self.motion:.4g}" if self.motion else "unknown",
            options.smooth_order,
            {f"{k:.4g}": round(v[0], 3) for k, v in self.tried.items()},
        )

    def apply(self, output, triangulation: Mapping[str, Any]) -> dict:
        """Keep the triangulation where the chosen refinement lost; returns the refinement
        artifact's ``accuracy`` attribute. ``output``: the refinement's output being written (an
        :class:`~flylib.refinement.solver.ArraySink` or one of its kind), changed in place;
        ``triangulation`` has ``points3d``, ``reproj_error`` and ``points``."""
        from ..accuracy import accuracy_summary, keep_triangulation

        tri_err = self.held["triangulation"]
        ref_err = self.held["refinement"][self.scale]
        keep, everywhere = keep_triangulation(tri_err, ref_err)
        n_points = self.n_points

        def on_windows(dataset) -> np.ndarray:  # the evaluated frames only: memory stays flat
            parts = [np.asarray(dataset[lo:hi], np.float64) for lo, hi in self.windows]
            return np.concatenate(parts) if parts else np.zeros((0, n_points, 3))

        refined3d = on_windows(output.points3d)
        tri3d = on_windows(triangulation["points3d"])
        if keep.any():
            keep_triangulation_points(triangulation, output, keep, self.options.chunk_frames)
        both = np.isfinite(tri_err) & np.isfinite(ref_err)
        chosen = np.where(keep[None, None], tri_err, ref_err)
        names = dict(view_names=list(self.cameras.names), point_names=self.point_names)
        shape = dict(bones=self.terms["bones"], mirror=self.terms["mirror"])
        output3d = np.where(keep[None, :, None], tri3d, refined3d)

        def summary(err, pts3d):
            return accuracy_summary(np.where(both, err, np.nan), pts3d, **names, **shape)

        return {
            "frames_evaluated": int(len(self.held["frames"])),
            "frames_total": int(self.n_frames),
            "windows": [list(w) for w in self.windows],
            "compared_on": "observations both methods reconstructed without the view",
            "triangulation": summary(tri_err, tri3d),
            "refinement": summary(ref_err, refined3d),
            "output": summary(chosen, output3d),
            "kept_triangulation": [self.point_names[p] for p in np.flatnonzero(keep)],
            "kept_everywhere": bool(everywhere),
            "smoothness": {
                "motion_per_frame": self.motion,
                "scale": self.scale,
                "tried": {f"{k:.6g}": {"median": v[0], "p95": v[1]} for k, v in self.tried.items()},
            },
        }


def keep_triangulation_points(
    triangulation: Mapping[str, Any], output, keep: Bool[np.ndarray, " P"], chunk: int
) -> None:
    """Points ``keep`` ``(P,)`` take the triangulation's everywhere (:func:`take_triangulation`)."""
    keep = np.asarray(keep, bool)
    take_triangulation(
        triangulation, output, lambda lo, hi: np.broadcast_to(keep, (hi - lo, keep.size)), chunk
    )


def keep_corrected(triangulation: Mapping[str, Any], output, chunk: int = 1024) -> None:
    """Points a person corrected (the triangulation's ``corrected`` ``(T, P)``, from a
    ``corrections.h5``) keep the triangulation's 3D, 2D and errors, flagged ``kept_triangulation``:
    a person's call is not smoothed away (``output`` as in :meth:`HeldOutCheck.apply`)."""
    if "corrected" not in triangulation:
        return
    corrected = triangulation["corrected"]
    take_triangulation(
        triangulation, output, lambda lo, hi: np.asarray(corrected[lo:hi], bool), chunk
    )


def take_triangulation(
    triangulation: Mapping[str, Any],
    output,
    select: Callable[[int, int], Bool[np.ndarray, "T P"]],
    chunk: int,
) -> None:
    """The ``(frame, point)`` entries ``select(lo, hi)`` picks in frames ``lo:hi`` take the
    triangulation's 3D, 2D and errors together (a result never pairs one stage's 3D with another's
    2D), flagged ``kept_triangulation``, their NaN-derived flags
    (:func:`~flylib.refinement.solver.flags_from_nan`) recomputed from what they now hold."""
    from .solver import flags_from_nan

    bit = np.uint8(FLAG_BITS["kept_triangulation"][0])
    n_frames = output.points3d.shape[0]
    step = max(1, int(chunk))
    for lo in range(0, n_frames, step):
        hi = min(lo + step, n_frames)
        mask = np.asarray(select(lo, hi), bool)
        if not mask.any():
            continue
        for name, source_name, axis in _KEPT_ARRAYS:
            source, target = triangulation[source_name], getattr(output, name)
            frames = (slice(None),) * axis + (slice(lo, hi),)
            picked = (slice(None),) * axis + (mask,)
            values = np.array(target[frames])
            values[picked] = np.asarray(source[frames])[picked]
            target[frames] = values
        flags = np.array(output.flags[lo:hi])
        redone = flags_from_nan(
            flags, np.asarray(output.points2d[:, lo:hi]), np.asarray(output.points3d[lo:hi])
        )
        flags = np.where(mask, redone | bit, flags).astype(np.uint8)
        output.flags[lo:hi] = flags
