"""The refinement workflow stage: triangulation artifact + 2D + rig -> ``stages/refinement.h5``.

The artifact holds ``refinement/`` with

- ``points3d`` ``(T, P, 3)`` float64: the refined 3D (NaN: no view supports the point
  for more than ``gap_length`` frames);
- ``reproj_error`` ``(V, T, P)`` float64: pixel error of every observation kept;
- ``points`` ``(V, T, P, 2)`` float64: the observations kept (rejected outliers NaN);
- ``flags`` ``(T, P)`` uint8: per-point bit flags, their meaning in the group's
  ``flag_bits`` attribute (JSON ``{name: [bit, meaning]}``, see
  :data:`flylib.refinement.FLAG_BITS`);

and attributes ``bone_lengths`` (``{"a-b": length}``), ``rigid_centres``
(``{point: [x, y, z]}``), ``summary`` (timings, iterations, observations kept and
rejected), ``options`` (the ``refinement`` table in force) and ``accuracy``.

Refinement never makes a recording worse by the truth-free yardstick of
:mod:`flylib.accuracy` (:class:`HeldOutCheck`): every view is held out in turn and
both the triangulation and the refinement are re-solved without it (on at most
:data:`~flylib.accuracy.EVALUATION_FRAMES` frames), the refinement once per candidate
smoothness scale (``smooth_scale`` and ``motion_scales`` times the recording's own
per-frame motion, which carries the frame rate); the whole recording is then solved
at the scale of lowest held-out error. A point whose refined held-out-view
error (median or 95th percentile) is higher than the triangulation's keeps the
triangulation's 3D, 2D and errors in every frame, flagged ``kept_triangulation``; if
the output is still worse overall, every point does. The ``accuracy`` attribute holds
the three summaries (``triangulation``, ``refinement`` as solved, ``output``), the
points kept and the frames evaluated.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, replace
from pathlib import Path

import h5py
import numpy as np

from ..paths import atomic_path
from .setup import options_from_params
from .solver import FLAG_BITS, ArraySink, RefinementResult

STAGE = "refinement"

log = logging.getLogger(__name__)


class H5Source:
    """Chunks of the pose2d and triangulation artifacts, read on demand (h5py slices)."""

    def __init__(self, pose2d: h5py.File, triangulation: h5py.File):
        self.pts2d = pose2d["pose2d/points"]
        self.conf = pose2d.get("pose2d/conf", None)
        self.start = triangulation["triangulation/points3d"]
        self.inlier_2d = triangulation["triangulation/points"]
        self.n_views, self.n_frames, self.n_points = self.pts2d.shape[:3]
        if self.start.shape != (self.n_frames, self.n_points, 3):
            from ..errors import ResultsError

            raise ResultsError(
                f"{triangulation.filename}: 3D of shape {self.start.shape} does not match the "
                f"2D {self.pts2d.shape}; re-run the triangulation stage"
            )

    def read(self, lo: int, hi: int):
        conf = None if self.conf is None else self.conf[:, lo:hi].astype(np.float64)
        inliers = np.isfinite(self.inlier_2d[:, lo:hi]).all(-1)
        return (
            self.pts2d[:, lo:hi].astype(np.float64),
            conf,
            self.start[lo:hi].astype(np.float64),
            inliers,
        )


class H5Sink(ArraySink):
    """Writes the refinement group chunk by chunk (datasets chunked along time, gzip);
    :class:`ArraySink`'s methods over HDF5 datasets instead of arrays."""

    def __init__(self, group: h5py.Group, n_views: int, n_frames: int, n_points: int, chunk: int):
        step = max(1, min(n_frames, chunk))

        from .. import results as results_module

        def make(name, shape, dtype, axis, fill):
            chunks = list(shape)
            chunks[axis] = step
            return group.create_dataset(
                name,
                shape=shape,
                dtype=dtype,
                chunks=tuple(chunks),
                compression="gzip",
                compression_opts=1,
                fillvalue=fill,
                fletcher32=results_module._FLETCHER32,
            )

        self.points3d = make("points3d", (n_frames, n_points, 3), np.float64, 0, np.nan)
        self.reproj_error = make(
            "reproj_error", (n_views, n_frames, n_points), np.float64, 1, np.nan
        )
        self.points2d = make("points", (n_views, n_frames, n_points, 2), np.float64, 1, np.nan)
        self.flags = make("flags", (n_frames, n_points), np.uint8, 0, 0)


def _attrs(skeleton, lengths, rigid_points, rigid_centres, info, options) -> dict:
    names = list(skeleton.point_names)
    bones = {
        f"{names[i]}-{names[j]}": (None if not np.isfinite(v) else float(v))
        for (i, j), v in zip(np.asarray(skeleton.bones), lengths)
    }
    centres = {
        names[p]: [float(c) for c in centre] for p, centre in zip(rigid_points, rigid_centres)
    }
    return {
        "flag_bits": {k: list(v) for k, v in FLAG_BITS.items()},
        "bone_lengths": bones,
        "rigid_centres": centres,
        "summary": info,
        "options": options,
    }


