"""Library one-shot: 2D detections -> (bundle adjustment) -> (pictorial structures) -> 3D.

Its defaults are the packaged default config's (:meth:`flylib.config.Config.default`),
so the one-shot and the workflow start from the same settings.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ..config.constants import TRIANGULATION_METHODS
from ..errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..camera.rig import CameraGroup
    from ..pictorial import Candidates
    from ..results import PoseResult
    from ..skeleton import Skeleton

log = logging.getLogger(__name__)

#: The ``bundle_adjustment`` settings the one-shot takes from the packaged default config
#: when ``bundle_adjust_kwargs`` does not give them.
BUNDLE_ADJUST_DEFAULT_KEYS = ("fixed", "max_frames", "frame_sampling")


def _defaults():
    """The packaged default config (read once per call; the file is small)."""
    from ..config import Config

    return Config.default()


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

    Steps: optionally bundle-adjust the rig (on the arg-max ``pts2d``), optionally run
    pictorial structures over the detector's top-K ``candidates``, then triangulate.

    Parameters
    ----------
    cameras, skeleton, pts2d, conf
        The rig, skeleton, detections ``(V, T, P, 2)`` (NaN = missing) and confidences
        ``(V, T, P)`` or ``None``.
    do_bundle_adjust
        Refine the rig first (:func:`flylib.bundle_adjustment.bundle_adjust_sequence`).
    bundle_adjust_kwargs
        Keyword arguments for the adjustment (``fixed``, ``shared``, ``points_to_use``,
        ``max_frames``, ``frame_sampling``, ``weigh_by_confidence``, ``least_squares``
        options, ``solver``, ``bone_lengths``, ``rigid_points`` ...); ``fixed``,
        ``max_frames`` and ``frame_sampling`` default to the packaged config's
        ``bundle_adjustment`` values (intrinsics fixed, 200 evenly spaced frames).
    triangulation, weigh_by_confidence, ransac_threshold, min_inliers, reproj_threshold, max_drops
        ``None`` takes the packaged default config's ``triangulation`` value.
        ``triangulation``: ``"ransac"`` (largest consistent view set; ``ransac_threshold``,
        ``min_inliers``), ``"greedy"`` (drop the worst view; ``reproj_threshold``,
        ``max_drops``) or ``"dlt"`` (plain least squares).
        ``weigh_by_confidence``: confidence-weighted triangulation (``sqrt(conf)`` per
        view).
    do_pictorial, candidates, ps_kwargs
        Pictorial-structures peak recovery (:func:`flylib.pictorial.reconstruct`, with
        ``ps_kwargs`` such as ``temporal``, ``lam``, ``max_hyp``) over ``candidates``;
        its committed 2D feeds the triangulation.
    fps, meta
        Recorded in the result's ``meta``.

    Returns
    -------
    PoseResult
        Refined rig, committed 2D, 3D points and reprojection errors; ``meta`` holds
        ``fps``, ``triangulation``, ``pictorial`` and, after bundle adjustment, its
        ``bundle_adjustment`` summary.

    Raises
    ------
    ConfigError
        For an unknown ``triangulation`` method, or ``do_pictorial`` without
        ``candidates``.
    """
    from ..results import PoseResult
    from ..triangulation import reconstruct

    defaults = _defaults()
    given = {
        "method": triangulation,
        "weigh_by_confidence": weigh_by_confidence,
        "ransac_threshold": ransac_threshold,
        "min_inliers": min_inliers,
        "reproj_threshold": reproj_threshold,
        "max_drops": max_drops,
    }
    tri = replace(defaults.triangulation, **{k: v for k, v in given.items() if v is not None})
    triangulation = tri.method
    if triangulation not in TRIANGULATION_METHODS:
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
    run_meta: dict = {
        "fps": float(fps),
        "triangulation": triangulation,
        "pictorial": bool(do_pictorial),
    }

    if do_bundle_adjust:
        from ..bundle_adjustment import bundle_adjust_sequence

        ba = defaults.data["bundle_adjustment"]
        kwargs = {**{k: ba[k] for k in BUNDLE_ADJUST_DEFAULT_KEYS}, **(bundle_adjust_kwargs or {})}
        kwargs.update(kwargs.pop("least_squares", None) or {})
        result, cameras, _ = bundle_adjust_sequence(cameras, pts2d, conf, skeleton, **kwargs)
        run_meta["bundle_adjustment"] = {
            "initial_median_px": result.initial_median_px,
            "final_median_px": result.final_median_px,
            "cost": float(result.cost),
            "nfev": int(result.nfev),
            "message": str(result.message),
            **({"report": result.report} if hasattr(result, "report") else {}),
        }

    tri_input = pts2d
    if do_pictorial:
        from ..pictorial import reconstruct as ps_reconstruct

        _, tri_input, _ = ps_reconstruct(cameras, skeleton, candidates, pts2d, **(ps_kwargs or {}))

    pts3d, pts2d_out, reproj = reconstruct(cameras, tri_input, tri, conf)
    return PoseResult(
        cameras=cameras,
        skeleton=skeleton,
        pts2d=pts2d_out,
        conf=conf,
        pts3d=pts3d,
        reproj_error=reproj,
        meta={**run_meta, **(meta or {})},
    )
