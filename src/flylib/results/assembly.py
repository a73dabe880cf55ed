"""Assembling ``results.h5`` from the stage artifacts: :func:`assemble_results`."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py

from ..errors import ResultsError
from ..paths import atomic_path
from ..skeleton import Skeleton
from .artifacts import STAGE_GROUPS
from .checksums import check_group
from .datasets import read_json_attrs, read_strings
from .groups import write_cameras, write_skeleton
from .hdf5 import create_file, new_meta, open_checked, read_meta_from
from .invariants import require_consistent

if TYPE_CHECKING:  # pragma: no cover
    from ..camera.rig import CameraGroup


def assemble_results(
    out_path: str | Path,
    *,
    skeleton: Skeleton,
    config_rig: CameraGroup,
    stage_files: Mapping[str, str | Path],
    meta: Mapping[str, Any] | None = None,
    verify: bool = True,
) -> None:
    """Assemble ``results.h5`` atomically from ``stage_files`` (``stage -> artifact``; pose2d
    required): each stage group verified and copied verbatim, the config's ``skeleton`` and
    ``config_rig`` written as ``skeleton/`` and ``pose2d/cameras`` (so editing the rig never
    invalidates detection) once their names match the pose2d artifact's (else a ResultsError, as
    for a missing pose2d or an unreadable artifact). ``verify``: refuse a file that contradicts
    itself (:func:`~flylib.results.invariants.require_consistent`); ``False`` only for made-up
    arrays (tests of the assembly's mechanics, benchmarks)."""
    unknown = sorted(set(stage_files) - set(STAGE_GROUPS))
    if unknown:
        raise ValueError(
            f"unknown stage(s) {', '.join(unknown)} (known: {', '.join(STAGE_GROUPS)})"
        )
    if "pose2d" not in stage_files:
        raise ResultsError(
            f"{out_path}: cannot assemble without the pose2d artifact; run the pose2d stage"
        )
    with atomic_path(out_path) as tmp:
        with create_file(tmp) as dst:
            dst.attrs["meta"] = json.dumps(
                new_meta("assemble", {**(meta or {}), "stages": list(stage_files)})
            )
            write_skeleton(dst.create_group("skeleton"), skeleton)
            for stage in STAGE_GROUPS:
                if stage not in stage_files:
                    continue
                src_path = stage_files[stage]
                with open_checked(src_path, f"re-run the {stage} stage") as src:
                    if stage not in src:
                        raise ResultsError(
                            f"{src_path}: has no {stage} group; re-run the {stage} stage"
                        )
                    check_group(src_path, src[stage])  # a raw copy would carry damage over unseen
                    src.copy(src[stage], dst, name=stage)
                    dst[stage].attrs["meta"] = json.dumps(read_meta_from(src))
                    if stage == "pose2d":
                        _check_pose2d_matches(src, src_path, skeleton, config_rig)
            g2d = dst["pose2d"]
            if "cameras" in g2d:
                del g2d["cameras"]
            write_cameras(g2d.create_group("cameras"), config_rig)
        # a contradiction is a bug upstream: refuse it before the file is put in place
        if verify:
            require_consistent(tmp, writer="assemble", shown=out_path)


def _check_pose2d_matches(
    src: h5py.File, src_path: str | Path, skeleton: Skeleton, rig: CameraGroup
) -> None:
    if "skeleton" in src:
        detected = read_strings(src["skeleton/point_names"])
        if list(detected) != list(skeleton.point_names):
            raise ResultsError(
                f"{src_path}: detected with skeleton points {detected[:3]}... which differ from the"
                " config's skeleton; re-run the pose2d stage"
            )
    n_points = src["pose2d/points"].shape[2]
    if n_points != skeleton.n_points:
        raise ResultsError(
            f"{src_path}: has {n_points} points but the skeleton has {skeleton.n_points}; re-run the pose2d stage"
        )
    views = read_json_attrs(src["pose2d"]).get("view_names")
    if views is not None and list(views) != list(rig.names):
        raise ResultsError(
            f"{src_path}: 2D points are for views {views} but the rig has cameras {list(rig.names)};"
            " re-run the pose2d stage or restore the camera names/order"
        )
