"""Validation of a parsed config mapping: :func:`validate_config` and the detection-plan checks."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import fields
from typing import Any

from ..errors import did_you_mean, unknown_key
from ..paths import name_problem
from ..skeleton import default_skeleton_table, skeleton_problems
from .checks import boolean, got, integer, is_int, mapping, non_finite_problems
from .constants import EXPORT_KEYS, POSE2D_PLAN_KEYS, STAGES, SUBPIXEL_METHODS, TOP_LEVEL_KEYS
from .nwb_metadata import metadata_problems
from .params import (
    LEAST_SQUARES_CHECKS,
    LEAST_SQUARES_OPTIONS,
    PARAM_TABLES,
    BundleAdjustmentParams,
    Pose2dParams,
    table_problems,
)
from .postprocessing import kinematics_problems

#: The :data:`~.params.PARAM_TABLES` tables checked by their own code below; every other
#: one is checked by :func:`~.params.table_problems` alone, in that map's order.
OWN_CHECKS = ("pose2d", "bundle_adjustment", "kinematics", "io")


def _named_entries(entries: Any, path: str, problems: list[str]) -> dict[str, dict]:
    """A list of ``{name: ..., ...}`` tables as ``name -> entry`` (problems recorded)."""
    if entries is None:
        return {}
    if not isinstance(entries, list):
        problems.append(f"{path}: expected a list of tables, {got(entries)}")
        return {}
    out: dict[str, dict] = {}
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            problems.append(f"{path}[{i}]: expected a table, {got(entry)}")
            continue
        name = entry.get("name")
        if not isinstance(name, str) or not name:
            problems.append(f"{path}[{i}].name: expected a non-empty string, got {name!r}")
        elif name in out:
            problems.append(f"{path}[{i}].name: {name!r} is defined twice")
        else:
            out[name] = dict(entry)
    return out


def _reference(value: Any, known: Mapping, what: str, where: str, problems: list[str]) -> bool:
    if isinstance(value, str) and value in known:
        return True
    problems.append(f"{where}: unknown {what} {value!r} (known: {', '.join(known) or 'none'})")
    return False


def _plan_problems(
    data: Mapping, point_names: tuple[str, ...], view_names: list[str] | None
) -> list[str]:
    """Problems with the detection plan: sources, preprocessors, models, pathways, output_points."""
    problems: list[str] = []
    pose2d = data.get("pose2d") or {}
    sources = _named_entries(data.get("sources"), "sources", problems)
    for name, entry in sources.items():
        if "filename" in entry and not isinstance(entry["filename"], str):
            problems.append(
                f"sources.{name}.filename: expected a glob string, {got(entry['filename'])}"
            )
    preprocessors = _named_entries(pose2d.get("preprocessors"), "pose2d.preprocessors", problems)
    for name, entry in preprocessors.items():
        ops = entry.get("ops", [])
        if not isinstance(ops, list) or not all(
            isinstance(op, Mapping) and "op" in op for op in ops
        ):
            problems.append(
                f"pose2d.preprocessors.{name}.ops: expected a list of tables each with an 'op' key"
            )
    models = _named_entries(pose2d.get("models"), "pose2d.models", problems)
    n_channels: dict[str, int | None] = {}
    for name, entry in models.items():
        n_out = entry.get("n_out_channels")
        if n_out is not None and not (is_int(n_out) and n_out >= 1):
            problems.append(
                f"pose2d.models.{name}.n_out_channels: expected an integer >= 1, {got(n_out)}"
            )
            n_out = None
        n_channels[name] = n_out
        size = entry.get("input_size")
        if size is not None and not (
            isinstance(size, list) and len(size) == 2 and all(is_int(s) and s > 0 for s in size)
        ):
            problems.append(
                f"pose2d.models.{name}.input_size: expected [height, width] in pixels, got {size!r}"
            )
        if "weights" in entry and not isinstance(entry["weights"], str):
            problems.append(
                f"pose2d.models.{name}.weights: expected a path string ('' for the published weights)"
            )
        if "subpixel" in entry and entry["subpixel"] not in SUBPIXEL_METHODS:
            problems.append(
                f"pose2d.models.{name}.subpixel: expected one of {', '.join(SUBPIXEL_METHODS)}, "
                f"got {entry['subpixel']!r}"
            )
    weights = pose2d.get("weights")
    if weights is not None and not isinstance(weights, Mapping):
        problems.append(
            f"pose2d.weights: expected a mapping model name -> checkpoint path, {got(weights)}"
        )
    elif weights:
        for name, path in weights.items():
            if name not in models:
                problems.append(
                    f"pose2d.weights.{name}: unknown model {name!r} (known: {', '.join(models) or 'none'})"
                )
            elif path is not None and not isinstance(path, str):
                problems.append(
                    f"pose2d.weights.{name}: expected a path string ('' for the published weights), {got(path)}"
                )
    pathways = _named_entries(pose2d.get("pathways"), "pose2d.pathways", problems)
    pathway_model: dict[str, str | None] = {}
    for name, entry in pathways.items():
        where = f"pose2d.pathways.{name}"
        _reference(entry.get("source"), sources, "source", f"{where}.source", problems)
        if entry.get("preprocessor") is not None:
            _reference(
                entry["preprocessor"],
                preprocessors,
                "preprocessor",
                f"{where}.preprocessor",
                problems,
            )
        ok = _reference(entry.get("model"), models, "model", f"{where}.model", problems)
        pathway_model[name] = entry["model"] if ok else None

    output_points = pose2d.get("output_points")
    if output_points is None:
        return problems
    if not isinstance(output_points, Mapping):
        return [
            *problems,
            "pose2d.output_points: expected a mapping view -> point -> {pathway, out_channel}",
        ]
    known_points = set(point_names)
    for view, table in output_points.items():
        where_view = f"pose2d.output_points.{view}"
        if view_names is not None and view not in view_names:
            problems.append(
                f"{where_view}: unknown view {view!r} (cameras: {', '.join(view_names)})"
            )
        if not isinstance(table, Mapping):
            problems.append(f"{where_view}: expected a mapping point -> {{pathway, out_channel}}")
            continue
        for point, slot in table.items():
            where = f"{where_view}.{point}"
            if known_points and point not in known_points:
                problems.append(
                    f"{where}: unknown point {point!r} (known: {', '.join(point_names)})"
                )
            if not isinstance(slot, Mapping):
                problems.append(
                    f"{where}: expected {{pathway: ..., out_channel: ...}}, {got(slot)}"
                )
                continue
            extra = sorted(str(k) for k in set(slot) - {"pathway", "out_channel"})
            if extra:
                problems.append(
                    f"{where}: unknown key(s) {', '.join(extra)} (known: pathway, out_channel)"
                )
            has_pathway = _reference(
                slot.get("pathway"), pathways, "pathway", f"{where}.pathway", problems
            )
            channel = slot.get("out_channel")
            if not (is_int(channel) and channel >= 0):
                problems.append(f"{where}.out_channel: expected an integer >= 0, {got(channel)}")
                continue
            n_out = (
                n_channels.get(pathway_model.get(slot.get("pathway")) or "")
                if has_pathway
                else None
            )
            if n_out is not None and channel >= n_out:
                model = pathway_model[slot["pathway"]]
                problems.append(
                    f"{where}.out_channel: {channel} is out of range for model {model!r}"
                    f" (n_out_channels {n_out}: use 0..{n_out - 1})"
                )
    return problems


def default_point_names() -> tuple[str, ...]:
    return tuple(default_skeleton_table()["point_names"])


def validate_config(data: Any) -> list[str]:
    """Every problem with a parsed config mapping, one ``"<key path>: <problem>"`` line each."""
    if not isinstance(data, Mapping):
        return [f"<top level>: expected a mapping of tables, {got(data)}"]
    problems = [
        f"{key}: {unknown_key('top-level table', key, TOP_LEVEL_KEYS)}"
        for key in data
        if key not in TOP_LEVEL_KEYS
    ]
    bad_tables = _table_kind_problems(data, problems)

    def table(name: str) -> Mapping:
        return {} if name in bad_tables else (data.get(name) or {})

    if "skeleton" in data and "skeleton" not in bad_tables:
        skeleton_issues = skeleton_problems(data["skeleton"])
        problems += skeleton_issues
        names = data["skeleton"].get("point_names")
        # only a valid list names the points other tables refer to (skeleton_problems reports)
        valid = isinstance(names, list) and all(isinstance(n, str) for n in names)
        point_names = tuple(names) if valid else ()
    else:
        point_names = default_point_names()
    view_names = _camera_view_names(data, table("cameras"), problems)
    problems += _pipeline_problems(table("pipeline"))

    pose2d = table("pose2d")
    problems += table_problems(pose2d, Pose2dParams, "pose2d", POSE2D_PLAN_KEYS)
    if "import" in pose2d and mapping(nullable=True)(pose2d["import"]):
        problems.append(f"pose2d.import: {mapping(nullable=True)(pose2d['import'])}")
    if "sources" not in bad_tables and "pose2d" not in bad_tables:
        problems += _plan_problems(data, point_names, view_names)

    problems += _bundle_adjustment_problems(table("bundle_adjustment"), point_names)
    for name, cls in PARAM_TABLES.items():
        if name not in OWN_CHECKS:
            problems += table_problems(table(name), cls, name)
    rigid = table("refinement").get("rigid_points")
    if isinstance(rigid, list) and point_names:
        for point in rigid:
            if isinstance(point, str) and point not in point_names:
                problems.append(
                    f"refinement.rigid_points: unknown point {point!r} (known: {', '.join(point_names)})"
                )
    problems += kinematics_problems(table("kinematics"), point_names)
    problems += _io_problems(table("io"))

    videos = table("visualization").get("videos")
    if videos is not None and not isinstance(videos, list):
        problems.append(f"visualization.videos: expected a list of video tables, {got(videos)}")
    problems += _export_problems(data)
    return _with_non_finite(problems, data)


def _with_non_finite(problems: list[str], data: Mapping) -> list[str]:
    """``problems`` plus one line per non-finite number, replacing the other checks' line on the
    same key (or on the list holding the number): each key gets one line, the root cause."""
    non_finite = non_finite_problems(data)
    if not non_finite:
        return problems
    keys = {re.sub(r"(\[\d+\])+$", "", where) for where in non_finite} | set(non_finite)
    kept = [p for p in problems if p.split(": ", 1)[0] not in keys]
    return kept + list(non_finite.values())


def _table_kind_problems(data: Mapping, problems: list[str]) -> set[str]:
    """Tables of the wrong kind (a list where a mapping belongs, ...), recorded in ``problems``;
    returns their names, which the other checks then skip."""
    table_kinds = {
        "io": mapping(),
        "skeleton": mapping(),
        "cameras": mapping(),
        "pipeline": mapping(),
        **{stage: mapping() for stage in STAGES},
        "calibration": mapping(nullable=True),
        "demo": mapping(nullable=True),
        "sources": lambda v: (
            None if isinstance(v, list) else f"expected a list of tables, {got(v)}"
        ),
        "recordings": lambda v: (
            None
            if isinstance(v, (list, str))
            else f"expected a list of recordings or the path of a .tsv or .csv sheet, {got(v)}"
        ),
        "recursive": boolean,
        "outdir": lambda v: (
            None
            if v is None or isinstance(v, str)
            else f"expected a path template or null, {got(v)}"
        ),
        "corrections": lambda v: (
            None
            if v is None or (isinstance(v, str) and v.strip())
            else f"expected the path (template) of a corrections.h5 sidecar or null, {got(v)}"
        ),
    }
    bad_tables = set()
    for key, check in table_kinds.items():
        if key in data:
            why = check(data[key])
            if why:
                problems.append(f"{key}: {why}")
                bad_tables.add(key)
    return bad_tables


def _camera_view_names(data: Mapping, cameras: Mapping, problems: list[str]) -> list[str] | None:
    """The rig's view names (``None`` when a calibration file names them); camera entries that
    are not tables are recorded in ``problems``."""
    view_names = [name for name in cameras if name != "defaults"]
    for name, spec in cameras.items():
        if name_problem(str(name)):  # a view names files (exports write <view>.csv)
            problems.append(
                f"cameras.{name}: cannot be a view name: {name_problem(str(name))}; rename it"
            )
        if spec is None:  # a table a null deleted would be gone: there was none
            known = ", ".join(n for n in view_names if cameras[n] is not None)
            problems.append(
                f"cameras.{name}: null removes a camera, and the rig has no camera {name!r} "
                f"(cameras: {known}); check the name"
            )
        elif not isinstance(spec, Mapping):
            problems.append(f"cameras.{name}: expected a table of camera parameters, {got(spec)}")
    if not view_names and data.get("calibration"):
        view_names = None  # the rig comes from the calibration file: names unknown here
    return view_names


def _pipeline_problems(pipeline: Mapping) -> list[str]:
    """The ``pipeline`` table: only ``do_<stage>`` booleans."""
    problems: list[str] = []
    pipeline_checks = {f"do_{stage}": boolean for stage in STAGES}
    for key, value in pipeline.items():
        if key not in pipeline_checks:
            problems.append(f"pipeline.{key}: {unknown_key('parameter', key, pipeline_checks)}")
        elif pipeline_checks[key](value):
            problems.append(f"pipeline.{key}: {pipeline_checks[key](value)}")
    return problems


def _bundle_adjustment_problems(ba: Mapping, point_names: tuple[str, ...]) -> list[str]:
    """The ``bundle_adjustment`` table: its parameters, least-squares options and points."""
    problems: list[str] = []
    ba_fields = tuple(f.name for f in fields(BundleAdjustmentParams) if f.name != "least_squares")
    ls_keys = LEAST_SQUARES_OPTIONS
    for key, value in ba.items():
        where = f"bundle_adjustment.{key}"
        if key in ba_fields:
            continue
        if key not in ls_keys:
            problems.append(
                f"{where}: unknown parameter; {did_you_mean(key, [*ba_fields, *ls_keys])}"
                f"(known: {', '.join(ba_fields)}, or a"
                f" scipy.optimize.least_squares option: {', '.join(ls_keys)})"
            )
        elif key in LEAST_SQUARES_CHECKS and LEAST_SQUARES_CHECKS[key](value):
            problems.append(f"{where}: {LEAST_SQUARES_CHECKS[key](value)}")
    problems += table_problems(
        {k: v for k, v in ba.items() if k in ba_fields}, BundleAdjustmentParams, "bundle_adjustment"
    )
    if isinstance(ba.get("points_to_use"), (list, tuple)) and point_names:
        for point in ba["points_to_use"]:
            if isinstance(point, str) and point not in point_names:
                problems.append(
                    f"bundle_adjustment.points_to_use: unknown point {point!r} (known: {', '.join(point_names)})"
                )
    return problems


def _io_problems(io: Mapping) -> list[str]:
    """The ``io`` table: ``on_corrupt_frame`` and the per-kind reader tables."""
    problems: list[str] = []
    for key, value in io.items():
        if key == "on_corrupt_frame":
            if value not in ("error", "missing"):
                problems.append(f"io.on_corrupt_frame: expected 'error' or 'missing', {got(value)}")
            continue
        if not isinstance(value, Mapping):
            problems.append(f"io.{key}: expected a table, {got(value)}")
    workers = io.get("image", {})
    if isinstance(workers, Mapping) and "workers" in workers and integer(0)(workers["workers"]):
        problems.append(f"io.image.workers: {integer(0)(workers['workers'])}")
    return problems


def _export_problems(data: Mapping) -> list[str]:
    """The ``exports`` table (which extra outputs to write) and the NWB export's ``nwb`` table."""
    problems: list[str] = []
    exports = data.get("exports")
    if exports is not None and not isinstance(exports, Mapping):
        problems.append(f"exports: expected a table such as {{nwb: true}}, {got(exports)}")
    for key, value in (exports if isinstance(exports, Mapping) else {}).items():
        if key not in EXPORT_KEYS:
            problems.append(f"exports.{key}: unknown export (known: {', '.join(EXPORT_KEYS)})")
        elif boolean(value):
            problems.append(f"exports.{key}: {boolean(value)}")
    return problems + metadata_problems(data.get("nwb"))
