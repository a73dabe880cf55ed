"""Multi-view 3D hypotheses per (frame, joint) from pairs of candidate peaks."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from itertools import combinations

import numpy as np

DEFAULT_MAX_HYP = 12
DEFAULT_INLIER_PX = 15.0
DEFAULT_NMS = 0.1  # NMS radius, fraction of the median bone length
SEED_K = 3  # peaks per view that seed two-view hypotheses (all K may join as inliers)
_CHUNK_FRAMES = 64


@dataclass
class _Hypotheses:
    """Per (frame, joint) the kept 3D hypotheses, padded to ``S`` slots."""

    pos: np.ndarray  # (T, P, S, 3)
    evidence: np.ndarray  # (T, P, S), -inf for an empty slot
    assign: np.ndarray  # (T, P, S, V) candidate index per view, -1 = view not used


def _normalized(cameras, xy: np.ndarray) -> np.ndarray:
    """Raw pixels ``(V, ...)`` -> undistorted normalized coordinates ``(V, ..., 2)``."""
    und = cameras.undistort_points(xy)
    intr = np.asarray(cameras.intrs)
    shape = (len(intr),) + (1,) * (xy.ndim - 2) + (2,)
    return (und - intr[:, 2:4].reshape(shape)) / intr[:, 0:2].reshape(shape)


def _solve3(mat: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Batched 3x3 solve by the adjugate (NaN where singular)."""
    a, b, c = mat[..., 0, 0], mat[..., 0, 1], mat[..., 0, 2]
    d, e, f = mat[..., 1, 0], mat[..., 1, 1], mat[..., 1, 2]
    g, h, i = mat[..., 2, 0], mat[..., 2, 1], mat[..., 2, 2]
    co = np.stack(
        [
            e * i - f * h,
            c * h - b * i,
            b * f - c * e,
            f * g - d * i,
            a * i - c * g,
            c * d - a * f,
            d * h - e * g,
            b * g - a * h,
            a * e - b * d,
        ],
        -1,
    ).reshape(mat.shape)
    det = a * co[..., 0, 0] + b * co[..., 1, 0] + c * co[..., 2, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.einsum("...ij,...j->...i", co, rhs) / det[..., None]
    return np.where(np.abs(det[..., None]) > 1e-300, out, np.nan)


def _frame_hypotheses(
    rt: np.ndarray,
    focal: np.ndarray,
    norm: np.ndarray,
    score: np.ndarray,
    views: np.ndarray,
    *,
    inlier_px: float,
    max_hyp: int,
    nms_radius: float,
):
    """Hypotheses ``pos (T, J, S, 3)``, ``evidence (T, J, S)``, ``assign (T, J, S, n)`` for a
    group of joints sharing a view count: ``rt`` ``(V, 3, 4)`` world-to-camera ``[R | t]``,
    ``focal`` ``(V,)`` pixels per normalized unit, ``norm`` ``(T, J, n, K, 2)`` normalized
    candidates and ``score`` ``(T, J, n, K)`` of the group's ``n`` views per joint, ``views``
    ``(J, n)`` the view index of each slot."""
    n_t, n_j, n_v, n_k, _ = norm.shape
    proj = rt[views]  # (J, n, 3, 4)
    # Per candidate: two DLT rows (x P3 - P1, y P3 - P2) as normal-equation terms.
    rows = (
        norm[..., :, None] * proj[None, :, :, None, 2:3, :] - proj[None, :, :, None, 0:2, :]
    )  # (T, J, n, K, 2, 4)
    rows = np.where(np.isfinite(rows), rows, 0.0)
    lhs = np.einsum("...ri,...rj->...ij", rows[..., :3], rows[..., :3])  # (T,J,n,K,3,3)
    rhs = -np.einsum("...ri,...r->...i", rows[..., :3], rows[..., 3])  # (T,J,n,K,3)
    valid = np.isfinite(norm).all(-1)  # (T, J, n, K)

    pairs = np.array(list(combinations(range(n_v), 2)))  # (Q, 2)
    # Only the strongest SEED_K peaks of a view seed hypotheses; all K can join one.
    n_seed = min(n_k, SEED_K)
    ka, kb = np.meshgrid(np.arange(n_seed), np.arange(n_seed), indexing="ij")
    ka, kb = ka.ravel(), kb.ravel()
    va = np.repeat(pairs[:, 0], n_seed * n_seed)
    vb = np.repeat(pairs[:, 1], n_seed * n_seed)
    ka, kb = np.tile(ka, len(pairs)), np.tile(kb, len(pairs))  # (H,)
    x0 = _solve3(lhs[:, :, va, ka] + lhs[:, :, vb, kb], rhs[:, :, va, ka] + rhs[:, :, vb, kb])
    seed_ok = valid[:, :, va, ka] & valid[:, :, vb, kb]  # (T, J, H)

    def nearest(points):
        cam = np.einsum("jvab,tjhb->tjhva", proj[..., :3], points) + proj[None, :, None, :, :, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = cam[..., :2] / cam[..., 2:3]  # (T, J, H, n, 2)
            dx = xy[..., None, 0] - norm[:, :, None, ..., 0]  # (T, J, H, n, K)
            dy = xy[..., None, 1] - norm[:, :, None, ..., 1]
        reach = (inlier_px / focal[views])[None, :, None, :, None] ** 2
        near = (dx * dx + dy * dy <= reach) & (cam[..., 2:3] > 0)  # NaN compares False
        # Among the candidates within reach, the strongest peak speaks for the view.
        best = np.argmax(np.where(near, score[:, :, None], -np.inf), axis=-1)
        return best, near.any(-1)

    best, inlier = nearest(x0)
    # The two seed views keep their own peaks.
    hyp = np.arange(len(va))
    best[:, :, hyp, va], best[:, :, hyp, vb] = ka, kb
    inlier[:, :, hyp, va] = inlier[:, :, hyp, vb] = True
    inlier &= seed_ok[..., None]
    # Refit from the inlier candidates.
    t_i, j_i = np.arange(n_t)[:, None, None], np.arange(n_j)[None, :, None]
    lhs_sum = np.zeros(x0.shape + (3,))
    rhs_sum = np.zeros(x0.shape)
    evidence = np.zeros(x0.shape[:-1])
    for v in range(n_v):
        w = inlier[..., v]
        bv = best[..., v]
        lhs_sum += lhs[t_i, j_i, v, bv] * w[..., None, None]
        rhs_sum += rhs[t_i, j_i, v, bv] * w[..., None]
        evidence += np.where(w, score[t_i, j_i, v, bv], 0.0)
    x1 = _solve3(lhs_sum, rhs_sum)
    x1 = np.where(np.isfinite(x1), x1, x0)
    n_in = inlier.sum(-1)
    ok = seed_ok & (n_in >= 2) & np.isfinite(x1).all(-1)
    evidence = np.where(ok, evidence, -np.inf)
    assign = np.where(inlier, best, -1)

    # Merge hypotheses with the same inlier set: keep the first of each code.
    code = ((assign + 1) * (n_k + 1) ** np.arange(n_v)).sum(-1)
    code = np.where(ok, code, -1)
    order = np.argsort(code, axis=-1, kind="stable")
    sorted_code = np.take_along_axis(code, order, -1)
    dup_sorted = np.concatenate(
        [np.zeros((n_t, n_j, 1), bool), sorted_code[..., 1:] == sorted_code[..., :-1]], -1
    )
    dup = np.zeros_like(dup_sorted)
    np.put_along_axis(dup, order, dup_sorted, -1)
    evidence = np.where(dup, -np.inf, evidence)

    # Strongest first, then NMS among the best few.
    m = min(evidence.shape[-1], 2 * max_hyp)
    top = np.argsort(-evidence, axis=-1, kind="stable")[..., :m]
    ev = np.take_along_axis(evidence, top, -1)
    pos = np.take_along_axis(x1, top[..., None], -2)
    asg = np.take_along_axis(assign, top[..., None], -2)
    keep = np.isfinite(ev)
    if nms_radius > 0 and m > 1:
        diff = pos[..., :, None, :] - pos[..., None, :, :]
        close = np.einsum("...i,...i->...", diff, diff) < nms_radius**2
        for s in range(1, m):
            keep[..., s] &= ~(close[..., s, :s] & keep[..., :s]).any(-1)
    ev = np.where(keep, ev, -np.inf)
    order = np.argsort(-ev, axis=-1, kind="stable")[..., :max_hyp]
    return (
        np.take_along_axis(pos, order[..., None], -2),
        np.take_along_axis(ev, order, -1),
        np.take_along_axis(asg, order[..., None], -2),
    )


def all_hypotheses(cameras, cand_xy, cand_score, *, inlier_px, max_hyp, nms_radius):
    """Hypotheses for every (frame, joint); joints grouped by their number of views."""
    n_v, n_t, n_p, n_k, _ = cand_xy.shape
    norm = _normalized(cameras, cand_xy)  # (V, T, P, K, 2)
    rt = np.concatenate([np.asarray(cameras.rmats), np.asarray(cameras.tvecs)[..., None]], -1)
    focal = np.asarray(cameras.intrs)[:, 0:2].mean(-1)
    seen = np.isfinite(cand_xy).all(-1).any(axis=(1, 3))  # (V, P)
    hyp = _Hypotheses(
        np.full((n_t, n_p, max_hyp, 3), np.nan),
        np.full((n_t, n_p, max_hyp), -np.inf),
        np.full((n_t, n_p, max_hyp, n_v), -1),
    )
    by_count: dict[int, list[int]] = defaultdict(list)
    for p in range(n_p):
        by_count[int(seen[:, p].sum())].append(p)
    for count, joints in by_count.items():
        if count < 2:
            continue
        joints = np.array(joints)
        views = np.stack([np.flatnonzero(seen[:, p]) for p in joints])  # (J, n)
        for lo in range(0, n_t, _CHUNK_FRAMES):
            t = slice(lo, min(lo + _CHUNK_FRAMES, n_t))
            g_norm = norm[views, t, joints[:, None]]  # (J, n, Tc, K, 2)
            g_score = cand_score[views, t, joints[:, None]]
            pos, ev, asg = _frame_hypotheses(
                rt,
                focal,
                g_norm.transpose(2, 0, 1, 3, 4),
                g_score.transpose(2, 0, 1, 3),
                views,
                inlier_px=inlier_px,
                max_hyp=max_hyp,
                nms_radius=nms_radius,
            )
            s = pos.shape[2]
            hyp.pos[t, joints, :s] = pos
            hyp.evidence[t, joints, :s] = ev
            full = np.full(asg.shape[:3] + (n_v,), -1)
            full[:, np.arange(len(joints))[:, None], :, views] = asg.transpose(1, 3, 0, 2)
            hyp.assign[t, joints, :s] = full
    return hyp
