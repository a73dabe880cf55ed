"""Pictorial structures: recover joints whose detector arg-max landed on the wrong peak.

Where RANSAC triangulation can only veto a bad detection, this stage reconsiders the
detector's top-K heatmap peaks per (view, point) (DeepFly3D, Gunel et al. 2019):

1. :func:`peak_candidates` turns heatmaps into the top-K local maxima with sub-pixel
   refinement (the detector calls it; :class:`Candidates` holds them in raw pixels).
2. Per joint and frame, every pair of candidate peaks (the ``SEED_K`` strongest per
   view) from two views is triangulated;
   each view then contributes its candidate nearest the hypothesis' reprojection when
   within ``inlier_px``, the hypothesis is refitted from those inliers and its evidence
   is the summed peak score. Hypotheses with the same inlier set are merged, the rest
   thinned by non-maximum suppression at a fraction of the bone scale, and the
   ``max_hyp`` strongest kept.
3. One hypothesis (or none) per joint is chosen by exact dynamic programming along each
   limb chain: unary ``-evidence`` (plus, with ``temporal``, ``mu * (jump / scale)^2``
   against the previous frame) and a Huber bone-length term
   ``lam * huber((|Xi - Xj| - L_ij) / scale) / huber`` between neighbouring joints.

Geometry runs in NumPy on undistorted, intrinsics-free coordinates of the rig; every
step is vectorized over frames and joints, only the optional temporal DP walks frames.
"""

from __future__ import annotations

import logging
import warnings
from collections import defaultdict
from dataclasses import dataclass
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np

from .errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from .cameras import CameraGroup
    from .config import Config
    from .skeleton import Skeleton

log = logging.getLogger(__name__)

DEFAULT_K = 5
DEFAULT_PEAK_RADIUS = 2
DEFAULT_PEAK_THRESHOLD = 0.05
DEFAULT_SUBPIXEL = "taylor"
SUBPIXEL_METHODS = ("argmax", "weighted", "taylor")
DEFAULT_MAX_HYP = 12
DEFAULT_INLIER_PX = 15.0
DEFAULT_LAMBDA = 1.0
DEFAULT_HUBER = 0.25  # relative bone-length deviation where the cost turns linear
DEFAULT_MU = 1.0
DEFAULT_NMS = 0.1  # NMS radius, fraction of the median bone length
SEED_K = 3  # peaks per view that seed two-view hypotheses (all K may join as inliers)
_CHUNK_FRAMES = 64


@dataclass(frozen=True)
class Candidates:
    """Top-K detector peaks per (view, point) for a sequence, in raw-frame pixels.

    Attributes
    ----------
    xy
        ``(V, T, P, K, 2)`` peak positions ``(x, y)``, NaN where padded / unseen.
    score
        ``(V, T, P, K)`` peak values, 0 where padded; ``K = 0`` is the arg-max.
    """

    xy: np.ndarray
    score: np.ndarray

    def __post_init__(self):
        xy = np.asarray(self.xy, dtype=np.float64)
        score = np.asarray(self.score, dtype=np.float64)
        if xy.ndim != 5 or xy.shape[-1] != 2 or score.shape != xy.shape[:-1]:
            raise ValueError(f"Candidates need xy (V, T, P, K, 2) and score (V, T, P, K), "
                             f"got {xy.shape} and {score.shape}")
        score = np.where(np.isfinite(xy).all(-1), np.nan_to_num(score), 0.0)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "score", score)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(V, T, P, K)``."""
        return self.score.shape

    def frame(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Candidates of one frame: ``(V, P, K, 2)`` and ``(V, P, K)``."""
        return self.xy[:, t], self.score[:, t]

    def argmax(self) -> np.ndarray:
        """The strongest peak per (view, frame, point): ``(V, T, P, 2)``."""
        return self.xy[..., 0, :]

    @classmethod
    def from_points(cls, pts2d: np.ndarray, conf: np.ndarray | None = None) -> "Candidates":
        """Single-peak candidates (``K = 1``) from plain detections ``(V, T, P, 2)``."""
        pts2d = np.asarray(pts2d, float)
        score = np.ones(pts2d.shape[:-1]) if conf is None else np.asarray(conf, float)
        return cls(pts2d[..., None, :], score[..., None])


# -- heatmap peaks -----------------------------------------------------------------


