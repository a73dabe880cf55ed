"""How accurate a reconstruction is, without a ground truth.

The yardstick is the leave-one-camera-out (held-out-view) reprojection error: each point is
reconstructed again without view ``v`` (the 3D method re-run from scratch, never reusing what ``v``
told it), projected into ``v`` and compared with ``v``'s own 2D. A method that fits its input more
tightly without being closer to the truth (an over-smoothing prior, a wrong bone length) shows up
here, where the ordinary reprojection error would reward it. Beside it: how much each bone's
length spreads over time and how far left and right twins differ, both zero for a perfect rigid
fly. Refinement is re-solved once per view, so on long recordings both methods are evaluated on
the same evenly spread windows of contiguous frames (:func:`evaluation_windows`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .skeleton import mirror_bones

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float, Int

    from .camera.rig import CameraGroup
    from .skeleton import Skeleton

#: At most this many frames are held out per recording (in windows of
#: :data:`EVALUATION_WINDOW` contiguous frames), bounding refinement's re-solves.
EVALUATION_FRAMES = 500
EVALUATION_WINDOW = 250

#: ``triangulate(pts2d (V, T, P, 2), conf (V, T, P) | None) -> (pts3d (T, P, 3), kept (V, T, P))``
Triangulate = Callable[[np.ndarray, "np.ndarray | None"], tuple[np.ndarray, np.ndarray]]
#: ``refine(pts2d, conf, start (T, P, 3), kept (V, T, P)) -> pts3d (T, P, 3)``
Refine = Callable[[np.ndarray, "np.ndarray | None", np.ndarray, np.ndarray], np.ndarray]


def evaluation_windows(
    n_frames: int, max_frames: int = EVALUATION_FRAMES, window: int = EVALUATION_WINDOW
) -> list[tuple[int, int]]:
    """Contiguous frame ranges ``[(lo, hi), ...]`` to hold views out on: the whole recording
    up to ``max_frames`` frames, else ``max_frames // window`` windows spread evenly."""
    if n_frames <= max_frames:
        return [(0, n_frames)] if n_frames else []
    count = max(1, max_frames // max(window, 1))
    starts = np.linspace(0, n_frames - window, count).round().astype(int)
    return [(int(s), int(s) + window) for s in starts]


def held_out_errors(
    cameras: CameraGroup,
    pts2d: Float[np.ndarray, "V T P 2"],
    triangulate: Triangulate,
    *,
    conf: Float[np.ndarray, "V T P"] | None = None,
    refine: Refine | Mapping[Any, Refine] | None = None,
    windows: Sequence[tuple[int, int]] | None = None,
) -> dict[str, Any]:
    """Leave-one-camera-out reprojection errors of triangulation (and refinement).

    For every view ``v`` and window (default :func:`evaluation_windows`), ``v``'s 2D is removed, the
    points are triangulated from the other views, refined from that start (with ``refine``), and
    projected into ``v``. ``pts2d`` ``(V, T, P, 2)``, NaN = missing, may be an h5py dataset (read
    window by window); ``conf`` ``(V, T, P)`` is handed to the methods. ``refine`` may be a mapping
    ``label -> Refine`` (variants judged on the same held-out triangulations).

    Returns ``frames`` ``(T',)``, the frames evaluated, and ``triangulation`` and (with
    ``refine``) ``refinement``: ``(V, T', P)`` pixel errors (NaN where ``v`` has no 2D or the
    method could not reconstruct the point without it), or ``label -> (V, T', P)``."""
    variants = dict(refine) if isinstance(refine, Mapping) else {None: refine} if refine else {}
    n_views, n_frames, n_points = pts2d.shape[:3]
    windows = evaluation_windows(n_frames) if windows is None else list(windows)
    frames = np.concatenate([np.arange(lo, hi) for lo, hi in windows] or [np.zeros(0, int)])
    tri_parts: list[np.ndarray] = []
    ref_parts: dict[Any, list[np.ndarray]] = {label: [] for label in variants}
    for lo, hi in windows:
        seen = np.asarray(pts2d[:, lo:hi], np.float64)
        part_conf = None if conf is None else np.asarray(conf[:, lo:hi], np.float64)
        tri = np.full(seen.shape[:3], np.nan)
        ref = {label: np.full(seen.shape[:3], np.nan) for label in variants}
        for v in range(n_views):
            if not np.isfinite(seen[v]).any():
                continue
            without = seen.copy()
            without[v] = np.nan
            start, kept = triangulate(without, part_conf)
            tri[v] = _view_error(cameras, v, start, seen[v])
            for label, method in variants.items():
                refined = method(without, part_conf, start, kept)
                ref[label][v] = _view_error(cameras, v, refined, seen[v])
        tri_parts.append(tri)
        for label in variants:
            ref_parts[label].append(ref[label])

    def joined(parts):
        return np.concatenate(parts, axis=1) if parts else np.zeros((n_views, 0, n_points))

    out: dict[str, Any] = {"frames": frames, "triangulation": joined(tri_parts)}
    if variants:
        refined = {label: joined(parts) for label, parts in ref_parts.items()}
        out["refinement"] = refined if isinstance(refine, Mapping) else refined[None]
    return out


def _view_error(cameras, v: int, pts3d: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """``(T, P)`` distance between view ``v``'s projection of ``pts3d`` and its 2D."""
    projected = cameras.project(pts3d)[v]
    return np.linalg.norm(projected - observed, axis=-1)


def bone_length_spread(
    pts3d: Float[np.ndarray, "T P 3"], bones: Int[np.ndarray, "B 2"]
) -> Float[np.ndarray, " B"]:
    """Each bone's length spread over time, interquartile range / median ``(B,)`` (NaN for a
    bone never seen whole); 0 for a perfectly rigid skeleton."""
    bones = np.asarray(bones, int).reshape(-1, 2)
    length = np.linalg.norm(pts3d[:, bones[:, 0]] - pts3d[:, bones[:, 1]], axis=-1)  # (T, B)
    out = np.full(len(bones), np.nan)
    for b in range(len(bones)):
        values = length[:, b][np.isfinite(length[:, b])]
        if values.size and np.median(values) > 0:
            q25, q50, q75 = np.percentile(values, [25, 50, 75])
            out[b] = (q75 - q25) / q50
    return out


def left_right_asymmetry(
    pts3d: Float[np.ndarray, "T P 3"],
    bones: Int[np.ndarray, "B 2"],
    mirror: Int[np.ndarray, " B"],
) -> Float[np.ndarray, " B"]:
    """``|L_b - L_twin| / mean(L_b, L_twin)`` of every bone's median length against its
    left/right twin's ``(B,)``; NaN for a bone without a twin or never seen whole."""
    bones = np.asarray(bones, int).reshape(-1, 2)
    length = np.linalg.norm(pts3d[:, bones[:, 0]] - pts3d[:, bones[:, 1]], axis=-1)
    with np.errstate(all="ignore"):
        median = np.array(
            [np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else np.nan for c in length.T]
        )
        twin = median[np.asarray(mirror, int)]
        out = np.abs(median - twin) / (0.5 * (median + twin))
    out[np.asarray(mirror, int) == np.arange(len(bones))] = np.nan
    return out


def keep_triangulation(
    triangulation: Float[np.ndarray, "V T P"], refinement: Float[np.ndarray, "V T P"]
) -> tuple[Bool[np.ndarray, " P"], bool]:
    """Where refinement's held-out-view error ``(V, T, P)`` is not better than triangulation's.

    Both are compared on the observations both reconstructed without the view. A point keeps
    the triangulation when refinement's median or 95th percentile there is higher; a point with
    nothing to compare (never seen by three cameras at once) when refinement is worse over all
    the points compared, or nothing can be compared. If the output mixed that way is still
    worse overall (median or p95), every point keeps it. Returns ``keep`` ``(P,)``
    bool and whether every point keeps the triangulation."""
    tri = np.asarray(triangulation, np.float64)
    ref = np.asarray(refinement, np.float64)
    both = np.isfinite(tri) & np.isfinite(ref)

    def worse(b, a) -> bool:  # b's median or p95 higher than a's (a never empty)
        return np.median(b) > np.median(a) or np.percentile(b, 95) > np.percentile(a, 95)

    unchecked = not both.any() or worse(ref[both], tri[both])  # refinement's verdict where checked
    keep = np.array(
        [worse(r[w], t[w]) if w.any() else unchecked for t, r, w in zip(tri.T, ref.T, both.T)]
    )
    if both.any() and worse(np.where(keep[None, None], tri, ref)[both], tri[both]):
        keep[:] = True
    return keep.astype(bool), bool(keep.all())


def _stats(values: np.ndarray) -> dict[str, float | int | None]:
    finite = values[np.isfinite(values)]
    if not finite.size:
        return {"median": None, "p95": None, "n": 0}
    return {
        "median": float(np.median(finite)),
        "p95": float(np.percentile(finite, 95)),
        "n": int(finite.size),
    }


def accuracy_summary(
    errors: Float[np.ndarray, "V T P"],
    pts3d: Float[np.ndarray, "T P 3"] | None,
    *,
    view_names: Sequence[str],
    point_names: Sequence[str],
    bones: Int[np.ndarray, "B 2"] | None = None,
    mirror: Int[np.ndarray, " B"] | None = None,
) -> dict[str, Any]:
    """The truth-free accuracy figures of one reconstruction, as plain JSON-able numbers.

    From ``errors`` ``(V, T', P)`` (:func:`held_out_errors`) and, for the bone figures,
    ``pts3d`` ``(T, P, 3)`` with ``bones`` ``(B, 2)`` and ``mirror`` ``(B,)``: ``held_out_px``
    {``median``, ``p95``, ``n``}, ``per_view`` and ``per_point`` (name -> the same),
    ``bone_length_spread`` and ``left_right_asymmetry`` (medians over bones, fractions)."""
    errors = np.asarray(errors, np.float64)
    out: dict[str, Any] = {
        "held_out_px": _stats(errors),
        "per_view": {name: _stats(errors[v]) for v, name in enumerate(view_names)},
        "per_point": {name: _stats(errors[:, :, p]) for p, name in enumerate(point_names)},
        "bone_length_spread": None,
        "left_right_asymmetry": None,
    }
    if pts3d is not None and bones is not None and len(bones):
        spread = bone_length_spread(np.asarray(pts3d, np.float64), bones)
        if np.isfinite(spread).any():
            out["bone_length_spread"] = float(np.nanmedian(spread))
        if mirror is not None:
            asym = left_right_asymmetry(np.asarray(pts3d, np.float64), bones, mirror)
            if np.isfinite(asym).any():
                out["left_right_asymmetry"] = float(np.nanmedian(asym))
    return out


def triangulation_accuracy(
    triangulate: Triangulate,
    cameras: CameraGroup,
    skeleton: Skeleton,
    pts2d: Float[np.ndarray, "V T P 2"],
    pts3d: Float[np.ndarray, "T P 3"],
    conf: Float[np.ndarray, "V T P"] | None = None,
) -> dict[str, Any]:
    """The triangulation stage's truth-free accuracy: :func:`accuracy_summary` of its
    held-out-view errors and of ``pts3d`` on the same frames, plus ``frames_evaluated`` and
    ``frames_total``; the skeleton's bones give the spread and left/right figures."""
    held = held_out_errors(cameras, pts2d, triangulate, conf=conf)
    frames = held["frames"]
    return {
        "frames_evaluated": int(len(frames)),
        "frames_total": int(pts2d.shape[1]),
        "triangulation": accuracy_summary(
            held["triangulation"],
            np.asarray(pts3d, np.float64)[frames],
            view_names=list(cameras.names),
            point_names=list(skeleton.point_names),
            bones=np.asarray(skeleton.bones, int),
            mirror=mirror_bones(skeleton),
        ),
    }
