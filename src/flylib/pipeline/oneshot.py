"""Library one-shot: 2D detections -> (bundle adjustment) -> (pictorial structures) -> 3D.

It is the workflow's chain without files: each stage's inputs from the packaged default
config (:meth:`flylib.config.Config.default`) with the caller's overrides and skeleton,
and each stage's pure step (``compute_bundle_adjustment``,
``compute_pictorial_structures``, ``compute_triangulation``).
"""

from __future__ import annotations

import logging
from dataclasses import fields, replace
from typing import TYPE_CHECKING

import numpy as np

from ..config.constants import TRIANGULATION_METHODS
from ..config.params import LEAST_SQUARES_OPTIONS, BundleAdjustmentParams, TriangulationParams
from ..errors import ConfigError
from .inputs import SkeletonSpec, stage_inputs

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..camera.rig import CameraGroup
    from ..config import Config
    from ..pictorial import Candidates
    from ..results import PoseResult
    from ..skeleton import Skeleton
    from .inputs import StageInputs

log = logging.getLogger(__name__)

#: The keys of the ``bundle_adjustment`` table (its least-squares options flat, as a
#: config writes them); any other ``bundle_adjust_kwargs`` key goes to the solver as is.
BUNDLE_ADJUSTMENT_KEYS = frozenset(
    {f.name for f in fields(BundleAdjustmentParams)} - {"least_squares"}
) | frozenset(LEAST_SQUARES_OPTIONS)


def packaged_defaults():
    """The packaged default config (read once per call; the file is small)."""
    from ..config import Config

    return Config.default()


def _stage(config: Config, stage: str, skeleton: Skeleton) -> StageInputs:
    """``stage``'s inputs under ``config``, on the caller's ``skeleton``."""
    spec = SkeletonSpec(point_names=skeleton.point_names, limbs=tuple(skeleton.limbs.items()))
    return replace(stage_inputs(config, stage), skeleton=spec)