def peak_candidates(heatmaps, k: int = DEFAULT_K, *, radius: int = DEFAULT_PEAK_RADIUS,
                    threshold: float = DEFAULT_PEAK_THRESHOLD,
                    method: str = DEFAULT_SUBPIXEL) -> tuple[np.ndarray, np.ndarray]:
    """Top-``k`` local-maximum peaks of each heatmap, sub-pixel refined.

    A pixel is a peak when it is the maximum of its ``(2 radius + 1)^2`` neighbourhood
    and exceeds ``threshold``; the ``k`` strongest are returned strongest first.

    Parameters
    ----------
    heatmaps
        ``(..., H, W)`` float array.
    k
        Peaks kept per heatmap.
    radius
        Neighbourhood half-width for the local-maximum test and the ``weighted``
        refinement window, in heatmap pixels.
    threshold
        Peaks at or below this value are ignored.
    method
        ``"argmax"`` (integer pixel), ``"weighted"`` (score-weighted centroid of the
        window) or ``"taylor"`` (Newton step on the log-heatmap: exact for a Gaussian
        blob).

    Returns
    -------
    xy : np.ndarray
        ``(..., k, 2)`` peak ``(x, y)`` in heatmap pixel coordinates (x = column,
        y = row, pixel centres at integers); NaN where fewer than ``k`` peaks exist.
    score : np.ndarray
        ``(..., k)`` heatmap value at the peak pixel, 0 where padded.
    """
    from scipy.ndimage import maximum_filter

    if method not in SUBPIXEL_METHODS:
        raise ConfigError(f"pictorial_structures: unknown sub-pixel method {method!r}; "
                          f"use one of {', '.join(SUBPIXEL_METHODS)}")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    hm = np.asarray(heatmaps, dtype=np.float64)
    if hm.ndim < 2:
        raise ValueError(f"heatmaps must be (..., H, W), got shape {hm.shape}")
    lead, (height, width) = hm.shape[:-2], hm.shape[-2:]
    flat_hm = hm.reshape(-1, height, width)
    local_max = maximum_filter(flat_hm, size=(1, 2 * radius + 1, 2 * radius + 1),
                               mode="constant", cval=-np.inf)
    is_peak = (flat_hm == local_max) & (flat_hm > threshold)
    values = np.where(is_peak, flat_hm, -np.inf).reshape(len(flat_hm), -1)
    kk = min(k, values.shape[1])
    top = np.argpartition(-values, kk - 1, axis=1)[:, :kk]
    top_val = np.take_along_axis(values, top, axis=1)
    order = np.argsort(-top_val, axis=1, kind="stable")
    top, top_val = np.take_along_axis(top, order, 1), np.take_along_axis(top_val, order, 1)
    rows, cols = top // width, top % width
    dx, dy = _refine(flat_hm, rows, cols, method, radius)
    valid = np.isfinite(top_val)
    xy = np.where(valid[..., None], np.stack([cols + dx, rows + dy], axis=-1), np.nan)
    score = np.where(valid, top_val, 0.0)
    if kk < k:  # fewer pixels than k: pad
        xy = np.concatenate([xy, np.full((len(xy), k - kk, 2), np.nan)], axis=1)
        score = np.concatenate([score, np.zeros((len(score), k - kk))], axis=1)
    return xy.reshape(*lead, k, 2), score.reshape(*lead, k)


def _refine(hm: np.ndarray, rows: np.ndarray, cols: np.ndarray, method: str, radius: int):
    """Sub-pixel offsets ``(dx, dy)`` of peaks at ``(rows, cols)`` of ``hm`` ``(M, H, W)``."""
    n, height, width = hm.shape
    if method == "argmax":
        return np.zeros(rows.shape), np.zeros(rows.shape)
    chan = np.arange(n)[:, None]
    if method == "weighted":
        offsets = np.arange(-radius, radius + 1)
        r = rows[..., None, None] + offsets[:, None]
        c = cols[..., None, None] + offsets[None, :]
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
        w = hm[chan[..., None, None], np.clip(r, 0, height - 1), np.clip(c, 0, width - 1)]
        w = np.where(inside, np.maximum(w, 0.0), 0.0)
        total = w.sum(axis=(-1, -2))
        safe = np.where(total > 0, total, 1.0)
        dy = (w * offsets[:, None]).sum(axis=(-1, -2)) / safe
        dx = (w * offsets[None, :]).sum(axis=(-1, -2)) / safe
        return np.where(total > 0, dx, 0.0), np.where(total > 0, dy, 0.0)
    # taylor: one Newton step on log(h) with central differences
    inner = (rows >= 1) & (rows < height - 1) & (cols >= 1) & (cols < width - 1)
    r, c = np.clip(rows, 1, height - 2), np.clip(cols, 1, width - 2)

    def at(dr, dc):
        return np.log(np.maximum(hm[chan, r + dr, c + dc], 1e-10))

    centre = at(0, 0)
    gx = 0.5 * (at(0, 1) - at(0, -1))
    gy = 0.5 * (at(1, 0) - at(-1, 0))
    hxx = at(0, 1) - 2 * centre + at(0, -1)
    hyy = at(1, 0) - 2 * centre + at(-1, 0)
    hxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
    det = hxx * hyy - hxy * hxy
    ok = inner & (det > 1e-12) & (hxx < 0)
    safe = np.where(ok, det, 1.0)
    dx = -(hyy * gx - hxy * gy) / safe
    dy = -(hxx * gy - hxy * gx) / safe
    ok &= (np.abs(dx) <= 1.0) & (np.abs(dy) <= 1.0)
    return np.where(ok, dx, 0.0), np.where(ok, dy, 0.0)


