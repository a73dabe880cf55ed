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
rejected) and ``options`` (the ``refinement`` table in force).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import h5py
import numpy as np

from ..paths import atomic_path
from .setup import options_from_params, refine_from_config
from .solver import FLAG_BITS, RefinementResult

STAGE = "refinement"


def write_refinement(path: str | Path, result: RefinementResult, skeleton, options: dict) -> None:
    """Write the refinement artifact atomically (layout in the module docstring)."""
    from ..results import _new_meta, _write_array

    names = list(skeleton.point_names)
    bones = {f"{names[i]}-{names[j]}": (None if not np.isfinite(v) else float(v))
             for (i, j), v in zip(np.asarray(skeleton.bones), result.bone_lengths)}
    centres = {names[p]: [float(c) for c in centre] for p, centre in zip(result.rigid_points, result.rigid_centres)}
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["meta"] = json.dumps(_new_meta(STAGE))
        group = f.create_group(STAGE)
        _write_array(group, "points3d", result.points3d)
        _write_array(group, "reproj_error", result.reproj_error)
        _write_array(group, "points", result.points2d)
        _write_array(group, "flags", result.flags, dtype=np.uint8)
        attrs = {
            "flag_bits": {k: list(v) for k, v in FLAG_BITS.items()},
            "bone_lengths": bones,
            "rigid_centres": centres,
            "summary": result.info,
            "options": options,
        }
        for key, value in attrs.items():
            group.attrs[key] = json.dumps(value)


def run_refinement(config, pose2d_path: str | Path, triangulation_path: str | Path, out_path: str | Path, *,
                   ba_path: str | Path | None = None, recording_dir: str | Path | None = None) -> Path:
    """Refine the triangulated 3D of one recording and write ``stages/refinement.h5``.

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
    from ..results import Pose2dData, read_stage
    from ..stages import _rig_for

    pose2d = Pose2dData.load(pose2d_path)
    tri = read_stage(triangulation_path, "triangulation")
    cameras = _rig_for(config, pose2d, ba_path, recording_dir)
    inliers = np.isfinite(np.asarray(tri["points"], float)).all(-1)
    result = refine_from_config(config, pose2d.pts2d, cameras, np.asarray(tri["points3d"], float),
                                conf=pose2d.conf, inliers=inliers)
    options = asdict(options_from_params(config.refinement))
    options["rigid_points"] = [config.skeleton().point_names[p] for p in result.rigid_points]
    write_refinement(out_path, result, config.skeleton(), options)
    return Path(out_path)
