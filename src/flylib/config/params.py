"""Typed per-stage views: the ``*Params`` dataclasses, their table checks and builders.

Each field is declared once with :func:`~flylib.config.checks.param`: its default (the one place it
is written; the algorithms' keyword defaults read it from the class), check and conversion. A
stage's params track every field except a ``track_default=False`` one at its default: give a new
knob that marker so results made before it existed keep their params hash.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

from ..errors import unknown_key
from ..stages import derived, registry
from .checks import (
    Check,
    boolean,
    choice,
    integer,
    is_tracked,
    mapping,
    number,
    param,
    string,
    string_groups,
    string_list,
)
from .constants import (
    BA_DISTORTION_MODES,
    BA_SOLVERS,
    FRAME_SAMPLINGS,
    PRECISIONS,
    TETHERED_RIGID_POINTS,
    TRIANGULATION_METHODS,
)


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
        The compiled detector (:mod:`flylib.pose2d.compiled`): ``true``, ``false`` or ``auto``
        (when it beats eager; performance only).
    """

    precision: str = param("bfloat16", choice(*PRECISIONS))
    batch_size: int = param(16, integer(1))
    decode_buffer: int = param(4, integer(1))
    device: str = param("auto", string)
    compile: bool | str = param("auto", choice(True, False, "auto"))


#: Each triangulation method's own knobs: ``triangulation`` key -> its function's keyword
#: (the stage's params track the keys, :func:`flylib.triangulation.reconstruct` passes keywords).
TRIANGULATION_KNOBS: dict[str, dict[str, str]] = {
    "ransac": {"ransac_threshold": "threshold", "min_inliers": "min_inliers"},
    "greedy": {"reproj_threshold": "reproj_threshold", "max_drops": "max_drops"},
    "dlt": {},
}