# -- skeleton helpers ------------------------------------------------------------------


def bone_length_targets(cameras: "CameraGroup", pts2d: np.ndarray, skeleton: "Skeleton"):
    """Median length of every skeleton bone over a RANSAC triangulation of ``pts2d``.

    Shared by bundle adjustment (bone prior) and pictorial structures.

    Parameters
    ----------
    cameras
        The rig.
    pts2d
        ``(V, F, P, 2)`` detections.
    skeleton
        Supplies the bones.

    Returns
    -------
    i, j : np.ndarray
        ``(B,)`` bone endpoint indices (:meth:`Skeleton.bone_index_pairs`).
    targets : np.ndarray
        ``(B,)`` median lengths, NaN for a bone never triangulated.
    """
    from .triangulation import triangulate_ransac

    pts3d, _ = triangulate_ransac(np.asarray(pts2d, float), cameras, threshold=DEFAULT_INLIER_PX)
    i, j = skeleton.bone_index_pairs()
    lengths = np.linalg.norm(pts3d[:, i] - pts3d[:, j], axis=-1)
    with warnings.catch_warnings():  # an all-NaN bone gives a NaN target, on purpose
        warnings.simplefilter("ignore", RuntimeWarning)
        targets = np.nanmedian(lengths, axis=0) if lengths.size else np.zeros(0)
    return np.asarray(i), np.asarray(j), np.asarray(targets, float)


def skeleton_chains(skeleton: "Skeleton") -> list[list[int]]:
    """The skeleton's bones as ordered simple chains (isolated points as singletons).

    Each connected component of the bone graph must be a path (the fly's limbs are);
    it is returned walked from one end.

    Raises
    ------
    ConfigError
        If a component branches or closes a loop (exact chain DP would not apply).
    """
    adjacency: dict[int, list[int]] = defaultdict(list)
    for a, b in np.asarray(skeleton.bones).reshape(-1, 2):
        adjacency[int(a)].append(int(b))
        adjacency[int(b)].append(int(a))
    chains, seen = [], set()
    for start in range(skeleton.n_points):
        if start in seen:
            continue
        component, stack = [], [start]
        while stack:
            node = stack.pop()
            if node not in seen:
                seen.add(node)
                component.append(node)
                stack.extend(adjacency[node])
        ends = [n for n in component if len(adjacency[n]) <= 1]
        if len(component) > 1 and (len(ends) != 2 or
                                   any(len(adjacency[n]) > 2 for n in component)):
            names = [skeleton.point_names[n] for n in component]
            raise ConfigError(f"skeleton: the limb through {names} branches or loops; "
                              f"pictorial structures needs simple chains")
        chain, prev = [ends[0]], None
        while len(chain) < len(component):
            nxt = [m for m in adjacency[chain[-1]] if m != prev][0]
            prev = chain[-1]
            chain.append(nxt)
        chains.append(chain)
    return chains


