"""HDF5 results (schema version 2) and the per-stage artifacts they are assembled from.

Every file holds ``attrs["meta"]`` (JSON: ``deeperfly_format_version``, ``flylib_version``,
``created_utc``, ``stage``) and the group of each stage that produced it; ``results.h5`` is the
union of the stage files plus ``skeleton/`` and the config rig as ``pose2d/cameras``. Group
attributes are JSON text; arrays are float64 (NaN = missing), chunked along their longest axis
(time) and gzip-compressed once they are large. Every write goes to a temporary sibling renamed
into place on success (:func:`atomic_path`), so an interrupted run never leaves a truncated file.

Integrity: every non-empty dataset carries HDF5's Fletcher-32 checksum filter, and files are
written with HDF5 1.8's object-header format, whose metadata (object headers with their
attributes, link tables, the superblock) carries checksums too; HDF5 verifies both on every read,
so a damaged file fails to load with a :class:`~flylib.errors.ResultsError` naming the file and
the dataset (:func:`verify_file` checks a whole file, as ``flylib inspect`` does). Names are
fixed-length UTF-8 strings, inside the checksummed chunks.

The package, by concern (every name is importable from ``flylib.results``):

- ``checksums``: the Fletcher-32 codec, :func:`verify_file`, per-dataset checks
- ``hdf5``: :func:`open_hdf5` (the one read-only opener, also for other tools' files),
  :func:`open_checked` (with the format-version check), the meta JSON, new files
- ``datasets``: array, string and JSON-attribute writers and readers
- ``groups``: the rig and skeleton groups, :func:`read_cameras`, :func:`read_skeleton`
- ``pose``: :class:`PoseResult`, the assembled result
- ``pose2d``: :class:`Pose2dData`, the pose2d artifact; ``candidates``: the top-K peaks
- ``artifacts``: :func:`write_stage` / :func:`read_stage`, :func:`write_analysis`, the
  workflow's file names (:data:`ARTIFACTS`, :data:`SUMMARY_FILES`, :func:`candidates_artifact`)
- ``assembly``: :func:`assemble_results`
- ``invariants``: what ``results.h5`` must never contradict, :func:`check_results`,
  :func:`require_consistent` (assemble and ``flylib inspect --verify`` run it)
- ``summary``: :func:`summarize_results`, the figures ``flylib inspect`` prints
"""

from __future__ import annotations

from ..paths import atomic_path
from .artifacts import (
    ARTIFACTS,
    STAGE_GROUPS,
    SUMMARY_FILES,
    artifact_path,
    candidates_artifact,
    read_stage,
    write_analysis,
    write_stage,
)
from .assembly import assemble_results
from .candidates import load_candidates, save_candidates
from .checksums import fletcher32 as fletcher32, verify_file
from .datasets import write_array as write_array
from .groups import read_cameras, read_skeleton
from .hdf5 import (
    FORMAT_VERSION,
    new_meta as new_meta,
    open_checked,
    open_hdf5 as open_hdf5,
    read_meta,
    read_meta_from as read_meta_from,
)
from .invariants import check_results, require_consistent
from .pose import Detections, PoseResult, read_detections
from .pose2d import Pose2dData, read_image_sizes
from .summary import summarize_results

__all__ = [
    "ARTIFACTS",
    "FORMAT_VERSION",
    "STAGE_GROUPS",
    "SUMMARY_FILES",
    "Detections",
    "PoseResult",
    "Pose2dData",
    "artifact_path",
    "assemble_results",
    "atomic_path",
    "candidates_artifact",
    "check_results",
    "load_candidates",
    "open_checked",
    "read_cameras",
    "read_detections",
    "read_meta",
    "read_skeleton",
    "read_image_sizes",
    "read_stage",
    "require_consistent",
    "save_candidates",
    "summarize_results",
    "verify_file",
    "write_analysis",
    "write_stage",
]
