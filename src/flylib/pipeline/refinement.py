"""The refinement workflow stage: triangulation artifact + 2D + rig -> ``stages/refinement.h5``.

The artifact holds ``refinement/`` with

- ``points3d`` ``(T, P, 3)`` float64: the refined 3D (NaN: no view supports the point for more
  than ``gap_length`` frames);
- ``reproj_error`` ``(V, T, P)`` float64: pixel error of every observation kept;
- ``points`` ``(V, T, P, 2)`` float64: the observations kept (rejected outliers NaN);
- ``flags`` ``(T, P)`` uint8: per-point bit flags, their meaning in the group's ``flag_bits``
  attribute (JSON ``{name: [bit, meaning]}``, see :data:`flylib.refinement.FLAG_BITS`);

and attributes ``bone_lengths`` (``{"a-b": length}``), ``rigid_centres``
(``{point: [x, y, z]}``), ``summary`` (timings, iterations, observations kept and rejected),
``options`` (the ``refinement`` table in force) and ``accuracy``.

Refinement never makes a recording worse by the truth-free yardstick of :mod:`flylib.accuracy`
(:class:`~flylib.refinement.held_out.HeldOutCheck`): each view is held out in turn and both
solves re-run without it (on at most :data:`~flylib.accuracy.EVALUATION_FRAMES` frames), the
refinement once per smoothness scale (``smooth_scale`` and ``motion_scales`` times the
recording's per-frame motion); the recording is solved at the scale of lowest held-out error.
A point whose refined held-out error (median or 95th percentile) is higher than the
triangulation's (one no held-out view checks: over the points checked) keeps the
triangulation's 3D, 2D and errors, flagged ``kept_triangulation``; if the output is still
worse overall, every point does. The ``accuracy`` attribute holds the three summaries
(``triangulation``, ``refinement`` as solved, ``output``), the points kept and the frames.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from ..config import TriangulationParams
from ..config.params import build_params
from ..config.postprocessing import RefinementParams
from ..paths import atomic_path
from ..refinement.solver import FLAG_BITS, ArraySink
from ..stages import Stage
from .inputs import RigSpec, SkeletonSpec, StageInputs, register
from .stage_helpers import RigRuntime, tracked_rig
from .triangulation import triangulation_method

if TYPE_CHECKING:  # pragma: no cover
    from ..camera.rig import CameraGroup
    from ..config import Config

RECORD = Stage(
    "refinement",
    default_on=True,
    after=("triangulation",),
    needs_one_of=("triangulation",),
    params=RefinementParams,
    artifact="refinement.h5",
    results_group=True,
    solves_3d=True,
    hint="check triangulation's 3D (flylib inspect) and the refinement settings, or "
    "set pipeline.do_refinement: false",
    memory=(410, 140),
)

STAGE = RECORD.name


@register
@dataclass(frozen=True)
class RefinementInputs(StageInputs):
    """What the refinement stage reads. ``triangulation`` is tracked because the held-out
    check re-runs it; ``rig`` is ``None`` with bundle adjustment on (rig from its artifact)."""

    STAGE = STAGE  # not a field: the base declares it a ClassVar

    refinement: RefinementParams
    triangulation: TriangulationParams
    skeleton: SkeletonSpec
    rig: RigSpec | None
    runtime: RigRuntime = RigRuntime()

    @classmethod
    def from_config(cls, config: Config) -> RefinementInputs:
        rig = tracked_rig(config)
        return cls(
            refinement=config.refinement,
            triangulation=_triangulation(config.triangulation.method_params()),
            skeleton=SkeletonSpec.from_config(config),
            rig=rig,
            runtime=RigRuntime.from_config(config),
        )


def _triangulation(method_params: Mapping) -> TriangulationParams:
    """The method and the knobs it reads (the others at defaults it never reads)."""
    return build_params(TriangulationParams, method_params)


class TriangulationSource:
    """The refinement's input, read on demand (h5py datasets or arrays): the 2D and
    confidences with the manual corrections applied (``corrected_2d``/``edited_2d``, as
    :meth:`~flylib.corrections.Corrections.apply_2d` does), the triangulation's 3D as the
    start and its inlier views (its kept 2D)."""

    def __init__(self, pose2d: Mapping[str, Any], triangulation: Mapping[str, Any]):
        self.pts2d = pose2d["points"]
        self.conf = pose2d.get("conf", None)
        self.start = triangulation["points3d"]
        self.inlier_2d = triangulation["points"]
        self.n_views, self.n_frames, self.n_points = self.pts2d.shape[:3]
        self.touched = triangulation["corrected_2d"] if "corrected_2d" in triangulation else None
        self.edited = None
        if self.touched is not None:
            if "edited_2d" not in triangulation:
                from ..errors import ResultsError

                raise ResultsError(
                    "the triangulation artifact marks corrected 2D (corrected_2d) but holds "
                    "no edited_2d (written by an older flylib); re-run the triangulation "
                    "stage (delete stages/triangulation.h5)"
                )
            self.edited = triangulation["edited_2d"]

    def read(self, lo: int, hi: int):
        pts2d = np.asarray(self.pts2d[:, lo:hi], np.float64)
        conf = None if self.conf is None else np.asarray(self.conf[:, lo:hi], np.float64)
        if self.touched is not None:
            touched = np.asarray(self.touched[:, lo:hi], bool)
            edited = np.asarray(self.edited[:, lo:hi], np.float64)
            pts2d = np.where(touched[..., None], edited, pts2d)
            if conf is not None:
                given = np.isfinite(edited).all(-1)
                conf = np.where(touched, np.where(given, 1.0, np.nan), conf)
        inliers = np.isfinite(self.inlier_2d[:, lo:hi]).all(-1)
        return (
            pts2d,
            conf,
            np.asarray(self.start[lo:hi], np.float64),
            inliers,
        )


class H5Sink(ArraySink):
    """:class:`ArraySink` over HDF5 datasets (chunked along time, gzip), written chunk by chunk."""

    def __init__(self, group: h5py.Group, n_views: int, n_frames: int, n_points: int, chunk: int):
        step = max(1, min(n_frames, chunk))
        from ..results import datasets  # its checksum switch, read now (tests turn it off)

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
                fletcher32=datasets.FLETCHER32,
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


def run_refinement(
    inputs: RefinementInputs,
    pose2d_path: str | Path,
    triangulation_path: str | Path,
    out_path: str | Path,
    *,
    ba_path: str | Path | None = None,
    recording_dir: str | Path | None = None,
) -> Path:
    """Refine one recording's triangulated 3D into ``stages/refinement.h5``, chunk by chunk
    (memory does not grow with length). ``ba_path`` (its rig) is required when ``inputs.rig``
    is ``None``; ``recording_dir`` is where a relative calibration file is looked up."""
    from ..provenance import stage_provenance
    from ..results import new_meta, open_checked
    from .stage_helpers import solving

    with solving(STAGE, recording_dir or triangulation_path):
        cameras = refinement_rig(inputs, pose2d_path, ba_path, recording_dir)
        with (
            open_checked(pose2d_path, "re-run the pose2d stage") as p2d,
            open_checked(triangulation_path, "re-run the triangulation stage") as tri,
        ):
            _check_shapes(p2d, tri)
            with atomic_path(out_path) as tmp, h5py.File(tmp, "w") as f:
                upstream = {
                    "pose2d": pose2d_path,
                    "triangulation": triangulation_path,
                    "bundle_adjustment": ba_path,
                }
                f.attrs["meta"] = json.dumps(
                    new_meta(STAGE, stage_provenance(inputs.canonical_params(), STAGE, upstream))
                )
                group = f.create_group(STAGE)
                n_views, n_frames, n_points = p2d["pose2d/points"].shape[:3]
                sink = H5Sink(group, n_views, n_frames, n_points, inputs.refinement.chunk_frames)
                attrs = compute_refinement(
                    inputs, cameras, p2d["pose2d"], tri["triangulation"], sink
                )
                for key, value in attrs.items():
                    group.attrs[key] = json.dumps(value)
    return Path(out_path)


def refinement_rig(inputs: RefinementInputs, pose2d_path, ba_path, recording_dir) -> CameraGroup:
    """The bundle-adjustment artifact's rig when given, else the config rig."""
    from ..errors import ConfigError
    from ..results import read_image_sizes, read_stage

    if ba_path:
        return read_stage(ba_path, "bundle_adjustment")["cameras"]
    if inputs.rig is None:
        raise ConfigError(
            "refinement: pipeline.do_bundle_adjustment is on, so the rig comes from the "
            "bundle-adjustment artifact: pass it (--bundle-adjustment), or set "
            "pipeline.do_bundle_adjustment: false"
        )
    return inputs.rig.camera_group(read_image_sizes(pose2d_path), recording_dir)