def write_refinement(path: str | Path, result: RefinementResult, skeleton, options: dict) -> None:
    """Write an in-memory :class:`RefinementResult` as the refinement artifact (atomically)."""
    from ..results import _new_meta, _write_array

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["meta"] = json.dumps(_new_meta(STAGE))
        group = f.create_group(STAGE)
        _write_array(group, "points3d", result.points3d)
        _write_array(group, "reproj_error", result.reproj_error)
        _write_array(group, "points", result.points2d)
        _write_array(group, "flags", result.flags, dtype=np.uint8)
        attrs = _attrs(
            skeleton,
            result.bone_lengths,
            result.rigid_points,
            result.rigid_centres,
            result.info,
            options,
        )
        for key, value in attrs.items():
            group.attrs[key] = json.dumps(value)


def run_refinement(
    config,
    pose2d_path: str | Path,
    triangulation_path: str | Path,
    out_path: str | Path,
    *,
    ba_path: str | Path | None = None,
    recording_dir: str | Path | None = None,
) -> Path:
    """Refine the triangulated 3D of one recording and write ``stages/refinement.h5``.

    The artifacts are read and the result written chunk by chunk, so memory does not
    grow with the recording's length.

    Parameters
    ----------
    config
        The run's :class:`~flylib.config.Config` (its ``refinement`` table and skeleton).
    pose2d_path
        The pose2d artifact: every 2D observation and its confidence.
    triangulation_path
        The triangulation artifact: the starting 3D and its inlier views.
    out_path
        Where to write.
    ba_path
        The bundle-adjustment artifact (its rig); default the config rig.
    recording_dir
        The recording (for a calibration file relative to it).
    """
    from ..pipeline.planning import config_rig, tracked_params
    from ..provenance import stage_provenance
    from ..results import _new_meta, open_checked, read_image_sizes
    from .setup import skeleton_terms
    from .solver import refine_stream

    if ba_path:
        from ..results import read_stage

        cameras = read_stage(ba_path, "bundle_adjustment")["cameras"]
    else:
        cameras = config_rig(config, read_image_sizes(pose2d_path), recording_dir)
    params = config.refinement
    skeleton = config.skeleton()
    terms = skeleton_terms(skeleton, params.rigid_points)
    options = options_from_params(params)
    with (
        open_checked(pose2d_path, "re-run the pose2d stage") as p2d,
        open_checked(triangulation_path, "re-run the triangulation stage") as tri,
    ):
        source = H5Source(p2d, tri)
        with atomic_path(out_path) as tmp, h5py.File(tmp, "w") as f:
            f.attrs["meta"] = json.dumps(
                _new_meta(
                    STAGE,
                    stage_provenance(
                        tracked_params(config, STAGE),
                        STAGE,
                        {
                            "pose2d": pose2d_path,
                            "triangulation": triangulation_path,
                            "bundle_adjustment": ba_path,
                        },
                    ),
                )
            )
            group = f.create_group(STAGE)
            sink = H5Sink(
                group, source.n_views, source.n_frames, source.n_points, options.chunk_frames
            )
            check = HeldOutCheck(config, cameras, source, tri, terms, options)
            options = check.options
            out = refine_stream(source, cameras, sink, options=options, **terms)
            _keep_corrected(tri, group)
            accuracy = check.apply(group)
            record = asdict(options)
            record["rigid_points"] = [skeleton.point_names[p] for p in out["rigid_points"]]
            attrs = _attrs(
                skeleton,
                out["bone_lengths"],
                out["rigid_points"],
                out["rigid_centres"],
                out["info"],
                record,
            )
            attrs["accuracy"] = accuracy
            for key, value in attrs.items():
                group.attrs[key] = json.dumps(value)
    return Path(out_path)


