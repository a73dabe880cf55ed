"""The run configuration: loading (YAML or TOML), validation, typed per-stage views.

A :class:`Config` wraps the parsed mapping (:attr:`Config.data`) and, when read from a
file, its exact text (:attr:`Config.text`) so the run can snapshot it byte-for-byte.
Every constructor validates: all problems are collected and raised together as one
:class:`~flylib.errors.ConfigError`, one line per problem, each naming its key path.

:meth:`Config.stage_params` gives, per workflow stage, the exact subset of the config
that affects that stage's result (JSON-serialisable, deterministic), so the workflow
re-runs a stage exactly when one of its parameters changes. Performance-only knobs
(``pose2d.batch_size``, ``decode_buffer``, ``device``, ``compile``, ``io.*``) never
appear in it.
"""

from __future__ import annotations

import copy
import json
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from .errors import ConfigError
from .skeleton import skeleton_problems

if TYPE_CHECKING:  # pragma: no cover
    from .cameras import CameraGroup
    from .skeleton import Skeleton

__all__ = [
    "BundleAdjustmentParams",
    "Config",
    "DEFAULT_CONFIG_PATH",
    "IoParams",
    "PARAM_STAGES",
    "PictorialParams",
    "Pose2dParams",
    "STAGES",
    "STAGE_DEFAULTS",
    "TriangulationParams",
]

DEFAULT_CONFIG_PATH = Path(__file__).with_name("default_config.yaml")

#: The pipeline stages, in run order; each is toggled by ``pipeline.do_<stage>``.
STAGES: tuple[str, ...] = (
    "pose2d",
    "bundle_adjustment",
    "pictorial_structures",
    "triangulation",
    "visualization",
)
#: Whether each stage runs when its ``pipeline.do_<stage>`` key is absent.
STAGE_DEFAULTS: dict[str, bool] = {
    "pose2d": True,
    "bundle_adjustment": True,
    "pictorial_structures": False,
    "triangulation": True,
    "visualization": True,
}
#: The workflow rules that :meth:`Config.stage_params` describes.
PARAM_STAGES: tuple[str, ...] = (
    "pose2d",
    "bundle_adjustment",
    "pictorial_structures",
    "triangulation",
    "assemble",
    "visualization",
)

TOP_LEVEL_KEYS: tuple[str, ...] = (
    "sources",
    "io",
    "skeleton",
    "cameras",
    "pipeline",
    "pose2d",
    "bundle_adjustment",
    "pictorial_structures",
    "triangulation",
    "visualization",
    "calibration",
    "recordings",
    "recursive",
    "outdir",
    "demo",
)
TRIANGULATION_METHODS = ("ransac", "greedy", "dlt")
FRAME_SAMPLINGS = ("even", "confidence", "coverage", "diversity")
PRECISIONS = ("float32", "float16", "bfloat16")
_POSE2D_PLAN_KEYS = ("preprocessors", "models", "pathways", "output_points", "import")
# least_squares arguments the bundle adjuster owns itself (the problem definition).
_LEAST_SQUARES_RESERVED = ("fun", "x0", "jac", "bounds", "args", "kwargs", "jac_sparsity", "callback")
# least_squares arguments that change only speed or logging, never the result.
_LEAST_SQUARES_PERF = ("verbose", "workers")


# -- value checks --------------------------------------------------------------
# A check takes a value and returns what is wrong with it ("expected ..."), or None.

Check = Callable[[Any], "str | None"]


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _got(value: Any) -> str:
    return f"got {value!r} ({type(value).__name__})"