# -- hypotheses --------------------------------------------------------------------------


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
    co = np.stack([e * i - f * h, c * h - b * i, b * f - c * e,
                   f * g - d * i, a * i - c * g, c * d - a * f,
                   d * h - e * g, b * g - a * h, a * e - b * d], -1).reshape(mat.shape)
    det = a * co[..., 0, 0] + b * co[..., 1, 0] + c * co[..., 2, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.einsum("...ij,...j->...i", co, rhs) / det[..., None]
    return np.where(np.abs(det[..., None]) > 1e-300, out, np.nan)


def _frame_hypotheses(rt: np.ndarray, focal: np.ndarray, norm: np.ndarray, score: np.ndarray,
                      views: np.ndarray, *, inlier_px: float, max_hyp: int,
                      nms_radius: float):
    """Hypotheses for a group of joints sharing a view count.

    Parameters
    ----------
    rt
        ``(V, 3, 4)`` world-to-camera ``[R | t]``.
    focal
        ``(V,)`` pixels per normalized unit (for the pixel threshold).
    norm, score
        ``(T, J, n, K, 2)`` normalized candidates and ``(T, J, n, K)`` scores of the
        group's ``n`` views per joint.
    views
        ``(J, n)`` view index of each slot.

    Returns
    -------
    pos, evidence, assign
        ``(T, J, S, 3)``, ``(T, J, S)``, ``(T, J, S, n)``.
    """
    n_t, n_j, n_v, n_k, _ = norm.shape
    proj = rt[views]  # (J, n, 3, 4)
    # Per candidate: two DLT rows (x P3 - P1, y P3 - P2) as normal-equation terms.
    rows = (norm[..., :, None] * proj[None, :, :, None, 2:3, :]
            - proj[None, :, :, None, 0:2, :])  # (T, J, n, K, 2, 4)
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
    dup_sorted = np.concatenate([np.zeros((n_t, n_j, 1), bool),
                                 sorted_code[..., 1:] == sorted_code[..., :-1]], -1)
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
        close = np.einsum("...i,...i->...", diff, diff) < nms_radius ** 2
        for s in range(1, m):
            keep[..., s] &= ~(close[..., s, :s] & keep[..., :s]).any(-1)
    ev = np.where(keep, ev, -np.inf)
    order = np.argsort(-ev, axis=-1, kind="stable")[..., :max_hyp]
    return (np.take_along_axis(pos, order[..., None], -2), np.take_along_axis(ev, order, -1),
            np.take_along_axis(asg, order[..., None], -2))


def _all_hypotheses(cameras, cand_xy, cand_score, *, inlier_px, max_hyp, nms_radius):
    """Hypotheses for every (frame, joint); joints grouped by their number of views."""
    n_v, n_t, n_p, n_k, _ = cand_xy.shape
    norm = _normalized(cameras, cand_xy)  # (V, T, P, K, 2)
    rt = np.concatenate([np.asarray(cameras.rmats), np.asarray(cameras.tvecs)[..., None]], -1)
    focal = np.asarray(cameras.intrs)[:, 0:2].mean(-1)
    seen = np.isfinite(cand_xy).all(-1).any(axis=(1, 3))  # (V, P)
    hyp = _Hypotheses(np.full((n_t, n_p, max_hyp, 3), np.nan),
                      np.full((n_t, n_p, max_hyp), -np.inf),
                      np.full((n_t, n_p, max_hyp, n_v), -1))
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
                rt, focal, g_norm.transpose(2, 0, 1, 3, 4), g_score.transpose(2, 0, 1, 3),
                views, inlier_px=inlier_px, max_hyp=max_hyp, nms_radius=nms_radius)
            s = pos.shape[2]
            hyp.pos[t, joints, :s] = pos
            hyp.evidence[t, joints, :s] = ev
            full = np.full(asg.shape[:3] + (n_v,), -1)
            full[:, np.arange(len(joints))[:, None], :, views] = asg.transpose(1, 3, 0, 2)
            hyp.assign[t, joints, :s] = full
    return hyp


# -- chain dynamic programming ---------------------------------------------------------


def _huber(x: np.ndarray, delta: float) -> np.ndarray:
    a = np.abs(x)
    return np.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))


