"""The skeleton as limb chains, bone-length targets, and exact chain dynamic programming."""

from __future__ import annotations

import warnings
from collections import defaultdict
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError
from .hypotheses import DEFAULT_INLIER_PX

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int

    from ..camera.rig import CameraGroup
    from ..skeleton import Skeleton


def bone_length_targets(
    cameras: CameraGroup, pts2d: Float[np.ndarray, "V F P 2"], skeleton: Skeleton
) -> tuple[Int[np.ndarray, " B"], Int[np.ndarray, " B"], Float[np.ndarray, " B"]]:
    """Median length of every skeleton bone over a RANSAC triangulation of ``pts2d`` (bundle
    adjustment's bone prior and pictorial structures'): bone endpoints ``i``, ``j``
    (:meth:`Skeleton.bone_index_pairs`) and the lengths, NaN for a bone never triangulated."""
    from ..triangulation import triangulate_ransac

    pts3d, _ = triangulate_ransac(cameras, np.asarray(pts2d, float), threshold=DEFAULT_INLIER_PX)
    i, j = skeleton.bone_index_pairs()
    lengths = np.linalg.norm(pts3d[:, i] - pts3d[:, j], axis=-1)
    with warnings.catch_warnings():  # an all-NaN bone gives a NaN target, on purpose
        warnings.simplefilter("ignore", RuntimeWarning)
        targets = np.nanmedian(lengths, axis=0) if lengths.size else np.zeros(0)
    return np.asarray(i), np.asarray(j), np.asarray(targets, float)


def skeleton_chains(skeleton: Skeleton) -> list[list[int]]:
    """The skeleton's bones as simple chains walked from one end (isolated points as singletons);
    a branch or loop is a ConfigError (exact chain DP would not apply)."""
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
        if len(component) > 1 and (len(ends) != 2 or any(len(adjacency[n]) > 2 for n in component)):
            names = [skeleton.point_names[n] for n in component]
            raise ConfigError(
                f"skeleton: the limb through {names} branches or loops; "
                f"pictorial structures needs simple chains"
            )
        chain, prev = [ends[0]], None
        while len(chain) < len(component):
            nxt = [m for m in adjacency[chain[-1]] if m != prev][0]
            prev = chain[-1]
            chain.append(nxt)
        chains.append(chain)
    return chains


def _huber(x: np.ndarray, delta: float) -> np.ndarray:
    a = np.abs(x)
    return np.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))


def solve_chains(hyp_pos, unary, chains, targets, *, lam, huber, scale):
    """Exact min-cost choice per joint along each chain, batched over frames: the chosen slot
    ``(T, P)`` of ``hyp_pos`` ``(T, P, S, 3)`` with ``unary`` ``(T, P, S)`` (inf = empty slot). A
    joint may also take "none" (slot ``S``) at zero cost and with no bone term."""
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
