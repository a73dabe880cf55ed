"""The pose2d stage: footage (or another tool's 2D) -> ``<outdir>/stages/pose2d.h5`` and,
while pictorial structures is on, the detector's candidate peaks beside it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config.constants import POSE2D_PLAN_KEYS
from ..config.params import IoParams, PictorialParams, Pose2dParams
from ..config.sources import feeding_sources, patterns_of
from ..errors import FootageError, ResultsError
from ..pose2d.plan import DECODING_CONVENTION, DetectionPlan
from ..stages import Stage
from .inputs import SkeletonSpec, StageInputs, register

if TYPE_CHECKING:  # pragma: no cover
    from ..config import Config
    from ..interop.importer import ImportTarget
    from ..results import Pose2dData

__all__ = [
    "Pose2dInputs",
    "Pose2dRuntime",
    "compute_pose2d",
    "import_inputs",
    "import_target",
    "run_pose2d",
]

#: The detection plan's tables in the ``pose2d`` table (``import`` is tracked apart).
PLAN_KEYS = tuple(key for key in POSE2D_PLAN_KEYS if key != "import")
#: The untracked ``pose2d`` settings (:class:`~flylib.config.params.Pose2dParams`).
DETECTOR_KNOBS = ("batch_size", "decode_buffer", "device", "compile")


RECORD = Stage(
    "pose2d", default_on=True, params=Pose2dParams, artifact="pose2d.h5", results_group=True
)


@dataclass(frozen=True)
class Pose2dRuntime:
    """The pose2d stage's untracked knobs: they change its speed, never its 2D.
    ``image_workers`` ``None``: the reader chooses. ``candidates_k`` (``pictorial_structures.k``)
    names the candidates file (``stages/candidates_k<k>.h5``), so it needs no tracking."""

    batch_size: int = Pose2dParams.batch_size
    decode_buffer: int = Pose2dParams.decode_buffer
    device: str = Pose2dParams.device
    compile: bool | str = Pose2dParams.compile
    image_workers: int | None = IoParams.image_workers
    candidates_k: int = PictorialParams.k

    @classmethod
    def from_config(cls, config: Config) -> Pose2dRuntime:
        return cls(
            **{knob: getattr(config.pose2d, knob) for knob in DETECTOR_KNOBS},
            image_workers=config.io.image_workers,
            candidates_k=int(config.pictorial_structures.k),
        )


@register
@dataclass(frozen=True)
class Pose2dInputs(StageInputs):
    """What the pose2d stage reads. ``plan``: the ``pose2d`` plan tables (:data:`PLAN_KEYS`,
    absent ones ``None``); ``import_spec`` ``None``: the detector runs, unless the recording has
    its own. ``on_corrupt_frame`` is tracked only when not ``"error"`` (older artifacts'
    params stay valid)."""

    STAGE = RECORD.name

    sources: tuple[Mapping[str, Any], ...]
    plan: Mapping[str, Any]
    precision: str
    import_spec: Mapping[str, Any] | None = field(metadata={"key": "import"})
    point_names: tuple[str, ...]
    views: tuple[str, ...]
    on_corrupt_frame: str = field(
        default=IoParams.on_corrupt_frame, metadata={"track_default": False}
    )
    runtime: Pose2dRuntime = Pose2dRuntime()

    @classmethod
    def from_config(cls, config: Config) -> Pose2dInputs:
        pose2d = config.data.get("pose2d") or {}
        return cls(
            sources=tuple(config.data.get("sources") or []),
            plan={key: pose2d.get(key) for key in PLAN_KEYS},
            precision=config.pose2d.precision,
            import_spec=pose2d.get("import"),
            point_names=SkeletonSpec.from_config(config).point_names,
            views=tuple(config.view_names()),
            on_corrupt_frame=config.io.on_corrupt_frame,
            runtime=Pose2dRuntime.from_config(config),
        )

    def params(self) -> dict:
        """The tracked params (:meth:`StageInputs.params`) and the heatmap decoding convention."""
        # Not PS's candidate peaks: a separate output named by k, existing only while PS is
        # on, so toggling PS or editing k with it off re-runs no detection.
        return {
            **super().params(),
            "decoding": DECODING_CONVENTION,  # heatmap cell -> pixel (flylib.pose2d.plan)
        }

    def detector_params(self) -> Pose2dParams:
        """The detector's settings: the tracked precision and the untracked knobs."""
        return Pose2dParams(
            precision=self.precision,
            **{knob: getattr(self.runtime, knob) for knob in DETECTOR_KNOBS},
        )

    def io(self) -> IoParams:
        """Frame reading: ``io.image.workers`` and ``io.on_corrupt_frame``."""
        return IoParams(
            image_workers=self.runtime.image_workers, on_corrupt_frame=self.on_corrupt_frame
        )

    def detection_plan(self) -> DetectionPlan:
        return DetectionPlan.from_tables(self.sources, self.plan, self.views, self.point_names)

    def source_patterns(self) -> dict[str, str]:
        """``source -> footage glob`` (:func:`flylib.config.sources.patterns_of`)."""
        return patterns_of(self.sources)

    def import_target(self) -> ImportTarget:
        """The views, points and footage imported 2D is placed on."""
        from ..interop.importer import ImportTarget

        plan = self.plan
        view_sources = feeding_sources(self.views, self.sources, plan)
        output_points = plan.get("output_points") or {}
        return ImportTarget(
            views=self.views,
            point_names=self.point_names,
            view_sources=view_sources,
            source_patterns=self.source_patterns() if view_sources else {},
            plan_points={
                str(view): tuple(entries)
                for view, entries in output_points.items()
                if isinstance(entries, dict)
            },
        )