def _solve_chains(hyp_pos, unary, chains, targets, *, lam, huber, scale):
    """Exact min-cost choice per joint along each chain, batched over frames.

    ``hyp_pos`` ``(T, P, S, 3)``, ``unary`` ``(T, P, S)`` (inf = empty slot). A joint
    may also take "none" (slot ``S``) at zero cost and with no bone term.

    Returns ``(T, P)`` chosen slot, ``S`` meaning none.
    """
    n_t, n_p, n_s = unary.shape
    none = np.zeros((n_t, n_p, 1))
    cost_all = np.concatenate([unary, none], -1)  # (T, P, S + 1)
    choice = np.full((n_t, n_p), n_s)
    rows = np.arange(n_t)
    for chain in chains:
        cost = cost_all[:, chain[0]]
        backs = []
        for prev, cur in zip(chain[:-1], chain[1:]):
            target = targets.get((min(prev, cur), max(prev, cur)), np.nan)
            pair = np.zeros((n_t, n_s + 1, n_s + 1))
            if np.isfinite(target) and lam > 0:
                length = np.linalg.norm(hyp_pos[:, prev, :, None] - hyp_pos[:, cur, None], axis=-1)
                bone = lam * _huber((length - target) / scale, huber) / huber
                pair[:, :n_s, :n_s] = np.nan_to_num(bone, nan=0.0, posinf=0.0)
            total = cost[:, :, None] + pair  # (T, S+1 prev, S+1 cur)
            back = np.argmin(total, axis=1)
            cost = np.take_along_axis(total, back[:, None, :], 1)[:, 0] + cost_all[:, cur]
            backs.append(back)
        slot = np.argmin(cost, axis=1)
        choice[:, chain[-1]] = slot
        for node, back in zip(reversed(chain[:-1]), reversed(backs)):
            slot = back[rows, slot]
            choice[:, node] = slot
    return choice


# -- public solvers --------------------------------------------------------------------


def _prior(cameras, skeleton, pts2d_argmax, bone_max_frames):
    n_t = pts2d_argmax.shape[1]
    sel = (np.arange(n_t) if bone_max_frames is None or n_t <= bone_max_frames
           else np.linspace(0, n_t - 1, bone_max_frames).round().astype(int))
    i, j, targets = bone_length_targets(cameras, pts2d_argmax[:, sel], skeleton)
    target_map = {(min(int(a), int(b)), max(int(a), int(b))): float(t)
                  for a, b, t in zip(i, j, targets) if np.isfinite(t)}
    scale = float(np.nanmedian(targets)) if np.isfinite(targets).any() else 1.0
    return target_map, scale


def solve_frames(cameras: "CameraGroup", cand_xy: np.ndarray, cand_score: np.ndarray,
                 chains: list[list[int]], target_map: dict, *, scale: float,
                 max_hyp: int = DEFAULT_MAX_HYP, inlier_px: float = DEFAULT_INLIER_PX,
                 lam: float = DEFAULT_LAMBDA, huber: float = DEFAULT_HUBER,
                 mu: float = DEFAULT_MU, temporal: bool = False,
                 prev_pts3d: np.ndarray | None = None, nms: float = DEFAULT_NMS):
    """Pictorial structures over a block of frames.

    Parameters
    ----------
    cameras
        The (bundle-adjusted) rig.
    cand_xy, cand_score
        ``(V, T, P, K, 2)`` / ``(V, T, P, K)`` candidates in raw pixels.
    chains, target_map, scale
        :func:`skeleton_chains`, ``(i, j) -> length`` with ``i < j``, and the bone
        scale (median bone length).
    max_hyp, inlier_px, lam, huber, mu, nms
        Hypotheses kept per joint, inlier radius (pixels), bone-prior weight, Huber
        corner (relative deviation), temporal weight, NMS radius (fraction of scale).
    temporal, prev_pts3d
        With ``temporal``, frames are solved in order and each frame's jump from the
        previous choice (``prev_pts3d`` ``(P, 3)`` before the first) costs
        ``mu * (jump / scale)^2``.

    Returns
    -------
    pts3d : np.ndarray
        ``(T, P, 3)`` chosen hypotheses (NaN where none).
    pts2d : np.ndarray
        ``(V, T, P, 2)`` the candidate each view committed to (NaN where none).
    """
    cand_xy = np.asarray(cand_xy, float)
    cand_score = np.where(np.isfinite(cand_xy).all(-1), np.nan_to_num(cand_score), 0.0)
    n_v, n_t, n_p, n_k, _ = cand_xy.shape
    hyp = _all_hypotheses(cameras, cand_xy, cand_score, inlier_px=inlier_px,
                          max_hyp=max_hyp, nms_radius=nms * scale)
    unary = np.where(np.isfinite(hyp.evidence), -hyp.evidence, np.inf)
    if temporal:
        choice = np.empty((n_t, n_p), int)
        prev = prev_pts3d
        for t in range(n_t):
            u = unary[t:t + 1]
            if prev is not None and mu > 0:
                jump = np.linalg.norm(hyp.pos[t] - prev[:, None], axis=-1) / scale  # (P, S)
                u = u + np.nan_to_num(mu * jump ** 2, nan=0.0)[None]
            choice[t] = _solve_chains(hyp.pos[t:t + 1], u, chains, target_map,
                                      lam=lam, huber=huber, scale=scale)[0]
            picked = _pick(hyp.pos[t:t + 1], choice[t:t + 1])[0]
            prev = np.where(np.isfinite(picked), picked, prev) if prev is not None else picked
    else:
        choice = _solve_chains(hyp.pos, unary, chains, target_map, lam=lam, huber=huber,
                               scale=scale)
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