def run_from_points2d(
    cameras: CameraGroup,
    skeleton: Skeleton,
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None = None,
    *,
    do_bundle_adjust: bool = True,
    bundle_adjust_kwargs: dict | None = None,
    triangulation: str | None = None,
    weigh_by_confidence: bool | None = None,
    do_pictorial: bool = False,
    candidates: Candidates | None = None,
    ps_kwargs: dict | None = None,
    ransac_threshold: float | None = None,
    min_inliers: int | None = None,
    reproj_threshold: float | None = None,
    max_drops: int | None = None,
    fps: float = 100.0,
    meta: dict | None = None,
) -> PoseResult:
    """Run the 2D-to-3D pipeline on detections and return a :class:`PoseResult`.

    Optionally bundle-adjust the rig (on the arg-max ``pts2d``), optionally run pictorial
    structures over the detector's top-K ``candidates``, then triangulate: the stages' compute
    steps on the packaged default config with the overrides below.

    Parameters
    ----------
    cameras, skeleton, pts2d, conf
        The rig, skeleton, detections ``(V, T, P, 2)`` (NaN = missing) and confidences
        ``(V, T, P)`` or ``None``.
    bundle_adjust_kwargs
        Overrides of the config's ``bundle_adjustment`` table (``fixed``, ``shared``,
        ``points_to_use``, ``max_frames``, ``solver`` ...; ``least_squares`` options flat or
        nested), checked as a config is; any other key (e.g. ``rigid_tolerance``) goes to
        :func:`flylib.bundle_adjustment.bundle_adjust_sequence` as is. Unset keys keep the
        config's: intrinsics fixed, 200 evenly spaced frames, the leg joints and antennae
        (``points_to_use``: ``None`` for every point, or a list for a non-fly skeleton).
    triangulation, weigh_by_confidence, ransac_threshold, min_inliers, reproj_threshold, max_drops
        ``None`` takes the config's ``triangulation`` value. Methods: ``"ransac"`` (largest
        consistent view set), ``"greedy"`` (drop the worst view) or ``"dlt"``;
        ``weigh_by_confidence`` weighs each view by ``sqrt(conf)``.
    do_pictorial, candidates, ps_kwargs
        Pictorial-structures peak recovery (:func:`flylib.pictorial.reconstruct`,
        ``ps_kwargs`` overriding the ``pictorial_structures`` table) over ``candidates``, its
        bone prior from ``pts2d``; its committed 2D feeds the triangulation.
    fps, meta
        Recorded in the result's ``meta``, with ``triangulation``, ``pictorial`` and, after
        bundle adjustment, its ``bundle_adjustment`` summary.

    Raises
    ------
    ConfigError
        For an unknown ``triangulation`` method, ``do_pictorial`` without ``candidates``, or
        an override the config's checks reject.
    """
    from ..config import Config
    from ..results import PoseResult
    from .bundle_adjustment import compute_bundle_adjustment
    from .pictorial_structures import compute_pictorial_structures
    from .triangulation import compute_triangulation

    knobs = {**locals(), "method": triangulation}  # the triangulation table's, by name
    if triangulation is not None and triangulation not in TRIANGULATION_METHODS:
        raise ConfigError(
            f"triangulation: unknown method {triangulation!r}; "
            f"use one of {', '.join(TRIANGULATION_METHODS)}"
        )
    if do_pictorial and candidates is None:
        raise ConfigError(
            "do_pictorial=True needs candidates=... (the detector's top-K "
            "peaks); 2D imported from another tool has none"
        )
    pts2d = np.asarray(pts2d, dtype=np.float64)
    conf = None if conf is None else np.asarray(conf, dtype=np.float64)
    ba_kwargs = dict(bundle_adjust_kwargs or {})
    ba_kwargs.update(ba_kwargs.pop("least_squares", None) or {})
    data = packaged_defaults().data
    overrides = {
        "bundle_adjustment": {k: v for k, v in ba_kwargs.items() if k in BUNDLE_ADJUSTMENT_KEYS},
        "pictorial_structures": dict(ps_kwargs or {}),
        "triangulation": {
            f.name: knobs[f.name] for f in fields(TriangulationParams) if knobs[f.name] is not None
        },
    }
    config = Config.from_dict({**data, **{k: {**data[k], **v} for k, v in overrides.items()}})
    tri_inputs = _stage(config, "triangulation", skeleton)
    run_meta: dict = {
        "fps": float(fps),
        "triangulation": tri_inputs.triangulation.method,
        "pictorial": bool(do_pictorial),
    }

    if do_bundle_adjust:
        ba_inputs = _stage(config, "bundle_adjustment", skeleton)
        passed_on = {k: v for k, v in ba_kwargs.items() if k not in BUNDLE_ADJUSTMENT_KEYS}
        runtime = replace(
            ba_inputs.runtime,
            solver_options={**ba_inputs.runtime.solver_options, **passed_on},
        )
        adjusted = compute_bundle_adjustment(
            replace(ba_inputs, runtime=runtime), cameras, pts2d, conf
        )
        cameras = adjusted.cameras
        run_meta["bundle_adjustment"] = {
            "initial_median_px": adjusted.solution.initial_median_px,
            "final_median_px": adjusted.solution.final_median_px,
            **adjusted.summary,
        }

    tri_input = pts2d
    if do_pictorial:
        ps_inputs = _stage(config, "pictorial_structures", skeleton)
        tri_input = compute_pictorial_structures(ps_inputs, cameras, candidates, pts2d).points

    result = compute_triangulation(tri_inputs, cameras, tri_input, conf)
    return PoseResult(
        cameras=cameras,
        skeleton=skeleton,
        pts2d=result.points,
        conf=conf,
        pts3d=result.points3d,
        reproj_error=result.reproj_error,
        meta={**run_meta, **(meta or {})},
    )
