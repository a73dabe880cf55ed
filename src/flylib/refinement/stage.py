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
:mod:`flylib.accuracy`: after the solve, every view is held out in turn and both the
triangulation and the refinement are re-solved without it (on at most
:data:`~flylib.accuracy.EVALUATION_FRAMES` frames). A point whose refined held-out-view
error (median or 95th percentile) is higher than the triangulation's keeps the
triangulation's 3D, 2D and errors in every frame, flagged ``kept_triangulation``; if
the output is still worse overall, every point does. The ``accuracy`` attribute holds
the three summaries (``triangulation``, ``refinement`` as solved, ``output``), the
points kept and the frames evaluated.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import h5py
import numpy as np

from ..paths import atomic_path
from .setup import options_from_params
from .solver import FLAG_BITS, ArraySink, RefinementResult

STAGE = "refinement"


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
    from ..interop.anipose import config_rig
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
                        config,
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
            out = refine_stream(source, cameras, sink, options=options, **terms)
            _keep_corrected(tri, group)
            accuracy = _held_out_check(config, cameras, source, tri, group, terms, options)
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


def _held_out_check(config, cameras, source, tri, group, terms, options) -> dict:
    """Hold each view out, compare refinement with triangulation, keep the triangulation
    where refinement is not better (see the module doc); returns the ``accuracy`` attrs."""
    from ..accuracy import (
        accuracy_summary,
        evaluation_windows,
        held_out_errors,
        keep_triangulation,
        triangulation_method,
    )
    from .solver import refine_points

    triangulate = triangulation_method(config, cameras)

    def refine(pts2d, conf, start, kept):
        return refine_points(
            pts2d, cameras, start, conf=conf, inliers=kept, options=options, **terms
        ).points3d

    windows = evaluation_windows(source.n_frames)
    held = held_out_errors(
        cameras, source.pts2d, triangulate, conf=source.conf, refine=refine, windows=windows
    )
    keep, everywhere = keep_triangulation(held["triangulation"], held["refinement"])
    frames = held["frames"]

    def on_windows(dataset) -> np.ndarray:  # the evaluated frames only: memory stays flat
        parts = [np.asarray(dataset[lo:hi], np.float64) for lo, hi in windows]
        return np.concatenate(parts) if parts else np.zeros((0, source.n_points, 3))

    refined3d = on_windows(group["points3d"])
    tri3d = on_windows(tri["triangulation/points3d"])
    if keep.any():
        _keep_triangulation_points(tri, group, keep, options.chunk_frames)
    both = np.isfinite(held["triangulation"]) & np.isfinite(held["refinement"])
    chosen = np.where(keep[None, None], held["triangulation"], held["refinement"])
    skeleton = config.skeleton()
    names = dict(view_names=list(cameras.names), point_names=list(skeleton.point_names))
    shape = dict(bones=terms["bones"], mirror=terms["mirror"])
    output3d = np.where(keep[None, :, None], tri3d, refined3d)
    result = {
        "frames_evaluated": int(len(frames)),
        "frames_total": int(source.n_frames),
        "windows": [list(w) for w in windows],
        "compared_on": "observations both methods reconstructed without the view",
        "triangulation": accuracy_summary(
            np.where(both, held["triangulation"], np.nan), tri3d, **names, **shape
        ),
        "refinement": accuracy_summary(
            np.where(both, held["refinement"], np.nan), refined3d, **names, **shape
        ),
        "output": accuracy_summary(np.where(both, chosen, np.nan), output3d, **names, **shape),
        "kept_triangulation": [skeleton.point_names[p] for p in np.flatnonzero(keep)],
        "kept_everywhere": bool(everywhere),
    }
    return result


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
