"""Pictorial-structures solvers: per frame and over a sequence."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from ..config.params import PictorialParams
from .chains import bone_length_targets, skeleton_chains, solve_chains
from .hypotheses import DEFAULT_INLIER_PX, DEFAULT_MAX_HYP, DEFAULT_NMS, all_hypotheses
from .peaks import Candidates

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..camera.rig import CameraGroup
    from ..skeleton import Skeleton

log = logging.getLogger(__name__)

DEFAULT_LAMBDA = PictorialParams.lam
DEFAULT_HUBER = 0.25  # relative bone-length deviation where the cost turns linear
DEFAULT_MU = 1.0


def prior(cameras, skeleton, pts2d_argmax, bone_max_frames):
    n_t = pts2d_argmax.shape[1]
    sel = (
        np.arange(n_t)
        if bone_max_frames is None or n_t <= bone_max_frames
        else np.linspace(0, n_t - 1, bone_max_frames).round().astype(int)
    )
    i, j, targets = bone_length_targets(cameras, pts2d_argmax[:, sel], skeleton)
    target_map = {
        (min(int(a), int(b)), max(int(a), int(b))): float(t)
        for a, b, t in zip(i, j, targets)
        if np.isfinite(t)
    }
    scale = float(np.nanmedian(targets)) if np.isfinite(targets).any() else 1.0
    return target_map, scale


def solve_frames(
    cameras: CameraGroup,
    cand_xy: Float[np.ndarray, "V T P K 2"],
    cand_score: Float[np.ndarray, "V T P K"],
    chains: list[list[int]],
    target_map: dict,
    *,
    scale: float,
    max_hyp: int = DEFAULT_MAX_HYP,
    inlier_px: float = DEFAULT_INLIER_PX,
    lam: float = DEFAULT_LAMBDA,
    huber: float = DEFAULT_HUBER,
    mu: float = DEFAULT_MU,
    temporal: bool = PictorialParams.temporal,
    prev_pts3d: Float[np.ndarray, "P 3"] | None = None,
    nms: float = DEFAULT_NMS,
) -> tuple[Float[np.ndarray, "T P 3"], Float[np.ndarray, "V T P 2"]]:
    """Pictorial structures over a block of frames: the chosen hypotheses ``pts3d`` and the
    candidate each view committed to ``pts2d`` (NaN where none).

    ``cand_xy``/``cand_score`` in raw pixels; ``chains`` (:func:`skeleton_chains`), ``target_map``
    ``(i, j) -> length`` with ``i < j`` and ``scale`` the median bone length; ``max_hyp``
    hypotheses kept per joint, ``inlier_px`` radius (pixels), ``lam`` bone-prior weight, ``huber``
    corner (relative deviation), ``nms`` radius (fraction of scale). With ``temporal``, frames
    are solved in order and each frame's jump from the previous choice (``prev_pts3d`` before the
    first) costs ``mu * (jump / scale)^2``."""
    cand_xy = np.asarray(cand_xy, float)
    cand_score = np.where(np.isfinite(cand_xy).all(-1), np.nan_to_num(cand_score), 0.0)
    n_v, n_t, n_p, n_k, _ = cand_xy.shape
    hyp = all_hypotheses(
        cameras, cand_xy, cand_score, inlier_px=inlier_px, max_hyp=max_hyp, nms_radius=nms * scale
    )
    unary = np.where(np.isfinite(hyp.evidence), -hyp.evidence, np.inf)
    if temporal:
        choice = np.empty((n_t, n_p), int)
        prev = prev_pts3d
        for t in range(n_t):
            u = unary[t : t + 1]
            if prev is not None and mu > 0:
                jump = np.linalg.norm(hyp.pos[t] - prev[:, None], axis=-1) / scale  # (P, S)
                u = u + np.nan_to_num(mu * jump**2, nan=0.0)[None]
            choice[t] = solve_chains(
                hyp.pos[t : t + 1], u, chains, target_map, lam=lam, huber=huber, scale=scale
            )[0]
            picked = _pick(hyp.pos[t : t + 1], choice[t : t + 1])[0]
            prev = np.where(np.isfinite(picked), picked, prev) if prev is not None else picked
    else:
        choice = solve_chains(hyp.pos, unary, chains, target_map, lam=lam, huber=huber, scale=scale)
    pts3d = _pick(hyp.pos, choice)
    slot = np.minimum(choice, max_hyp - 1)
    assign = np.take_along_axis(hyp.assign, slot[..., None, None], 2)[:, :, 0]  # (T, P, V)
    assign = np.where((choice < max_hyp)[..., None], assign, -1).transpose(2, 0, 1)  # (V,T,P)
    picked2d = np.take_along_axis(cand_xy, np.maximum(assign, 0)[..., None, None], 3)[..., 0, :]
    pts2d = np.where((assign >= 0)[..., None], picked2d, np.nan)
    return pts3d, pts2d


def _pick(pos: np.ndarray, choice: np.ndarray) -> np.ndarray:
    n_s = pos.shape[2]
    slot = np.minimum(choice, n_s - 1)
    out = np.take_along_axis(pos, slot[..., None, None], 2)[:, :, 0]
    return np.where((choice < n_s)[..., None], out, np.nan)


def solve_frame(
    cameras: CameraGroup,
    skeleton: Skeleton,
    cand_xy: Float[np.ndarray, "V P K 2"],
    cand_score: Float[np.ndarray, "V P K"],
    target_map: dict,
    chains: list[list[int]],
    *,
    scale: float,
    max_hyp: int = DEFAULT_MAX_HYP,
    inlier_px: float = DEFAULT_INLIER_PX,
    lam: float = DEFAULT_LAMBDA,
    huber: float = DEFAULT_HUBER,
    mu: float = DEFAULT_MU,
    prev_pts3d: Float[np.ndarray, "P 3"] | None = None,
) -> tuple[Float[np.ndarray, "P 3"], Float[np.ndarray, "V P 2"]]:
    """Pictorial structures for one frame: ``(V, P, K, 2)`` candidates in, ``pts3d (P, 3)`` and
    committed ``pts2d (V, P, 2)`` out. See :func:`solve_frames`."""
    pts3d, pts2d = solve_frames(
        cameras,
        np.asarray(cand_xy)[:, None],
        np.asarray(cand_score)[:, None],
        chains,
        target_map,
        scale=scale,
        max_hyp=max_hyp,
        inlier_px=inlier_px,
        lam=lam,
        huber=huber,
        mu=mu,
        temporal=prev_pts3d is not None,
        prev_pts3d=prev_pts3d,
    )
    return pts3d[0], pts2d[:, 0]


def reconstruct(
    cameras: CameraGroup,
    skeleton: Skeleton,
    candidates: Candidates,
    pts2d_argmax: Float[np.ndarray, "V T P 2"] | None = None,
    *,
    bone_max_frames: int | None = PictorialParams.bone_max_frames,
    temporal: bool = PictorialParams.temporal,
    max_hyp: int = DEFAULT_MAX_HYP,
    inlier_px: float = DEFAULT_INLIER_PX,
    lam: float = DEFAULT_LAMBDA,
    huber: float = DEFAULT_HUBER,
    mu: float = DEFAULT_MU,
    nms: float = DEFAULT_NMS,
) -> tuple[Float[np.ndarray, "T P 3"], Float[np.ndarray, "V T P 2"], Float[np.ndarray, "V T P"]]:
    """Pictorial-structures reconstruction of a sequence: ``pts3d``, the committed ``pts2d``
    (NaN where no view was kept) and their reprojection error in pixels.

    The bone-length prior comes from a RANSAC triangulation of the arg-max detections
    (``pts2d_argmax``, default the candidates' ``K = 0``) over up to ``bone_max_frames`` evenly
    spaced frames. The 3D is the DLT triangulation of the committed 2D, so with clean candidates
    (every arg-max right) the result is exactly the arg-max triangulation."""
    from ..triangulation import reprojection_error, triangulate

    argmax = candidates.argmax() if pts2d_argmax is None else np.asarray(pts2d_argmax, float)
    target_map, scale = prior(cameras, skeleton, argmax, bone_max_frames)
    chains = skeleton_chains(skeleton)
    _, pts2d = solve_frames(
        cameras,
        candidates.xy,
        candidates.score,
        chains,
        target_map,
        scale=scale,
        max_hyp=max_hyp,
        inlier_px=inlier_px,
        lam=lam,
        huber=huber,
        mu=mu,
        temporal=temporal,
        nms=nms,
    )
    pts3d = triangulate(cameras, pts2d)
    reproj = reprojection_error(cameras, pts3d, pts2d)
    changed = np.isfinite(argmax).all(-1) & ~np.isclose(pts2d, argmax).all(-1)
    log.info(
        "pictorial structures: %d of %d observations moved off the arg-max peak",
        int(changed.sum()),
        int(np.isfinite(argmax).all(-1).sum()),
    )
    return pts3d, pts2d, reproj
