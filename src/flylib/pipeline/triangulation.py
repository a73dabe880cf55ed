"""The triangulation stage: 2D (PS's when it ran, else pose2d's) + rig + manual corrections ->
3D, judged by its held-out-view error (:func:`flylib.accuracy.triangulation_accuracy`), in
``<outdir>/stages/triangulation.h5``."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config.params import TriangulationParams, build_params
from ..errors import ResultsError
from ..stages import Stage
from .inputs import RigSpec, SkeletonSpec, StageInputs, register
from .stage_helpers import RigRuntime, rig_for, solving, tracked_rig

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

    from ..accuracy import Triangulate
    from ..camera.rig import CameraGroup
    from ..config import Config
    from ..corrections import Corrections

log = logging.getLogger(__name__)

__all__ = [
    "Triangulated",
    "TriangulationInputs",
    "compute_triangulation",
    "run_triangulation",
    "triangulation_method",
]


RECORD = Stage(
    "triangulation",
    default_on=True,
    after=("pictorial_structures",),
    params=TriangulationParams,
    artifact="triangulation.h5",
    results_group=True,
    solves_3d=True,
    hint="check its 2D (pose2d, corrections) and the rig (bundle adjustment's "
    "result, cameras, calibration.file)",
    memory=(110, 120),
)


@register
@dataclass(frozen=True)
class TriangulationInputs(StageInputs):
    """What the triangulation stage reads. ``triangulation``: the method and only the knobs it
    reads (tracked); ``skeleton``: for the held-out accuracy's bone and left/right figures;
    ``points_from``: ``"pictorial_structures"`` or ``"pose2d"``; ``rig``: ``None`` while
    bundle adjustment is on (the rig comes from its artifact)."""

    STAGE = RECORD.name

    triangulation: TriangulationParams
    skeleton: SkeletonSpec
    points_from: str
    rig: RigSpec | None
    runtime: RigRuntime = RigRuntime()

    @classmethod
    def from_config(cls, config: Config) -> TriangulationInputs:
        flags = config.stage_flags()
        return cls(
            triangulation=build_params(TriangulationParams, config.triangulation.method_params()),
            skeleton=SkeletonSpec.from_config(config),
            points_from="pictorial_structures" if flags["pictorial_structures"] else "pose2d",
            rig=tracked_rig(config),
            runtime=RigRuntime.from_config(config),
        )


@dataclass(frozen=True)
class Triangulated:
    """The triangulation's result: ``points3d`` NaN where not reconstructed, ``points`` the 2D
    each was solved from (outlier views NaN), ``reproj_error`` in pixels, ``corrected`` the
    points a manual correction changed."""

    points3d: Float[np.ndarray, "T P 3"]
    points: Float[np.ndarray, "V T P 2"]
    reproj_error: Float[np.ndarray, "V T P"]
    corrected: Bool[np.ndarray, "T P"]


def compute_triangulation(
    inputs: TriangulationInputs,
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None = None,
    corrections: Corrections | None = None,
) -> Triangulated:
    """Lift ``pts2d`` to 3D on ``cameras`` (:func:`flylib.triangulation.reconstruct`), with the
    manual ``corrections`` (exactly ``pts2d``'s ``(V, T, P)``, else ResultsError) applied; no
    file I/O. The review GUI re-solves each edit with it.

    An edited 2D point replaces the detection (a NaN edit removes it) with confidence 1
    (:meth:`~flylib.corrections.Corrections.apply_2d`); a ``fixed`` view the robust method
    rejected is put back and the point re-solved by DLT from the kept and fixed views; an
    edited 3D point replaces the triangulated one (its reprojection errors follow).
    """
    from ..camera import model as camera_model
    from ..triangulation import reconstruct, reprojection_error

    if corrections is not None:
        if corrections.shape != np.shape(pts2d)[:3]:
            raise ResultsError(
                f"corrections of shape {corrections.shape} (views, frames, points) do not "
                f"match the 2D points {np.shape(pts2d)[:3]}; save them again from `flylib gui`"
            )
        pts2d, conf = corrections.apply_2d(pts2d, conf)
    pts3d, clean, error = reconstruct(cameras, pts2d, inputs.triangulation, conf)
    if corrections is None:
        return Triangulated(pts3d, clean, error, np.zeros(clean.shape[1:3], bool))
    fixed = corrections.fixed & corrections.edited & np.isfinite(pts2d).all(-1)
    lost = fixed & ~np.isfinite(clean).all(-1)  # fixed views the robust fit left out
    redo = np.argwhere(lost.any(axis=0))  # (n, 2) frame, point
    if len(redo):
        t, p = redo[:, 0], redo[:, 1]
        keep = np.isfinite(clean[:, t, p]).all(-1) | fixed[:, t, p]  # (V, n)
        obs = np.where(keep[..., None], pts2d[:, t, p], np.nan)
        und = cameras.undistort_points(obs) if np.any(cameras.dists) else obs
        pts3d[t, p] = camera_model.dlt_solve(np, und, cameras.pmats)
        clean[:, t, p] = obs
    if corrections.edited3d.any():
        pts3d = pts3d.copy()
        pts3d[corrections.edited3d] = corrections.points3d[corrections.edited3d]
    if len(redo) or corrections.edited3d.any():
        error = reprojection_error(cameras, pts3d, clean)
    return Triangulated(pts3d, clean, error, corrections.corrected_points())


def triangulation_method(params: TriangulationParams, cameras: CameraGroup) -> Triangulate:
    """The stage's 3D method as :func:`flylib.accuracy.held_out_errors` calls it."""
    from ..triangulation import reconstruct

    def triangulate(pts2d, conf):
        pts3d, clean, _ = reconstruct(cameras, pts2d, params, conf)
        return pts3d, np.isfinite(clean).all(-1)

    return triangulate


def run_triangulation(
    inputs: TriangulationInputs,
    pose2d_path: str | Path,
    out_path: str | Path,
    *,
    pictorial_path: str | Path | None = None,
    ba_path: str | Path | None = None,
    recording_dir: str | Path | None = None,
    corrections_path: str | Path | None = None,
) -> Path:
    """Lift the 2D (PS's when given, else pose2d's) to 3D with the bundle-adjusted rig when
    given, else the config rig. ``points`` holds the 2D the 3D was solved from.

    With ``corrections_path`` (a ``corrections.h5`` sidecar, :mod:`flylib.corrections`) the
    edits are applied first; the artifact then also holds bool masks ``corrected`` ``(T, P)``
    and ``corrected_2d`` ``(V, T, P)``, ``edited_2d`` ``(V, T, P, 2)`` (the 2D a person gave
    where ``corrected_2d``, NaN where marked invisible; refinement reads it) and attribute
    ``corrections`` (the sidecar's name, edit count, sha256).
    """
    from ..accuracy import triangulation_accuracy
    from ..corrections import Corrections
    from ..provenance import stage_provenance
    from ..results import Pose2dData, read_stage, write_stage

    pose2d = Pose2dData.load(pose2d_path)
    pts2d = pose2d.pts2d
    if pictorial_path:
        pts2d = np.asarray(read_stage(pictorial_path, "pictorial_structures")["points"], float)
    cameras = rig_for(inputs.rig, pose2d, ba_path, recording_dir, stage="triangulation")
    corrections = (
        Corrections.load(
            corrections_path,
            pts2d.shape[:3],
            [pose2d.image_sizes.get(name) for name in pose2d.view_names],
            cameras,
        )
        if corrections_path
        else None
    )
    with solving("triangulation", recording_dir or pose2d_path):
        log.info("triangulating with %s", inputs.triangulation.method)
        result = compute_triangulation(inputs, cameras, pts2d, pose2d.conf, corrections)
        # truth-free accuracy: each view predicted from the others, by the same method
        accuracy = triangulation_accuracy(
            triangulation_method(inputs.triangulation, cameras),
            cameras,
            inputs.skeleton.skeleton(),
            pts2d,
            result.points3d,
            pose2d.conf,
        )
    arrays = {
        "points": result.points,
        "points3d": result.points3d,
        "reproj_error": result.reproj_error,
    }
    attrs: dict[str, Any] = {"accuracy": accuracy}
    if corrections is not None:
        arrays["corrected"] = result.corrected
        arrays["corrected_2d"] = corrections.touched()
        arrays["edited_2d"] = corrections.edited_2d()
        from ..provenance import file_sha256

        attrs["corrections"] = {
            "file": str(corrections_path),
            "count": corrections.count(),
            "sha256": file_sha256(corrections_path),
        }
        log.info(
            "triangulation: %d manual corrections applied from %s",
            corrections.count(),
            corrections_path,
        )
    upstream = {
        "pose2d": pose2d_path,
        "pictorial_structures": pictorial_path,
        "bundle_adjustment": ba_path,
    }
    write_stage(
        out_path,
        "triangulation",
        arrays,
        attrs=attrs,
        meta=stage_provenance(inputs.canonical_params(), "triangulation", upstream),
    )
    return Path(out_path)