def _integer(minimum: int | None = None, nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if value is None and nullable:
            return None
        if _is_int(value) and (minimum is None or value >= minimum):
            return None
        bound = "" if minimum is None else f" >= {minimum}"
        return f"expected an integer{bound}{' or null' if nullable else ''}, {_got(value)}"

    return check


def _number(minimum: float | None = None, exclusive: bool = False, nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if value is None and nullable:
            return None
        if _is_number(value) and (
            minimum is None or (value > minimum if exclusive else value >= minimum)
        ):
            return None
        bound = "" if minimum is None else f" {'>' if exclusive else '>='} {minimum:g}"
        hint = (
            "; write exponents with a dot, e.g. 1.0e-8"
            if isinstance(value, str) and re.fullmatch(r"[-+]?[\d.]+[eE][-+]?\d+", value)
            else ""
        )
        return f"expected a number{bound}{' or null' if nullable else ''}, {_got(value)}{hint}"

    return check


def _boolean(value: Any) -> str | None:
    return None if isinstance(value, bool) else f"expected true or false, {_got(value)}"


def _string(value: Any) -> str | None:
    return None if isinstance(value, str) else f"expected a string, {_got(value)}"


def _choice(*options: Any) -> Check:
    def check(value: Any) -> str | None:
        if any(value == o and type(value) is type(o) for o in options):
            return None
        return f"expected one of {', '.join(map(repr, options))}, got {value!r}"

    return check


def _string_list(nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if value is None and nullable:
            return None
        if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            return None
        return f"expected a list of strings{' or null' if nullable else ''}, {_got(value)}"

    return check


def _string_groups(value: Any) -> str | None:
    if isinstance(value, (list, tuple)) and all(
        isinstance(g, (list, tuple)) and all(isinstance(s, str) for s in g) for g in value
    ):
        return None
    return f"expected a list of lists of strings, {_got(value)}"


def _mapping(nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if (value is None and nullable) or isinstance(value, Mapping):
            return None
        return f"expected a mapping{' or null' if nullable else ''}, {_got(value)}"

    return check


def _param(default: Any, check: Check, *, kind: type | None = None) -> Any:
    """A typed-parameter field: its default, its value check, and a conversion."""
    return field(default=default, metadata={"check": check, "kind": kind})


# -- typed per-stage views -----------------------------------------------------


@dataclass(frozen=True)
class Pose2dParams:
    """The scalar ``pose2d`` settings (the detection plan tables are parsed by ``flylib.pose2d``).

    Attributes
    ----------
    precision
        Detector forward precision: ``float32``, ``float16`` or ``bfloat16``.
    batch_size
        Frames per forward pass (performance only).
    decode_buffer
        Decoded batches queued ahead of the detector (performance only).
    device
        ``auto`` (CUDA, then Apple MPS, then CPU) or a torch device string (performance only).
    compile
        Wrap the forward in ``torch.compile``: ``true``, ``false`` or ``auto`` (performance only).
    """

    precision: str = _param("bfloat16", _choice(*PRECISIONS))
    batch_size: int = _param(16, _integer(1))
    decode_buffer: int = _param(4, _integer(1))
    device: str = _param("auto", _string)
    compile: bool | str = _param("auto", _choice(True, False, "auto"))


@dataclass(frozen=True)
class TriangulationParams:
    """The ``triangulation`` table.

    Attributes
    ----------
    method
        ``ransac`` (largest consistent view set), ``greedy`` (drop the worst view
        while over ``reproj_threshold``) or ``dlt`` (plain least squares).
    weigh_by_confidence
        Scale each view's equations by ``sqrt(conf)``.
    ransac_threshold, min_inliers
        ``ransac``: inlier reprojection radius in pixels and minimum agreeing views.
    reproj_threshold, max_drops
        ``greedy``: reprojection error in pixels that triggers a drop, and the most
        views dropped per point.
    """

    method: str = _param("ransac", _choice(*TRIANGULATION_METHODS))
    weigh_by_confidence: bool = _param(False, _boolean)
    ransac_threshold: float = _param(15.0, _number(0, exclusive=True), kind=float)
    min_inliers: int = _param(2, _integer(2))
    reproj_threshold: float = _param(40.0, _number(0, exclusive=True), kind=float)
    max_drops: int = _param(5, _integer(0))

    def method_params(self) -> dict[str, Any]:
        """The knobs the chosen ``method`` actually reads (plus ``weigh_by_confidence``)."""
        own = {
            "ransac": ("ransac_threshold", "min_inliers"),
            "greedy": ("reproj_threshold", "max_drops"),
            "dlt": (),
        }[self.method]
        return {
            "method": self.method,
            "weigh_by_confidence": self.weigh_by_confidence,
            **{name: getattr(self, name) for name in own},
        }


@dataclass(frozen=True)
class PictorialParams:
    """The ``pictorial_structures`` table.

    Attributes
    ----------
    k
        Candidate peaks per (view, point) the detector keeps for this stage.
    temporal
        Add the term tying each frame's 3D to the previous frame's.
    lam
        Weight of the bone-length prior.
    bone_max_frames
        Frames sampled to estimate the bone lengths (null: every frame).
    max_hyp, inlier_px, huber, mu, nms
        Hypothesis pruning and cost knobs; null keeps ``flylib.pictorial``'s defaults.
    """

    k: int = _param(5, _integer(1))
    temporal: bool = _param(False, _boolean)
    lam: float = _param(1.0, _number(0), kind=float)
    bone_max_frames: int | None = _param(100, _integer(1, nullable=True))
    max_hyp: int | None = _param(None, _integer(1, nullable=True))
    inlier_px: float | None = _param(None, _number(0, exclusive=True, nullable=True), kind=float)
    huber: float | None = _param(None, _number(0, exclusive=True, nullable=True), kind=float)
    mu: float | None = _param(None, _number(0, nullable=True), kind=float)
    nms: float | None = _param(None, _number(0, nullable=True), kind=float)

    def solver_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``flylib.pictorial.reconstruct`` (``k`` excluded, nulls dropped)."""
        out: dict[str, Any] = {
            "temporal": self.temporal,
            "lam": self.lam,
            "bone_max_frames": self.bone_max_frames,
        }
        for name in ("max_hyp", "inlier_px", "huber", "mu", "nms"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out


@dataclass(frozen=True)
class BundleAdjustmentParams:
    """The ``bundle_adjustment`` table.

    Attributes
    ----------
    points_to_use
        Skeleton points whose detections drive the adjustment (null: all).
    fixed
        Parameter references held constant, e.g. ``"*.intr"`` (every camera's intrinsics).
    shared
        Groups of parameter references tied to one value.
    weigh_by_confidence
        Scale each residual by ``sqrt(conf)``.
    max_frames
        Frames sampled for the adjustment (null: every frame).
    frame_sampling
        How frames are sampled: ``even``, ``confidence``, ``coverage`` or ``diversity``.
    least_squares
        Every other key of the table, passed through to ``scipy.optimize.least_squares``
        (e.g. ``max_nfev``, ``loss``, ``f_scale``).
    """

    points_to_use: tuple[str, ...] | None = _param(None, _string_list(nullable=True), kind=tuple)
    fixed: tuple[str, ...] = _param(("*.intr",), _string_list(), kind=tuple)
    shared: tuple[tuple[str, ...], ...] = _param((), _string_groups, kind=tuple)
    weigh_by_confidence: bool = _param(False, _boolean)
    max_frames: int | None = _param(200, _integer(1, nullable=True))
    frame_sampling: str = _param("even", _choice(*FRAME_SAMPLINGS))
    least_squares: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class IoParams:
    """Frame-reading settings (performance only).

    Attributes
    ----------
    image_workers
        Threads decoding image sequences; ``None`` lets the reader choose.
    """

    image_workers: int | None = None


_LEAST_SQUARES_CHECKS: dict[str, Check] = {
    "method": _choice("trf", "dogbox", "lm"),
    "loss": _choice("linear", "soft_l1", "huber", "cauchy", "arctan"),
    "f_scale": _number(0, exclusive=True),
    "max_nfev": _integer(1, nullable=True),
    "ftol": _number(0, nullable=True),
    "xtol": _number(0, nullable=True),
    "gtol": _number(0, nullable=True),
    "diff_step": _number(0, exclusive=True, nullable=True),
    "tr_solver": _choice("exact", "lsmr", None),
    "tr_options": _mapping(),
    "verbose": _choice(0, 1, 2),
}


# The scipy.optimize.least_squares options a config may set (its signature minus the
# arguments the bundle adjuster owns). Listed here rather than read from scipy so that
# loading a config does not import scipy.optimize; a test checks it against scipy.
LEAST_SQUARES_OPTIONS: tuple[str, ...] = (
    "method",
    "ftol",
    "xtol",
    "gtol",
    "x_scale",
    "loss",
    "f_scale",
    "diff_step",
    "tr_solver",
    "tr_options",
    "max_nfev",
    "verbose",
    "workers",
)


def _table_problems(table: Mapping, cls: type, path: str, extra_known: tuple[str, ...] = ()) -> list[str]:
    """Problems with a flat parameter table described by a params dataclass."""
    checks = {f.name: f.metadata["check"] for f in fields(cls) if "check" in f.metadata}
    problems = []
    for key, value in table.items():
        if key in checks:
            why = checks[key](value)
            if why:
                problems.append(f"{path}.{key}: {why}")
        elif key not in extra_known:
            known = ", ".join([*checks, *extra_known])
            problems.append(f"{path}.{key}: unknown parameter (known: {known})")
    return problems


def _build_params(cls: type, table: Mapping) -> Any:
    """Instantiate a params dataclass from an already-validated table."""
    kwargs = {}
    for f in fields(cls):
        if f.name not in table:
            continue
        value, kind = table[f.name], f.metadata.get("kind")
        if value is not None and kind is float:
            value = float(value)
        elif value is not None and kind is tuple:
            value = tuple(tuple(v) if isinstance(v, (list, tuple)) else v for v in value)
        kwargs[f.name] = value
    return cls(**kwargs)


# -- YAML loading --------------------------------------------------------------


class _YamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    """SafeLoader that also reads ``1e-8`` as a float (YAML 1.1 would read it as text)."""


_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _duplicate_key_problems(node: yaml.Node | None, path: str = "") -> list[str]:
    """Keys given twice in one YAML mapping (PyYAML would silently keep the last)."""
    problems: list[str] = []
    if isinstance(node, yaml.MappingNode):
        first_line: dict[Any, int] = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                problems += _duplicate_key_problems(value_node, f"{path}.<complex key>")
                continue
            key = key_node.value
            where = f"{path}.{key}" if path else str(key)
            line = key_node.start_mark.line + 1
            if key in first_line:
                what = (
                    f"(view {path.rsplit('.', 1)[-1]!r}, point {key!r}) is filled twice"
                    if path.startswith("pose2d.output_points.")
                    else "key given twice"
                )
                problems.append(f"{where}: {what} (lines {first_line[key]} and {line})")
            else:
                first_line[key] = line
            problems += _duplicate_key_problems(value_node, where)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            problems += _duplicate_key_problems(item, f"{path}[{i}]")
    return problems


def _parse_text(text: str, fmt: str, source: str) -> dict:
    if fmt == "toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"{source}: not valid TOML ({err}); fix the syntax") from None
    else:
        try:
            duplicates = _duplicate_key_problems(yaml.compose(text, Loader=_YamlLoader))
            data = yaml.load(text, Loader=_YamlLoader)
        except yaml.YAMLError as err:
            detail = " ".join(str(err).split())
            raise ConfigError(f"{source}: not valid YAML ({detail}); fix the syntax") from None
        if duplicates:
            raise ConfigError(_problem_report(source, duplicates))
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the top level must be a mapping of tables, got {type(data).__name__}")
    return data


def _problem_report(source: str, problems: list[str]) -> str:
    count = f"{len(problems)} problem{'s' if len(problems) != 1 else ''}"
    return f"invalid config {source} ({count}; fix and re-run):\n" + "\n".join(
        f"  {p}" for p in problems
    )


# -- validation ----------------------------------------------------------------


def _named_entries(entries: Any, path: str, problems: list[str]) -> dict[str, dict]:
    """A list of ``{name: ..., ...}`` tables as ``name -> entry`` (problems recorded)."""
    if entries is None:
        return {}
    if not isinstance(entries, list):
        problems.append(f"{path}: expected a list of tables, {_got(entries)}")
        return {}
    out: dict[str, dict] = {}
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            problems.append(f"{path}[{i}]: expected a table, {_got(entry)}")
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


def _plan_problems(data: Mapping, point_names: tuple[str, ...], view_names: list[str] | None) -> list[str]:
    """Problems with the detection plan: sources, preprocessors, models, pathways, output_points."""
    problems: list[str] = []
    pose2d = data.get("pose2d") or {}
    sources = _named_entries(data.get("sources"), "sources", problems)
    for name, entry in sources.items():
        if "filename" in entry and not isinstance(entry["filename"], str):
            problems.append(f"sources.{name}.filename: expected a glob string, {_got(entry['filename'])}")
    preprocessors = _named_entries(pose2d.get("preprocessors"), "pose2d.preprocessors", problems)
    for name, entry in preprocessors.items():
        ops = entry.get("ops", [])
        if not isinstance(ops, list) or not all(isinstance(op, Mapping) and "op" in op for op in ops):
            problems.append(f"pose2d.preprocessors.{name}.ops: expected a list of tables each with an 'op' key")
    models = _named_entries(pose2d.get("models"), "pose2d.models", problems)
    n_channels: dict[str, int | None] = {}
    for name, entry in models.items():
        n_out = entry.get("n_out_channels")
        if n_out is not None and not (_is_int(n_out) and n_out >= 1):
            problems.append(f"pose2d.models.{name}.n_out_channels: expected an integer >= 1, {_got(n_out)}")
            n_out = None
        n_channels[name] = n_out
        size = entry.get("input_size")
        if size is not None and not (
            isinstance(size, list) and len(size) == 2 and all(_is_int(s) and s > 0 for s in size)
        ):
            problems.append(f"pose2d.models.{name}.input_size: expected [height, width] in pixels, got {size!r}")
        if "weights" in entry and not isinstance(entry["weights"], str):
            problems.append(f"pose2d.models.{name}.weights: expected a path string ('' for the published weights)")
    pathways = _named_entries(pose2d.get("pathways"), "pose2d.pathways", problems)
    pathway_model: dict[str, str | None] = {}
    for name, entry in pathways.items():
        where = f"pose2d.pathways.{name}"
        _reference(entry.get("source"), sources, "source", f"{where}.source", problems)
        if entry.get("preprocessor") is not None:
            _reference(entry["preprocessor"], preprocessors, "preprocessor", f"{where}.preprocessor", problems)
        ok = _reference(entry.get("model"), models, "model", f"{where}.model", problems)
        pathway_model[name] = entry["model"] if ok else None

    output_points = pose2d.get("output_points")
    if output_points is None:
        return problems
    if not isinstance(output_points, Mapping):
        return [*problems, "pose2d.output_points: expected a mapping view -> point -> {pathway, out_channel}"]
    known_points = set(point_names)
    for view, table in output_points.items():
        where_view = f"pose2d.output_points.{view}"
        if view_names is not None and view not in view_names:
            problems.append(f"{where_view}: unknown view {view!r} (cameras: {', '.join(view_names)})")
        if not isinstance(table, Mapping):
            problems.append(f"{where_view}: expected a mapping point -> {{pathway, out_channel}}")
            continue
        for point, slot in table.items():
            where = f"{where_view}.{point}"
            if known_points and point not in known_points:
                problems.append(f"{where}: unknown point {point!r} (known: {', '.join(point_names)})")
            if not isinstance(slot, Mapping):
                problems.append(f"{where}: expected {{pathway: ..., out_channel: ...}}, {_got(slot)}")
                continue
            extra = sorted(set(slot) - {"pathway", "out_channel"})
            if extra:
                problems.append(f"{where}: unknown key(s) {', '.join(extra)} (known: pathway, out_channel)")
            has_pathway = _reference(slot.get("pathway"), pathways, "pathway", f"{where}.pathway", problems)
            channel = slot.get("out_channel")
            if not (_is_int(channel) and channel >= 0):
                problems.append(f"{where}.out_channel: expected an integer >= 0, {_got(channel)}")
                continue
            n_out = n_channels.get(pathway_model.get(slot.get("pathway")) or "") if has_pathway else None
            if n_out is not None and channel >= n_out:
                model = pathway_model[slot["pathway"]]
                problems.append(
                    f"{where}.out_channel: {channel} is out of range for model {model!r}"
                    f" (n_out_channels {n_out}: use 0..{n_out - 1})"
                )
    return problems


@lru_cache(maxsize=1)
def _default_skeleton_table() -> dict:
    """The packaged default config's ``skeleton`` table (read once; treat as read-only)."""
    return Config.default().data["skeleton"]


def _default_point_names() -> tuple[str, ...]:
    return tuple(_default_skeleton_table()["point_names"])


def validate_config(data: Any) -> list[str]:
    """Every problem with a parsed config mapping, one ``"<key path>: <problem>"`` line each.

    Parameters
    ----------
    data
        The parsed config.

    Returns
    -------
    list of str
        The problems; empty when the config is valid.
    """
    if not isinstance(data, Mapping):
        return [f"<top level>: expected a mapping of tables, {_got(data)}"]
    problems = [
        f"{key}: unknown top-level table (known: {', '.join(TOP_LEVEL_KEYS)})"
        for key in data
        if key not in TOP_LEVEL_KEYS
    ]
    table_kinds = {
        "io": _mapping(),
        "skeleton": _mapping(),
        "cameras": _mapping(),
        "pipeline": _mapping(),
        "pose2d": _mapping(),
        "bundle_adjustment": _mapping(),
        "pictorial_structures": _mapping(),
        "triangulation": _mapping(),
        "visualization": _mapping(),
        "calibration": _mapping(nullable=True),
        "demo": _mapping(nullable=True),
        "sources": lambda v: None if isinstance(v, list) else f"expected a list of tables, {_got(v)}",
        "recordings": lambda v: None
        if isinstance(v, (list, str))
        else f"expected a list of recordings or the path of a .tsv sheet, {_got(v)}",
        "recursive": _boolean,
        "outdir": lambda v: None if v is None or isinstance(v, str) else f"expected a path template or null, {_got(v)}",
    }
    bad_tables = set()
    for key, check in table_kinds.items():
        if key in data:
            why = check(data[key])
            if why:
                problems.append(f"{key}: {why}")
                bad_tables.add(key)

    def table(name: str) -> Mapping:
        return {} if name in bad_tables else (data.get(name) or {})

    if "skeleton" in data and "skeleton" not in bad_tables:
        skeleton_issues = skeleton_problems(data["skeleton"])
        problems += skeleton_issues
        names = data["skeleton"].get("point_names")
        point_names = tuple(names) if isinstance(names, list) else ()
    else:
        point_names = _default_point_names()

    cameras = table("cameras")
    view_names = [name for name in cameras if name != "defaults"]
    for name, spec in cameras.items():
        if not isinstance(spec, Mapping):
            problems.append(f"cameras.{name}: expected a table of camera parameters, {_got(spec)}")
    if not view_names and data.get("calibration"):
        view_names = None  # the rig comes from the calibration file: names unknown here

    pipeline_checks = {f"do_{stage}": _boolean for stage in STAGES}
    for key, value in table("pipeline").items():
        if key not in pipeline_checks:
            problems.append(f"pipeline.{key}: unknown parameter (known: {', '.join(pipeline_checks)})")
        elif pipeline_checks[key](value):
            problems.append(f"pipeline.{key}: {pipeline_checks[key](value)}")

    pose2d = table("pose2d")
    problems += _table_problems(pose2d, Pose2dParams, "pose2d", _POSE2D_PLAN_KEYS)
    if "import" in pose2d and _mapping(nullable=True)(pose2d["import"]):
        problems.append(f"pose2d.import: {_mapping(nullable=True)(pose2d['import'])}")
    if "sources" not in bad_tables and "pose2d" not in bad_tables:
        problems += _plan_problems(data, point_names, view_names)

    ba = table("bundle_adjustment")
    ba_fields = tuple(f.name for f in fields(BundleAdjustmentParams) if f.name != "least_squares")
    ls_keys = LEAST_SQUARES_OPTIONS
    for key, value in ba.items():
        where = f"bundle_adjustment.{key}"
        if key in ba_fields:
            continue
        if key not in ls_keys:
            problems.append(
                f"{where}: unknown parameter (known: {', '.join(ba_fields)}, or a"
                f" scipy.optimize.least_squares option: {', '.join(ls_keys)})"
            )
        elif key in _LEAST_SQUARES_CHECKS and _LEAST_SQUARES_CHECKS[key](value):
            problems.append(f"{where}: {_LEAST_SQUARES_CHECKS[key](value)}")
    problems += _table_problems(
        {k: v for k, v in ba.items() if k in ba_fields}, BundleAdjustmentParams, "bundle_adjustment"
    )
    if isinstance(ba.get("points_to_use"), (list, tuple)) and point_names:
        for point in ba["points_to_use"]:
            if isinstance(point, str) and point not in point_names:
                problems.append(
                    f"bundle_adjustment.points_to_use: unknown point {point!r} (known: {', '.join(point_names)})"
                )

    problems += _table_problems(table("pictorial_structures"), PictorialParams, "pictorial_structures")
    problems += _table_problems(table("triangulation"), TriangulationParams, "triangulation")

    for key, value in table("io").items():
        if not isinstance(value, Mapping):
            problems.append(f"io.{key}: expected a table, {_got(value)}")
    workers = table("io").get("image", {})
    if isinstance(workers, Mapping) and "workers" in workers and _integer(0)(workers["workers"]):
        problems.append(f"io.image.workers: {_integer(0)(workers['workers'])}")

    videos = table("visualization").get("videos")
    if videos is not None and not isinstance(videos, list):
        problems.append(f"visualization.videos: expected a list of video tables, {_got(videos)}")
    return problems


# -- canonical forms for stage_params ------------------------------------------


def _canonical(value: Any) -> Any:
    """JSON-ready copy with mapping keys sorted (order-bearing content is passed as lists)."""
    if isinstance(value, Mapping):
        return {str(k): _canonical(value[k]) for k in sorted(value, key=str)}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if hasattr(value, "item") and callable(value.item):  # numpy scalar
        return value.item()
    return value


def _plain(value: Any) -> Any:
    """YAML-dumpable copy: tuples become lists, numpy scalars Python numbers; key order kept."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "item") and callable(value.item):
        return value.item()
    return value


# -- the config object ---------------------------------------------------------


class Config:
    """A loaded, validated flylib run configuration.

    Build one with :meth:`from_file` (``.yaml``/``.yml``/``.toml``), :meth:`from_yaml`,
    :meth:`from_toml`, :meth:`from_dict` or :meth:`default`.

    Attributes
    ----------
    data
        The parsed mapping.
    text
        The exact source text when read from a file (``None`` for a dict): what
        :meth:`save_snapshot` writes back byte-for-byte.
    source
        The file it was read from, or ``None``.
    format
        ``"yaml"`` or ``"toml"``: the snapshot's format.
    """

    def __init__(
        self,
        data: Mapping,
        *,
        text: str | None = None,
        source: Path | None = None,
        format: str = "yaml",
    ) -> None:
        self.data: dict = dict(data)
        self.text = text
        self.source = source
        self.format = format
        problems = validate_config(self.data)
        if problems:
            error = ConfigError(_problem_report(str(source or "<dict>"), problems))
            error.problems = problems  # type: ignore[attr-defined]
            raise error

    def __repr__(self) -> str:
        return f"Config(source={str(self.source) if self.source else None!r})"

    # -- construction --------------------------------------------------------

    @classmethod
    def from_file(cls, path: str | Path) -> Config:
        """Load a config, choosing YAML or TOML by the file suffix.

        Parameters
        ----------
        path
            A ``.yaml``, ``.yml`` or ``.toml`` file.

        Returns
        -------
        Config
            The loaded, validated config.

        Raises
        ------
        ConfigError
            If the file is missing, has another suffix, does not parse or is invalid.
        """
        suffix = Path(path).suffix.lower()
        if suffix in (".yaml", ".yml"):
            return cls.from_yaml(path)
        if suffix == ".toml":
            return cls.from_toml(path)
        raise ConfigError(f"{path}: unknown config format {suffix!r}; use a .yaml, .yml or .toml file")

    @classmethod
    def from_yaml(cls, path: str | Path) -> Config:
        """Load a YAML config file (keeping its text for the snapshot).

        Parameters
        ----------
        path
            The YAML file.

        Returns
        -------
        Config
            The loaded, validated config.
        """
        return cls._from_path(Path(path), "yaml")

    @classmethod
    def from_toml(cls, path: str | Path) -> Config:
        """Load a TOML config file (keeping its text for the snapshot).

        Parameters
        ----------
        path
            The TOML file.

        Returns
        -------
        Config
            The loaded, validated config.
        """
        return cls._from_path(Path(path), "toml")

    @classmethod
    def _from_path(cls, path: Path, fmt: str) -> Config:
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raise ConfigError(f"{path}: config file not found; check the path") from None
        except IsADirectoryError:
            raise ConfigError(f"{path}: is a directory, not a config file") from None
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise ConfigError(f"{path}: not UTF-8 text ({err}); save it as UTF-8") from None
        return cls(_parse_text(text, fmt, str(path)), text=text, source=path, format=fmt)

    @classmethod
    def from_dict(cls, data: Mapping) -> Config:
        """Wrap an already-parsed mapping (library use, Snakemake's ``config``).

        Parameters
        ----------
        data
            The parsed config; it is deep-copied.

        Returns
        -------
        Config
            The validated config (no source text).
        """
        return cls(copy.deepcopy(dict(data)))

    @classmethod
    def default(cls) -> Config:
        """The packaged default config (:data:`DEFAULT_CONFIG_PATH`): the 7-camera fly rig."""
        return cls.from_yaml(DEFAULT_CONFIG_PATH)

    # -- typed per-stage views -------------------------------------------------

    @property
    def pose2d(self) -> Pose2dParams:
        """The scalar ``pose2d`` settings."""
        return _build_params(Pose2dParams, self.data.get("pose2d") or {})

    @property
    def triangulation(self) -> TriangulationParams:
        """The ``triangulation`` table."""
        return _build_params(TriangulationParams, self.data.get("triangulation") or {})

    @property
    def pictorial(self) -> PictorialParams:
        """The ``pictorial_structures`` table."""
        return _build_params(PictorialParams, self.data.get("pictorial_structures") or {})

    @property
    def bundle_adjustment(self) -> BundleAdjustmentParams:
        """The ``bundle_adjustment`` table; keys it does not name go to ``least_squares``."""
        table = dict(self.data.get("bundle_adjustment") or {})
        own = {f.name for f in fields(BundleAdjustmentParams)}
        leftovers = {k: v for k, v in table.items() if k not in own}
        params = _build_params(BundleAdjustmentParams, {k: v for k, v in table.items() if k in own})
        return BundleAdjustmentParams(**{**params.__dict__, "least_squares": leftovers})

    @property
    def io(self) -> IoParams:
        """Frame-reading settings (``io.image.workers``; 0 means let the reader choose)."""
        workers = ((self.data.get("io") or {}).get("image") or {}).get("workers")
        return IoParams(image_workers=workers or None)

    @property
    def visualization(self) -> dict:
        """The raw ``visualization`` table (parsed by ``flylib.visualization``)."""
        return self.data.get("visualization") or {}

    @property
    def videos(self) -> list:
        """The parsed output-video specs (``flylib.visualization.specs.read_video_specs``)."""
        from .visualization.specs import read_video_specs

        return read_video_specs(self)

    def detection_plan(self) -> Any:
        """The parsed 2D detection plan (``flylib.pose2d.plan.DetectionPlan.from_config``)."""
        from .pose2d.plan import DetectionPlan

        return DetectionPlan.from_config(self)

    @property
    def import_spec(self) -> dict | None:
        """The ``pose2d.import`` table (read 2D from another tool), or ``None``."""
        return (self.data.get("pose2d") or {}).get("import")

    # -- pipeline orchestration ---------------------------------------------

    def stage_flags(self) -> dict[str, bool]:
        """Which stages are enabled (``pipeline.do_<stage>``, else :data:`STAGE_DEFAULTS`).

        Returns
        -------
        dict of str to bool
            ``stage -> enabled`` for every stage in :data:`STAGES`.
        """
        pipeline = self.data.get("pipeline") or {}
        return {stage: bool(pipeline.get(f"do_{stage}", STAGE_DEFAULTS[stage])) for stage in STAGES}

    def stage_params(self, stage: str) -> dict:
        """The exact config subset that affects ``stage``'s result.

        Deterministic and JSON-serialisable; performance-only knobs never appear, so
        changing them re-runs nothing.

        - ``pose2d``: sources, detection plan, precision, import spec, skeleton point
          names, view names (the V axis) and the candidates' ``k`` (not whether
          pictorial structures is on: its candidates are an extra output of the same
          detection). Not the camera geometry.
        - ``bundle_adjustment``: its table, the rig, the skeleton's points and limbs.
        - ``pictorial_structures``: its table, the skeleton's points and limbs, and the
          config rig when bundle adjustment is off (otherwise the rig arrives in the
          bundle-adjustment artifact).
        - ``triangulation``: the method and the knobs that method reads, where its 2D
          comes from, and the config rig when bundle adjustment is off.
        - ``assemble``: the rig and the whole skeleton (palette included).
        - ``visualization``: the visualization table and the skeleton palette.

        Parameters
        ----------
        stage
            One of :data:`PARAM_STAGES`.

        Returns
        -------
        dict
            The parameters, with mapping keys in sorted order.
        """
        flags = self.stage_flags()
        if stage == "pose2d":
            pose2d = self.data.get("pose2d") or {}
            params: dict[str, Any] = {
                "sources": self.data.get("sources") or [],
                "plan": {key: pose2d.get(key) for key in _POSE2D_PLAN_KEYS if key != "import"},
                "precision": self.pose2d.precision,
                "import": pose2d.get("import"),
                "point_names": list(self._point_names()),
                "views": self.view_names(),
                # always, so that toggling pictorial structures re-runs no detection
                # (the candidates are a separate output that exists only while it is on)
                "candidates": {"k": self.pictorial.k},
            }
        elif stage == "bundle_adjustment":
            ba = asdict(self.bundle_adjustment)
            ba["least_squares"] = {
                k: v for k, v in ba["least_squares"].items() if k not in _LEAST_SQUARES_PERF
            }
            params = {"bundle_adjustment": ba, "rig": self._rig(), "skeleton": self._skeleton_structure()}
        elif stage == "pictorial_structures":
            params = {
                "pictorial_structures": asdict(self.pictorial),
                "skeleton": self._skeleton_structure(),
                "rig": None if flags["bundle_adjustment"] else self._rig(),
            }
        elif stage == "triangulation":
            params = {
                "triangulation": self.triangulation.method_params(),
                "points_from": "pictorial_structures" if flags["pictorial_structures"] else "pose2d",
                "rig": None if flags["bundle_adjustment"] else self._rig(),
            }
        elif stage == "assemble":
            params = {
                "rig": self._rig(),
                "skeleton": {**self._skeleton_structure(), "palette": self._palette(), "name": self._skeleton_name()},
            }
        elif stage == "visualization":
            params = {"visualization": self.visualization, "palette": self._palette()}
        else:
            raise ValueError(f"unknown stage {stage!r} (known: {', '.join(PARAM_STAGES)})")
        canonical = _canonical(params)
        json.dumps(canonical)  # fail here, not in the workflow, if something is not JSON-able
        return canonical

    def _point_names(self) -> tuple[str, ...]:
        spec = self.data.get("skeleton")
        return tuple(spec["point_names"]) if spec else _default_point_names()

    def _skeleton_spec(self) -> Mapping:
        return self.data.get("skeleton") or _default_skeleton_table()

    def _skeleton_structure(self) -> dict:
        limbs = self._skeleton_spec().get("limb_points") or {}
        return {"point_names": list(self._point_names()), "limbs": [[k, list(v)] for k, v in limbs.items()]}

    def _palette(self) -> dict:
        return dict(self._skeleton_spec().get("limb_palette") or {})

    def _skeleton_name(self) -> str:
        return str(self._skeleton_spec().get("name", "skeleton"))

    def _rig(self) -> dict:
        return {
            "views": self.view_names(),
            "cameras": self.data.get("cameras") or {},
            "calibration": self.data.get("calibration"),
        }

    # -- structured sections ---------------------------------------------------

    def view_names(self) -> list[str]:
        """The camera (view) names in config order: the V axis of every points array.

        Taken from the ``cameras`` table (``defaults`` excluded); a config whose rig
        comes from a calibration file and names no cameras falls back to the
        ``pose2d.output_points`` views.
        """
        names = [name for name in (self.data.get("cameras") or {}) if name != "defaults"]
        if not names:
            names = list(((self.data.get("pose2d") or {}).get("output_points") or {}))
        return names

    def camera_table(self) -> tuple[dict, dict]:
        """Split ``cameras`` into the shared defaults and the per-camera specs.

        Returns
        -------
        defaults, cameras : dict
            ``cameras.defaults`` and ``name -> spec`` for every real camera.
        """
        cameras = dict(self.data.get("cameras") or {})
        defaults = cameras.pop("defaults", {}) or {}
        return dict(defaults), cameras

    def source_patterns(self) -> dict[str, str]:
        """Each footage source's glob (``sources[].name -> filename``), in config order.

        A source without ``filename`` uses its name as the pattern.
        """
        return {s["name"]: s.get("filename", s["name"]) for s in self.data.get("sources") or []}

    def skeleton(self) -> Skeleton:
        """The configured skeleton, or the default fly skeleton when there is no ``skeleton`` table."""
        from .skeleton import Skeleton

        return Skeleton.from_config(self) if self.data.get("skeleton") else Skeleton.fly()

    def camera_group(self, image_sizes: Mapping[str, tuple[int, int]] | None = None) -> CameraGroup:
        """The configured camera rig (see ``flylib.cameras.CameraGroup.from_config``).

        Parameters
        ----------
        image_sizes
            ``view -> (height, width)`` of the raw footage, used for the principal point
            where the config gives none.

        Returns
        -------
        CameraGroup
            The rig.
        """
        from .cameras import CameraGroup

        return CameraGroup.from_config(self, image_sizes=image_sizes)

    # -- snapshot ----------------------------------------------------------------

    def snapshot_text(self) -> str:
        """The text :meth:`save_snapshot` writes: the source text, or a YAML dump for a dict."""
        if self.text is not None:
            return self.text
        return yaml.safe_dump(_plain(self.data), sort_keys=False, default_flow_style=None, allow_unicode=True)

    def save_snapshot(self, outdir: str | Path) -> Path:
        """Write the config that drives this run to ``<outdir>/config.yaml`` (or ``.toml``).

        The source text is copied byte-for-byte, atomically; a config built from a
        dict is written as YAML. A snapshot of the other format left by an earlier
        run is removed so the directory holds exactly one.

        Parameters
        ----------
        outdir
            The run's output directory (created if needed).

        Returns
        -------
        Path
            The snapshot file.
        """
        from .results import atomic_path

        fmt = self.format if self.text is not None else "yaml"
        target = Path(outdir) / f"config.{fmt}"
        with atomic_path(target) as tmp:
            tmp.write_bytes(self.snapshot_text().encode("utf-8"))
        stale = target.with_suffix(".toml" if fmt == "yaml" else ".yaml")
        stale.unlink(missing_ok=True)
        return target