class HeldOutCheck:
    """The held-out-view check around the refinement solve (see the module doc).

    Before the solve it judges, on :func:`~flylib.accuracy.evaluation_windows`, the
    triangulation and the refinement at each candidate smoothness scale (the config's
    ``smooth_scale``, and ``motion_scales`` times the recording's own motion) with each
    view held out, and picks the scale of lowest held-out error (:attr:`options`);
    after the solve, :meth:`apply` keeps the triangulation where that refinement lost.
    """

    def __init__(self, config, cameras, source, tri: h5py.File, terms: dict, options):
        from ..accuracy import evaluation_windows, held_out_errors, triangulation_method
        from .solver import recording_motion

        self.config, self.cameras, self.source = config, cameras, source
        self.tri, self.terms = tri, terms
        self.windows = evaluation_windows(source.n_frames)
        start = tri["triangulation/points3d"]
        motions = [
            recording_motion(np.asarray(start[lo:hi], np.float64), options.smooth_order)
            for lo, hi in self.windows
        ]
        motions = [m for m in motions if np.isfinite(m) and m > 0]
        self.motion = float(np.median(motions)) if motions else None
        scales = {float(options.smooth_scale)}
        if self.motion:
            scales |= {float(k * self.motion) for k in config.refinement.motion_scales}
        variants = {
            scale: self._refine(replace(options, smooth_scale=scale)) for scale in sorted(scales)
        }
        self.held = held_out_errors(
            cameras,
            source.pts2d,
            triangulation_method(config, cameras),
            conf=source.conf,
            refine=variants,
            windows=self.windows,
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

    def _refine(self, options):
        from .solver import refine_points

        cameras, terms = self.cameras, self.terms

        def refine(pts2d, conf, start, kept):
            return refine_points(
                pts2d, cameras, start, conf=conf, inliers=kept, options=options, **terms
            ).points3d

        return refine

    def apply(self, group: h5py.Group) -> dict:
        """Keep the triangulation where the chosen refinement lost (in ``group``, the
        artifact being written); returns the ``accuracy`` attrs."""
        from ..accuracy import accuracy_summary, keep_triangulation

        tri_err = self.held["triangulation"]
        ref_err = self.held["refinement"][self.scale]
        keep, everywhere = keep_triangulation(tri_err, ref_err)
        n_points = self.source.n_points

        def on_windows(dataset) -> np.ndarray:  # the evaluated frames only: memory stays flat
            parts = [np.asarray(dataset[lo:hi], np.float64) for lo, hi in self.windows]
            return np.concatenate(parts) if parts else np.zeros((0, n_points, 3))

        refined3d = on_windows(group["points3d"])
        tri3d = on_windows(self.tri["triangulation/points3d"])
        if keep.any():
            _keep_triangulation_points(self.tri, group, keep, self.options.chunk_frames)
        both = np.isfinite(tri_err) & np.isfinite(ref_err)
        chosen = np.where(keep[None, None], tri_err, ref_err)
        skeleton = self.config.skeleton()
        names = dict(view_names=list(self.cameras.names), point_names=list(skeleton.point_names))
        shape = dict(bones=self.terms["bones"], mirror=self.terms["mirror"])
        output3d = np.where(keep[None, :, None], tri3d, refined3d)

        def summary(err, pts3d):
            return accuracy_summary(np.where(both, err, np.nan), pts3d, **names, **shape)

        return {
            "frames_evaluated": int(len(self.held["frames"])),
            "frames_total": int(self.source.n_frames),
            "windows": [list(w) for w in self.windows],
            "compared_on": "observations both methods reconstructed without the view",
            "triangulation": summary(tri_err, tri3d),
            "refinement": summary(ref_err, refined3d),
            "output": summary(chosen, output3d),
            "kept_triangulation": [skeleton.point_names[p] for p in np.flatnonzero(keep)],
            "kept_everywhere": bool(everywhere),
            "smoothness": {
                "motion_per_frame": self.motion,
                "scale": self.scale,
                "tried": {f"{k:.6g}": {"median": v[0], "p95": v[1]} for k, v in self.tried.items()},
            },
        }


def _keep_triangulation_points(tri: h5py.File, group: h5py.Group, keep: np.ndarray, chunk: int):
    """Points ``keep`` ``(P,)`` take the triangulation's 3D, 2D and errors in every frame,
    flagged ``kept_triangulation`` (chunk by chunk along time)."""
    bit = np.uint8(FLAG_BITS["kept_triangulation"][0])
    n_frames = group["points3d"].shape[0]
    step = max(1, int(chunk))
    for lo in range(0, n_frames, step):
        hi = min(lo + step, n_frames)
        for name, axis in (("points3d", 0), ("reproj_error", 1), ("points", 1)):
            source = tri[f"triangulation/{name}"]
            if axis == 0:
                values = group[name][lo:hi]
                values[:, keep] = source[lo:hi][:, keep]
                group[name][lo:hi] = values
            else:
                values = group[name][:, lo:hi]
                values[:, :, keep] = source[:, lo:hi][:, :, keep]
                group[name][:, lo:hi] = values
        flags = group["flags"][lo:hi]
        flags[:, keep] |= bit
        group["flags"][lo:hi] = flags


def _keep_corrected(tri: h5py.File, group: h5py.Group) -> None:
    """Points a person corrected (``triangulation/corrected``, from a ``corrections.h5``)
    keep the triangulation's 3D: a person's call is not smoothed away."""
    if "triangulation/corrected" not in tri:
        return
    corrected = np.asarray(tri["triangulation/corrected"][()], bool)
    if not corrected.any():
        return
    points = group["points3d"][()]
    points[corrected] = np.asarray(tri["triangulation/points3d"][()], float)[corrected]
    group["points3d"][...] = points
