"""The per-stage artifacts: ``<outdir>/stages/<stage>.h5`` and the post-processing files.

Each holds the meta JSON and exactly the group its stage owns in ``results.h5``
(:data:`STAGE_GROUPS`), so assembly is a group copy; ``kinematics.h5`` and ``neuromechfly.h5``
(:func:`write_analysis`) are not part of it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from ..errors import ResultsError
from ..paths import atomic_path
from ..stages import by_name, derived, registry
from .datasets import json_attrs, read_dataset, read_json_attrs, write_array
from .groups import cameras_from_group, write_cameras
from .hdf5 import create_file, new_meta, read_checked

if TYPE_CHECKING:  # pragma: no cover
    from ..camera.rig import CameraGroup

#: Stage-artifact file names inside ``<outdir>/stages/``.
ARTIFACTS: dict[str, str] = derived(
    lambda: {s.name: s.artifact for s in registry() if s.artifact}, mapping=True
)
#: Stages that own a group in results.h5, in pipeline order.
STAGE_GROUPS: tuple[str, ...] = derived(lambda: [s.name for s in registry() if s.results_group])
#: The per-recording summary files the assemble stage writes beside ``results.h5``.
SUMMARY_FILES = ("summary.json", "summary.png", "calibration.toml", "suspects.csv")


def candidates_artifact(k: int) -> str:
    """File name of the detector's top-``k`` peaks inside ``<outdir>/stages/``: a file of its own
    named by ``k``, so turning pictorial structures off (or editing ``k`` while it is off) re-runs
    no detection, and a new ``k`` while it is on asks for a new file."""
    return f"candidates_k{int(k)}.h5"


def artifact_path(outdir: str | Path, stage: str) -> Path:
    """``<outdir>/stages/<stage>.h5``."""
    return Path(outdir) / "stages" / ARTIFACTS[stage]


def write_analysis(
    path: str | Path, stage: str, arrays: Mapping[str, Any], attrs: Mapping[str, Any]
) -> Path:
    """Write a post-processing stage's file (``kinematics.h5``, ``neuromechfly.h5``) atomically:
    the meta JSON, and a group ``<stage>`` holding ``arrays`` as checksummed float64 datasets and
    ``attrs`` as JSON group attributes."""
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["meta"] = json.dumps(new_meta(stage))
        group = f.create_group(stage)
        for name, value in arrays.items():
            write_array(group, name, value)
        json_attrs(group, attrs)
    return Path(path)


def write_stage(
    path: str | Path,
    stage: str,
    arrays: Mapping[str, Any],
    *,
    cameras: CameraGroup | None = None,
    attrs: Mapping[str, Any] | None = None,
    meta: Mapping[str, Any] | None = None,
) -> None:
    """Write one stage's artifact atomically: ``<stage>/`` with its arrays, rig and attributes.

    ``stage``: any stage of :data:`STAGE_GROUPS` but pose2d (:meth:`Pose2dData.save`);
    ``arrays``: ``name -> array`` stored as float64 datasets (e.g. ``points``, ``points3d``,
    ``reproj_error``; boolean masks stay boolean); ``cameras``: a rig to store as
    ``<stage>/cameras`` (bundle adjustment's); ``attrs``: JSON-serialisable group attributes;
    ``meta``: extra entries for the file's meta JSON (e.g. its params hash).
    """
    try:  # its own record only: a job finds no other stage's home
        owns = stage != "pose2d" and by_name(stage).results_group
    except ValueError:
        owns = False
    if not owns:
        raise ValueError(
            f"unknown stage {stage!r} (write_stage takes {', '.join(STAGE_GROUPS[1:])})"
        )
    with atomic_path(path) as tmp, create_file(tmp) as f:
        f.attrs["meta"] = json.dumps(new_meta(stage, meta))
        group = f.create_group(stage)
        for name, value in arrays.items():
            value = np.asarray(value)
            write_array(
                group, name, value, dtype=np.bool_ if value.dtype == np.bool_ else np.float64
            )
        if cameras is not None:
            write_cameras(group.create_group("cameras"), cameras)
        json_attrs(group, attrs)


def read_stage(path: str | Path, stage: str) -> dict[str, Any]:
    """Read one stage's group of a stage artifact (or results file): ``name -> np.ndarray`` for
    every dataset, ``"cameras"`` (a ``CameraGroup`` or ``None``) and ``"attrs"`` (decoded). A
    ResultsError if the file is missing, of another version, or lacks ``<stage>/``."""
    rerun = f"re-run the {stage} stage"
    with read_checked(path, rerun) as f:
        if stage not in f:
            raise ResultsError(f"{path}: has no {stage} group; {rerun}")
        group = f[stage]
        out: dict[str, Any] = {
            name: read_dataset(item)
            for name, item in group.items()
            if isinstance(item, h5py.Dataset)
        }
        out["cameras"] = cameras_from_group(group["cameras"]) if "cameras" in group else None
        out["attrs"] = read_json_attrs(group)
        return out