def solve_frame(cameras: "CameraGroup", skeleton: "Skeleton", cand_xy: np.ndarray,
                cand_score: np.ndarray, target_map: dict, chains: list[list[int]], *,
                scale: float, max_hyp: int = DEFAULT_MAX_HYP,
                inlier_px: float = DEFAULT_INLIER_PX, lam: float = DEFAULT_LAMBDA,
                huber: float = DEFAULT_HUBER, mu: float = DEFAULT_MU,
                prev_pts3d: np.ndarray | None = None):
    """Pictorial structures for one frame (seed API): ``(V, P, K, 2)`` candidates in,
    ``pts3d (P, 3)`` and committed ``pts2d (V, P, 2)`` out. See :func:`solve_frames`."""
    pts3d, pts2d = solve_frames(
        cameras, np.asarray(cand_xy)[:, None], np.asarray(cand_score)[:, None], chains,
        target_map, scale=scale, max_hyp=max_hyp, inlier_px=inlier_px, lam=lam, huber=huber,
        mu=mu, temporal=prev_pts3d is not None, prev_pts3d=prev_pts3d)
    return pts3d[0], pts2d[:, 0]


def reconstruct(cameras: "CameraGroup", skeleton: "Skeleton", candidates: Candidates,
                pts2d_argmax: np.ndarray | None = None, *, bone_max_frames: int | None = 100,
                temporal: bool = False, max_hyp: int = DEFAULT_MAX_HYP,
                inlier_px: float = DEFAULT_INLIER_PX, lam: float = DEFAULT_LAMBDA,
                huber: float = DEFAULT_HUBER, mu: float = DEFAULT_MU, nms: float = DEFAULT_NMS):
    """Pictorial-structures reconstruction of a sequence.

    The bone-length prior comes from a RANSAC triangulation of the arg-max detections
    (``pts2d_argmax``, default the candidates' ``K = 0``) over up to
    ``bone_max_frames`` evenly spaced frames. The returned 3D is the DLT triangulation
    of the committed 2D, so with clean candidates (every arg-max right) the result is
    exactly the arg-max triangulation.

    Returns
    -------
    pts3d : np.ndarray
        ``(T, P, 3)``.
    pts2d : np.ndarray
        ``(V, T, P, 2)`` committed candidates (NaN where no view was kept).
    reproj_error : np.ndarray
        ``(V, T, P)`` pixels.
    """
    from .triangulation import reprojection_error, triangulate

    argmax = candidates.argmax() if pts2d_argmax is None else np.asarray(pts2d_argmax, float)
    target_map, scale = _prior(cameras, skeleton, argmax, bone_max_frames)
    chains = skeleton_chains(skeleton)
    _, pts2d = solve_frames(cameras, candidates.xy, candidates.score, chains, target_map,
                            scale=scale, max_hyp=max_hyp, inlier_px=inlier_px, lam=lam,
                            huber=huber, mu=mu, temporal=temporal, nms=nms)
    pts3d = triangulate(pts2d, cameras)
    reproj = reprojection_error(pts3d, pts2d, cameras)
    changed = np.isfinite(argmax).all(-1) & ~np.isclose(pts2d, argmax).all(-1)
    log.info("pictorial structures: %d of %d observations moved off the arg-max peak",
             int(changed.sum()), int(np.isfinite(argmax).all(-1).sum()))
    return pts3d, pts2d, reproj


def reconstruct_from_config(config: "Config", candidates: Candidates, cameras: "CameraGroup"):
    """Run :func:`reconstruct` with the config's ``pictorial_structures`` table and skeleton.

    Returns
    -------
    pts3d, pts2d, reproj_error
        As :func:`reconstruct`.
    """
    return reconstruct(cameras, config.skeleton(), candidates,
                       **config.pictorial.solver_kwargs())