def import_target(config: Config) -> ImportTarget:
    """What :func:`flylib.import_points2d` places 2D on under ``config``: its views, points,
    footage and each view's planned points (:meth:`Pose2dInputs.import_target`)."""
    return Pose2dInputs.from_config(config).import_target()


def import_inputs(
    target: ImportTarget, spec: Mapping | None, recording_dir: str | Path
) -> list[Path]:
    """The files a recording's imported 2D is read from (none without an import spec): the
    pose2d rule's inputs besides the footage, so editing one re-runs pose2d. ImportFormatError
    for a bad spec or a ``files`` pattern that finds no file, or several, for a view."""
    if not spec:
        return []
    from ..interop.importer import import_files, import_spec

    files = import_files(target, import_spec(spec), recording_dir)
    return sorted({path for path in files.values() if path is not None})


# Imported 2D may stray a little past the frame (edge peaks, sub-pixel refinement); more than
# _OUTSIDE_FRACTION of a view's points beyond it by over _OUTSIDE_MARGIN of its size says the
# 2D was made on footage of another resolution.
_OUTSIDE_MARGIN = 0.02
_OUTSIDE_FRACTION = 0.01


def _check_inside_frames(pose2d, recording_dir: Path) -> None:
    """Refuse (FootageError) imported 2D whose points lie outside its footage."""
    sizes = pose2d.image_sizes or {}
    for v, view in enumerate(pose2d.view_names):
        if view not in sizes:
            continue
        height, width = (int(n) for n in sizes[view])
        xy = pose2d.pts2d[v].reshape(-1, 2)
        xy = xy[np.isfinite(xy).all(axis=1)]
        if not len(xy):
            continue
        limit = np.array([width, height], dtype=np.float64)
        outside = ((xy < -_OUTSIDE_MARGIN * limit) | (xy > (1 + _OUTSIDE_MARGIN) * limit)).any(
            axis=1
        )
        if outside.mean() > _OUTSIDE_FRACTION:
            top = np.max(xy, axis=0)
            raise FootageError(
                f"{recording_dir}: camera {view}: footage is {width}x{height} px but "
                f"{outside.mean():.0%} of its imported 2D lies outside that frame (up to "
                f"x={top[0]:.0f}, y={top[1]:.0f}); the 2D was made on footage of another size: "
                "use the footage it was made on, or re-run the 2D tool on this footage"
            )


def compute_pose2d(
    inputs: Pose2dInputs,
    recording_dir: str | Path,
    *,
    import_spec: Mapping | None = None,
    candidates: bool = False,
    progress: bool = False,
) -> Pose2dData:
    """One recording's 2D keypoints (writes nothing): the detector over its footage, or another
    tool's files under an import spec (``import_spec``, else the inputs' ``pose2d.import``).

    Returns ``pts2d (V, T, P, 2)``, ``conf (V, T, P)``, view names, raw frame sizes and, with
    ``candidates``, the detector's top-K peaks (``runtime.candidates_k``). FootageError: the
    footage is missing, unreadable or inconsistent; ResultsError: candidates asked of imported
    2D (other tools keep no peaks).
    """
    recording_dir = Path(recording_dir)
    spec = import_spec or inputs.import_spec
    if spec:
        if candidates:
            raise ResultsError(
                f"{recording_dir}: pictorial structures needs the detector's candidate peaks, "
                f"but this recording's 2D is imported ({spec.get('format', 'another tool')}), "
                "which keeps none; set pipeline.do_pictorial_structures: false"
            )
        from ..interop import import_points2d

        data = import_points2d(inputs.import_target(), recording_dir, spec)
        _check_inside_frames(data, recording_dir)
        return data
    from ..pose2d import detect_recording
    from ..recordings import find_recording

    sources = find_recording(recording_dir, inputs.source_patterns(), strict=True)
    return detect_recording(
        inputs.detection_plan(),
        sources,
        inputs.detector_params(),
        io=inputs.io(),
        k=inputs.runtime.candidates_k if candidates else None,
        progress=progress,
    )


def run_pose2d(
    inputs: Pose2dInputs,
    recording_dir: str | Path,
    out_path: str | Path,
    *,
    import_spec: Mapping | None = None,
    progress: bool = False,
    candidates_path: str | Path | None = None,
) -> Path:
    """Write one recording's 2D keypoints (:func:`compute_pose2d`) to ``out_path``; with
    ``candidates_path`` (PS on), the detector's top-K peaks there too, as a ``candidates`` stage."""
    from ..provenance import stage_provenance
    from ..skeleton import Skeleton

    data = compute_pose2d(
        inputs,
        recording_dir,
        import_spec=import_spec,
        candidates=candidates_path is not None,
        progress=progress,
    )
    provenance = stage_provenance(inputs.canonical_params(), "pose2d")
    candidates, data.candidates = data.candidates, None
    if candidates is not None:
        from ..results import save_candidates

        save_candidates(
            candidates_path, candidates, meta={**provenance, "k": int(inputs.runtime.candidates_k)}
        )
    # the skeleton as this stage tracks it: its points only
    data.save(
        out_path, Skeleton.from_spec({"point_names": list(inputs.point_names)}), meta=provenance
    )
    return Path(out_path)
