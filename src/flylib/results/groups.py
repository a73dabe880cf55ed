"""The camera rig and skeleton groups of flylib's HDF5 files: a rig is ``names``, ``rvecs``,
``tvecs``, ``intrs`` ([fx, fy, cx, cy]) and ``dists``; a skeleton ``point_names``, ``limb_names``,
``limb_id``, ``bones`` and a ``palette`` group of attributes."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import h5py
import numpy as np

from ..errors import ResultsError
from ..skeleton import Skeleton
from .datasets import read_dataset, read_strings, write_array, write_strings
from .hdf5 import read_checked

if TYPE_CHECKING:  # pragma: no cover
    from ..camera.rig import CameraGroup


def write_cameras(group: h5py.Group, cameras: CameraGroup) -> None:
    """Store a rig as ``names``, ``rvecs``, ``tvecs``, ``intrs`` ([fx, fy, cx, cy]), ``dists``."""
    write_strings(group, "names", cameras.names)
    for name in ("rvecs", "tvecs", "intrs", "dists"):
        write_array(group, name, getattr(cameras, name))


def cameras_from_group(group: h5py.Group) -> CameraGroup:
    from ..camera.rig import CameraGroup

    return CameraGroup.from_arrays(
        read_strings(group["names"]),
        read_dataset(group["rvecs"]),
        read_dataset(group["tvecs"]),
        read_dataset(group["intrs"]),
        read_dataset(group["dists"]),
    )


def write_skeleton(group: h5py.Group, skeleton: Skeleton) -> None:
    group.attrs["name"] = skeleton.name
    write_strings(group, "point_names", skeleton.point_names)
    write_strings(group, "limb_names", skeleton.limb_names)
    write_array(group, "limb_id", skeleton.limb_id, dtype=np.int64)
    write_array(group, "bones", skeleton.bones, dtype=np.int64)
    palette = group.create_group("palette")
    for limb, color in skeleton.palette.items():
        palette.attrs[limb] = color


def skeleton_from_group(group: h5py.Group) -> Skeleton:
    name = group.attrs.get("name", "skeleton")
    palette = (
        {str(k): str(v) for k, v in group["palette"].attrs.items()} if "palette" in group else {}
    )
    return Skeleton.from_arrays(
        read_strings(group["point_names"]),
        read_strings(group["limb_names"]),
        read_dataset(group["limb_id"]),
        read_dataset(group["bones"]),
        palette=palette,
        name=str(name),
    )


def read_skeleton(path: str | Path) -> Skeleton:
    """The ``skeleton/`` of a results or stage file; missing, stale or none: a ResultsError."""
    with read_checked(path, "re-run the pipeline") as f:
        if "skeleton" not in f:
            raise ResultsError(f"{path}: has no skeleton/ group; re-run pose2d")
        return skeleton_from_group(f["skeleton"])


def read_cameras(path: str | Path, group: str) -> CameraGroup:
    """The rig in ``<group>/cameras`` (e.g. ``"bundle_adjustment"``) of a results or stage file;
    a missing or stale file, or one without it, is a ResultsError."""
    with read_checked(path, f"re-run {group}") as f:
        if f"{group}/cameras" not in f:
            raise ResultsError(f"{path}: has no {group}/cameras group; re-run {group}")
        return cameras_from_group(f[f"{group}/cameras"])