def _check_shapes(pose2d: h5py.File, triangulation: h5py.File) -> None:
    """The triangulation's 3D must be of the 2D's frames and points."""
    shape = pose2d["pose2d/points"].shape
    start = triangulation["triangulation/points3d"].shape
    if start != (shape[1], shape[2], 3):
        from ..errors import ResultsError

        raise ResultsError(
            f"{triangulation.filename}: 3D of shape {start} does not match the "
            f"2D {shape}; re-run the triangulation stage"
        )


def compute_refinement(
    inputs: RefinementInputs,
    cameras: CameraGroup,
    pose2d: Mapping[str, Any],
    triangulation: Mapping[str, Any],
    sink: ArraySink,
) -> dict:
    """Refine the triangulation's 3D (no file I/O: ``sink`` takes ``points3d``,
    ``reproj_error``, ``points2d``, ``flags``) and return the group's attributes.

    ``pose2d``: ``points`` ``(V, T, P, 2)``, optionally ``conf`` ``(V, T, P)``;
    ``triangulation``: ``points3d`` ``(T, P, 3)`` (the start), ``points`` ``(V, T, P, 2)``
    (its inlier views), ``reproj_error`` ``(V, T, P)``, optionally ``corrected`` ``(T, P)``;
    arrays or h5py datasets (read window by window).
    """
    from ..refinement.held_out import HeldOutCheck, keep_corrected, refinement_method
    from ..refinement.setup import skeleton_terms
    from ..refinement.solver import refine_stream

    params = inputs.refinement
    skeleton = inputs.skeleton.skeleton()
    terms = skeleton_terms(skeleton, params.rigid_points)
    source = TriangulationSource(pose2d, triangulation)
    check = HeldOutCheck(
        cameras,
        source.pts2d,
        source.conf,
        source.start,
        triangulation_method(inputs.triangulation, cameras),
        lambda scale: refinement_method(replace(params, smooth_scale=scale), cameras, skeleton),
        params,
        params.motion_scales,
        terms,
        skeleton.point_names,
    )
    options = check.options
    out = refine_stream(source, cameras, sink, options=options, **terms)
    keep_corrected(triangulation, sink, params.chunk_frames)
    accuracy = check.apply(sink, triangulation)
    # the artifact's record of the solver's settings, kept in its old layout: without
    # motion_scales, rigid_points last
    record = {
        k: v for k, v in asdict(options).items() if k not in ("motion_scales", "rigid_points")
    }
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
    return attrs