@dataclass(frozen=True)
class TriangulationParams:
    """The ``triangulation`` table.

    Attributes
    ----------
    method
        ``ransac`` (largest consistent view set), ``greedy`` (drop the worst view while over
        ``reproj_threshold``) or ``dlt`` (plain least squares).
    weigh_by_confidence
        Scale each view's equations by ``sqrt(conf)``.
    ransac_threshold, min_inliers
        ``ransac``: inlier reprojection radius in pixels and minimum agreeing views.
    reproj_threshold, max_drops
        ``greedy``: reprojection error in pixels that triggers a drop, and the most views dropped
        per point.
    """

    method: str = param("ransac", choice(*TRIANGULATION_METHODS))
    weigh_by_confidence: bool = param(False, boolean)
    ransac_threshold: float = param(15.0, number(0, exclusive=True), kind=float)
    min_inliers: int = param(2, integer(2))
    reproj_threshold: float = param(40.0, number(0, exclusive=True), kind=float)
    max_drops: int = param(5, integer(0))

    def method_params(self) -> dict[str, Any]:
        """The knobs the chosen ``method`` reads (plus ``weigh_by_confidence``), as the stage
        tracks them (a ``track_default=False`` knob only when not at its default)."""
        return {
            "method": self.method,
            "weigh_by_confidence": self.weigh_by_confidence,
            **{
                name: getattr(self, name)
                for name in TRIANGULATION_KNOBS[self.method]
                if is_tracked(self, name)
            },
        }

    def method_kwargs(self) -> dict[str, Any]:
        """The chosen ``method``'s knobs under its function's keyword names."""
        return {
            keyword: getattr(self, name)
            for name, keyword in TRIANGULATION_KNOBS[self.method].items()
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

    k: int = param(5, integer(1))
    temporal: bool = param(False, boolean)
    lam: float = param(1.0, number(0), kind=float)
    bone_max_frames: int | None = param(100, integer(1, nullable=True))
    max_hyp: int | None = param(None, integer(1, nullable=True))
    inlier_px: float | None = param(None, number(0, exclusive=True, nullable=True), kind=float)
    huber: float | None = param(None, number(0, exclusive=True, nullable=True), kind=float)
    mu: float | None = param(None, number(0, nullable=True), kind=float)
    nms: float | None = param(None, number(0, nullable=True), kind=float)

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
    solver
        ``lm`` (Levenberg-Marquardt, reduced camera system) or ``scipy`` (``least_squares``).
    distortion
        ``auto`` (coefficients that start at zero stay zero on long lenses), ``free`` or ``fixed``.
    max_rounds, outlier_factor, outlier_min_px
        Outlier rounds: observations beyond ``outlier_factor`` x the median error (at least
        ``outlier_min_px``) sit out; repeated until the inlier set is stable.
    reseed_px
        Cameras whose starting median error exceeds this are resected by PnP first (null: never).
    bone_lengths, symmetric_bones, length_weight
        One unknown length per bone over all frames (left = right with ``symmetric_bones``),
        ``length_weight`` px per 100 % deviation.
    rigid_points
        Points that do not move over the recording when the body is fixed (a tethered fly's
        thorax-coxa joints); used only if the starting triangulation shows them still.
    warn_ratio
        Warn when the reduced Hessian's weakest non-gauge direction is below this x its strongest.
    session
        One solve over the recordings of one session (one rig), one ``calibration.toml`` they all
        read (:mod:`flylib.sessions`); not in the per-recording solve's params.
    least_squares
        Every other key, passed to ``scipy.optimize.least_squares`` (e.g. ``max_nfev``, ``loss``).
    """

    points_to_use: tuple[str, ...] | None = param(None, string_list(nullable=True), kind=tuple)
    fixed: tuple[str, ...] = param(("*.intr",), string_list(), kind=tuple)
    shared: tuple[tuple[str, ...], ...] = param((), string_groups, kind=tuple)
    weigh_by_confidence: bool = param(False, boolean)
    max_frames: int | None = param(200, integer(1, nullable=True))
    frame_sampling: str = param("even", choice(*FRAME_SAMPLINGS))
    solver: str = param("lm", choice(*BA_SOLVERS))
    distortion: str = param("auto", choice(*BA_DISTORTION_MODES))
    max_rounds: int = param(10, integer(1))
    outlier_factor: float = param(5.0, number(0, exclusive=True))
    outlier_min_px: float = param(3.0, number(0))
    reseed_px: float | None = param(100.0, number(0, exclusive=True, nullable=True))
    bone_lengths: bool = param(True, boolean)
    symmetric_bones: bool = param(True, boolean)
    length_weight: float = param(100.0, number(0, exclusive=True))
    rigid_points: tuple[str, ...] = param(TETHERED_RIGID_POINTS, string_list(), kind=tuple)
    warn_ratio: float = param(1e-9, number(0))
    session: bool = param(False, boolean, track_default=False)
    least_squares: dict[str, Any] = field(default_factory=dict)

    def sequence_kwargs(self, point_names: Sequence[str]) -> dict[str, Any]:
        """Keyword arguments for :func:`flylib.bundle_adjustment.bundle_adjust_sequence`
        (``rigid_points`` limited to ``point_names``, ``least_squares`` options flat)."""
        kwargs = {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name not in ("least_squares", "session")
        }
        names = set(point_names)
        kwargs["rigid_points"] = [p for p in self.rigid_points if p in names]
        return {**kwargs, **self.least_squares}

    @classmethod
    def from_table(cls, table: Mapping) -> BundleAdjustmentParams:
        """The table's own keys as fields; every other key goes to ``least_squares`` (a stage's
        tracked params hold them under ``least_squares`` already)."""
        own = {f.name for f in fields(cls)} - {"least_squares"}
        leftovers = {k: v for k, v in table.items() if k not in own}
        nested = leftovers.pop("least_squares", None) or {}
        params = build_params(cls, {k: v for k, v in table.items() if k in own})
        return replace(params, least_squares={**nested, **leftovers})


@dataclass(frozen=True)
class IoParams:
    """Frame-reading settings (performance only).

    Attributes
    ----------
    image_workers
        Threads decoding image sequences; ``None`` lets the reader choose.
    on_corrupt_frame
        A corrupt image in a sequence: ``"error"`` fails the job naming the file; ``"missing"``
        warns and marks the frame missing (2D NaN), and is part of pose2d's params.
    """

    image_workers: int | None = None
    on_corrupt_frame: str = "error"

    @classmethod
    def from_table(cls, table: Mapping) -> IoParams:
        """``io.image.workers`` (0 means let the reader choose) and ``io.on_corrupt_frame``."""
        workers = (table.get("image") or {}).get("workers")
        on_corrupt = table.get("on_corrupt_frame") or "error"
        return cls(image_workers=workers or None, on_corrupt_frame=on_corrupt)


LEAST_SQUARES_CHECKS: dict[str, Check] = {
    "method": choice("trf", "dogbox", "lm"),
    "loss": choice("linear", "soft_l1", "huber", "cauchy", "arctan"),
    "f_scale": number(0, exclusive=True),
    "max_nfev": integer(1, nullable=True),
    "ftol": number(0, nullable=True),
    "xtol": number(0, nullable=True),
    "gtol": number(0, nullable=True),
    "diff_step": number(0, exclusive=True, nullable=True),
    "tr_solver": choice("exact", "lsmr", None),
    "tr_options": mapping(),
    "verbose": choice(0, 1, 2),
}


# scipy.optimize.least_squares options a config may set (minus those the bundle adjuster owns);
# listed so loading a config does not import scipy.optimize; a test checks it against scipy.
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


def table_problems(
    table: Mapping, cls: type, path: str, extra_known: tuple[str, ...] = ()
) -> list[str]:
    """Problems with a flat parameter table described by a params dataclass."""
    checks = {f.name: f.metadata["check"] for f in fields(cls) if "check" in f.metadata}
    problems = []
    for key, value in table.items():
        if key in checks:
            why = checks[key](value)
            if why:
                problems.append(f"{path}.{key}: {why}")
        elif key not in extra_known:
            problems.append(
                f"{path}.{key}: {unknown_key('parameter', key, [*checks, *extra_known])}"
            )
    return problems


def build_params(cls: type, table: Mapping) -> Any:
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


def _param_tables() -> dict[str, type]:
    tables = {s.name: s.params for s in registry() if s.params}
    first = next(iter(tables.items()), None)  # io after the first stage's: the reference's order
    return dict([first, ("io", IoParams)] if first else [("io", IoParams)]) | tables


#: Config table name -> its typed params dataclass (a stage's from its record, and ``io``):
#: what :meth:`Config.params <flylib.config.Config.params>` builds,
#: :func:`~flylib.config.validate_config` checks and the docs' config reference describes.
PARAM_TABLES: dict[str, type] = derived(_param_tables, mapping=True)
