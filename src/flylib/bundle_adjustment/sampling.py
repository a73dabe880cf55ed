"""Choosing the frames bundle adjustment fits (``max_frames`` / ``frame_sampling``).

- ``even``: evenly spaced over the recording;
- ``confidence``: the highest mean detector confidence over their observations;
- ``coverage``: the most triangulable observations (points seen by two or more views), ties
  broken towards spreading over the recording;
- ``diversity``: farthest-point sampling of per-frame 2D poses (each view centred on its own
  median) from the most complete frame: many postures, few duplicates of a resting fly."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int

FRAME_SAMPLING = ("even", "confidence", "coverage", "diversity")


def select_frames(
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None,
    max_frames: int | None,
    method: str = "even",
) -> Int[np.ndarray, " F"]:
    """Sorted indices of at most ``max_frames`` frames of ``pts2d`` ``(V, T, P, 2)`` (``None``:
    all); ConfigError for an unknown ``method`` or a non-positive ``max_frames``."""
    if method not in FRAME_SAMPLING:
        raise ConfigError(
            f"bundle_adjustment.frame_sampling: unknown strategy {method!r}; "
            f"use one of {', '.join(FRAME_SAMPLING)}"
        )
    n_frames = pts2d.shape[1]
    if max_frames is None or max_frames >= n_frames:
        return np.arange(n_frames)
    if max_frames < 1:
        raise ConfigError(
            f"bundle_adjustment.max_frames must be >= 1 (or null for all frames), got {max_frames}"
        )
    seen = np.isfinite(pts2d).all(axis=-1)  # (V, T, P)
    if method == "even":
        return np.unique(np.linspace(0, n_frames - 1, max_frames).round().astype(int))
    if method == "confidence":
        if conf is None:
            score = seen.sum(axis=(0, 2)).astype(float)
        else:
            c = np.where(seen, np.nan_to_num(conf), 0.0)
            score = c.sum(axis=(0, 2)) / np.maximum(seen.sum(axis=(0, 2)), 1)
        return _top(score, max_frames)
    if method == "coverage":
        triangulable = seen.sum(axis=0) >= 2  # (T, P)
        score = (seen & triangulable[None]).sum(axis=(0, 2)).astype(float)
        return _top(score, max_frames)
    return _farthest_point_frames(pts2d, seen, max_frames)


def _top(score: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` best-scoring frames; equal scores go to evenly spread frames first."""
    n = score.size
    # Secondary key: a bit-reversal-like spread order (a permutation), so ties don't clump.
    rank_in_spread = np.argsort(_spread_order(n))
    order = np.lexsort((rank_in_spread, -score))
    return np.sort(order[:k])


def _spread_order(n: int) -> np.ndarray:
    """Frame indices ordered so that every prefix is spread over ``range(n)``."""
    order, seen = [], np.zeros(n, bool)
    step = 1 << max(int(np.ceil(np.log2(max(n, 1)))), 0)
    while step >= 1:
        for i in range(0, n, step):
            if not seen[i]:
                seen[i] = True
                order.append(i)
        step //= 2
    return np.array(order, int)


def _farthest_point_frames(pts2d: np.ndarray, seen: np.ndarray, k: int) -> np.ndarray:
    centred = pts2d - np.nanmedian(pts2d, axis=(1, 2), keepdims=True)
    feats = np.nan_to_num(centred).transpose(1, 0, 2, 3).reshape(pts2d.shape[1], -1)
    feats = feats.astype(np.float32)
    first = int(np.argmax(seen.sum(axis=(0, 2))))
    chosen = [first]
    dist = np.linalg.norm(feats - feats[first], axis=1)
    for _ in range(k - 1):
        nxt = int(np.argmax(dist))
        if dist[nxt] <= 0:
            break
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(feats - feats[nxt], axis=1))
    if len(chosen) < k:  # fewer distinct postures than asked for: pad evenly
        rest = [i for i in _spread_order(pts2d.shape[1]) if i not in set(chosen)]
        chosen.extend(rest[: k - len(chosen)])
    return np.sort(np.array(chosen, int))


def select_session_frames(
    trials: Sequence[Float[np.ndarray, "V T P 2"]],
    confs: Sequence[Float[np.ndarray, "V T P"] | None],
    max_frames: int | None,
    method: str = "even",
) -> list[Int[np.ndarray, " F"]]:
    """Each trial's frames for one solve over a whole session: ``max_frames`` (``None``: all) shared
    evenly between the trials (the first ones get the remainder, every trial at least one), each
    trial's chosen by :func:`select_frames`. The session's solve then costs about what one trial's
    does, and sees the postures of every trial."""
    if max_frames is not None and max_frames < 1:
        raise ConfigError(
            f"bundle_adjustment.max_frames must be >= 1 (or null for all frames), got {max_frames}"
        )
    n = len(trials)
    chosen = []
    for i, (pts2d, conf) in enumerate(zip(trials, confs, strict=True)):
        quota = None if max_frames is None else max(1, max_frames // n + (i < max_frames % n))
        chosen.append(select_frames(pts2d, conf, quota, method))
    return chosen
