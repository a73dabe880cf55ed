"""Suspect (frame, point) pairs: where a 3D pose most likely needs a person's look.

Five reasons, each measured against the recording's own robust statistics (median and
scaled median absolute deviation, MAD), so the same settings work on any rig, frame
rate and fly size:

``reprojection``
    A view's reprojection error far above that view's typical error.
``bone_length``
    A bone's length far from its median over the recording (both ends are flagged).
``jump``
    The 3D point far from the midpoint of its neighbouring frames (at the ends of the
    recording or of a gap: from the line through the two frames on one side).
``ransac_drop``
    A view detected the point but the robust triangulation left it out.
``two_views``
    The point was triangulated from two views only although it is usually seen by
    more. Weak on its own (score 0.5): dropouts make it common, so it makes a suspect
    only together with another reason.

Every other reason scores at least 1 (more the further past its threshold) and a pair
scoring >= 1 is a suspect. Points a person corrected (``corrected``) are not
suspects. The per-frame score (for the GUI's timeline) is the largest pair score of
the frame.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .paths import atomic_path

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float, Int

__all__ = ["REASONS", "SUSPECTS_FILE", "Suspects", "find_suspects", "suspects_from_results"]

SUSPECTS_FILE = "suspects.csv"
REASONS = ("reprojection", "bone_length", "jump", "ransac_drop", "two_views")
_MAD_SCALE = 1.4826  # MAD -> standard deviation of a normal distribution


@dataclass
class Suspects:
    """Suspect (frame, point) pairs of one recording.

    Attributes
    ----------
    frame, point
        ``(N,)`` int indices, sorted by frame then point.
    score
        ``(N,)`` float, >= 1.
    reasons
        ``N`` strings, reason names joined by ``;`` (see :data:`REASONS`).
    details
        ``N`` human-readable explanations (numbers behind the reasons).
    frame_score
        ``(T,)`` the largest pair score per frame (0 where nothing is odd).
    point_names
        The skeleton's point names (the P axis).
    """

    frame: Int[np.ndarray, " N"]
    point: Int[np.ndarray, " N"]
    score: Float[np.ndarray, " N"]
    reasons: list[str]
    details: list[str]
    frame_score: Float[np.ndarray, " T"]
    point_names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def frames(self) -> Int[np.ndarray, " F"]:
        """Sorted unique frames holding at least one suspect."""
        return np.unique(self.frame)

    def records(self, frame: int | None = None) -> list[dict]:
        """One dict per suspect (JSON-able): frame, point, point_name, score, reasons,
        detail; only those of ``frame`` when given."""
        rows = range(len(self.frame)) if frame is None else np.flatnonzero(self.frame == frame)
        out = []
        for i in rows:
            p = int(self.point[i])
            out.append(
                {
                    "frame": int(self.frame[i]),
                    "point": p,
                    "point_name": self.point_names[p] if p < len(self.point_names) else str(p),
                    "score": round(float(self.score[i]), 3),
                    "reasons": self.reasons[i].split(";"),
                    "detail": self.details[i],
                }
            )
        return out

    def to_csv(self, path: str | Path) -> Path:
        """Write ``frame,point,point_name,score,reasons,detail`` rows atomically."""
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(["frame", "point", "point_name", "score", "reasons", "detail"])
            for rec in self.records():
                writer.writerow(
                    [
                        rec["frame"],
                        rec["point"],
                        rec["point_name"],
                        f"{rec['score']:.3f}",
                        ";".join(rec["reasons"]),
                        rec["detail"],
                    ]
                )
        return Path(path)


def _robust_threshold(values: np.ndarray, k: float, floor: float, axis=None) -> np.ndarray:
    """``median + k * MAD-sigma`` of the finite values, at least ``median + floor``."""
    with np.errstate(all="ignore"), _quiet():
        med = np.nanmedian(values, axis=axis, keepdims=axis is not None)
        mad = _MAD_SCALE * np.nanmedian(np.abs(values - med), axis=axis, keepdims=axis is not None)
    return med + np.maximum(k * np.nan_to_num(mad), floor)


class _quiet:
    """Silence numpy's all-NaN slice warnings (all-NaN columns simply flag nothing)."""

    def __enter__(self):
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)


def find_suspects(
    pts3d: Float[np.ndarray, "T P 3"],
    pts2d_used: Float[np.ndarray, "V T P 2"],
    reproj_error: Float[np.ndarray, "V T P"],
    bones: Int[np.ndarray, "B 2"],
    *,
    pts2d_input: Float[np.ndarray, "V T P 2"] | None = None,
    corrected: Bool[np.ndarray, "T P"] | None = None,
    point_names: list[str] | None = None,
    k_reproj: float = 6.0,
    min_reproj_px: float = 3.0,
    k_bone: float = 6.0,
    bone_tolerance: float = 0.2,
    k_jump: float = 6.0,
    jump_tolerance: float = 0.2,
) -> Suspects:
    """Find the suspect (frame, point) pairs of a reconstruction.

    Parameters
    ----------
    pts3d
        ``(T, P, 3)``, NaN = not reconstructed.
    pts2d_used
        ``(V, T, P, 2)`` the 2D the points were solved from (triangulation's cleaned 2D).
    reproj_error
        ``(V, T, P)`` pixels.
    bones
        ``(B, 2)`` point-index pairs.
    pts2d_input
        ``(V, T, P, 2)`` the 2D triangulation was given (for ``ransac_drop``), or None.
    corrected
        ``(T, P)`` bool: points a person corrected (never suspects), or None.
    point_names
        The P axis' names (for :meth:`Suspects.records`).
    k_reproj, min_reproj_px
        Reprojection threshold per view: median + ``k_reproj`` MAD-sigmas, at least
        ``min_reproj_px`` above the median.
    k_bone, bone_tolerance
        Bone threshold: ``k_bone`` MAD-sigmas, at least ``bone_tolerance`` x the median length.
    k_jump, jump_tolerance
        Jump threshold per point: median + ``k_jump`` MAD-sigmas of its jumps, at least
        ``jump_tolerance`` x the median bone length.

    Returns
    -------
    Suspects
    """
    pts3d = np.asarray(pts3d, dtype=np.float64)
    used = np.asarray(pts2d_used, dtype=np.float64)
    error = np.asarray(reproj_error, dtype=np.float64)
    bones = np.asarray(bones, dtype=int).reshape(-1, 2)
    n_frames, n_points = pts3d.shape[:2]
    has3d = np.isfinite(pts3d).all(-1)  # (T, P)
    scores = {r: np.zeros((n_frames, n_points)) for r in REASONS}
    notes: dict[tuple[int, int], list[str]] = {}

    def note(mask, text_of):
        for t, p in np.argwhere(mask):
            notes.setdefault((int(t), int(p)), []).append(text_of(t, p))

    # reprojection error, per view
    thr = _robust_threshold(error.reshape(len(error), -1), k_reproj, min_reproj_px, axis=1)[
        :, :, None
    ]
    with np.errstate(invalid="ignore"):
        excess = np.nanmax(np.where(np.isfinite(error), error / thr.reshape(-1, 1, 1), 0.0), axis=0)
    mask = (excess > 1.0) & has3d
    scores["reprojection"][mask] = excess[mask]
    worst = np.nanargmax(np.where(np.isfinite(error), error, -1.0), axis=0)
    note(mask, lambda t, p: f"view {worst[t, p]} reprojects {error[worst[t, p], t, p]:.1f} px off")

    # bone lengths
    scale = np.nan
    if len(bones):
        lengths = np.linalg.norm(pts3d[:, bones[:, 0]] - pts3d[:, bones[:, 1]], axis=-1)  # (T, B)
        with np.errstate(all="ignore"), _quiet():
            median = np.nanmedian(lengths, axis=0)
            sigma = _MAD_SCALE * np.nanmedian(np.abs(lengths - median), axis=0)
            scale = float(np.nanmedian(median))
            allowed = np.maximum(k_bone * np.nan_to_num(sigma), bone_tolerance * median)
            ratio = np.abs(lengths - median) / allowed  # (T, B)
        bad = np.nan_to_num(ratio) > 1.0
        for b in np.flatnonzero(bad.any(axis=0)):
            for end in bones[b]:
                rows = bad[:, b]
                scores["bone_length"][rows, end] = np.maximum(
                    scores["bone_length"][rows, end], ratio[rows, b]
                )
                i, j = bones[b]
                note(
                    rows[:, None] & (np.arange(n_points) == end)[None],
                    lambda t, p, i=i, j=j, b=b: (
                        f"bone {i}-{j} {lengths[t, b]:.3g} vs median {median[b]:.3g}"
                    ),
                )

    # jumps from the neighbouring frames
    if n_frames >= 2:

        def shifted(k):  # pts3d[t + k] at t, NaN outside the recording
            out = np.full_like(pts3d, np.nan)
            if k > 0:
                out[:-k] = pts3d[k:]
            else:
                out[-k:] = pts3d[:k]
            return out

        # Predicted from the neighbours: their midpoint, else (at an end or a gap) the
        # straight-line extrapolation of the two frames on one side; a first
        # difference alone would measure speed, not a jump.
        predicted = 0.5 * (shifted(-1) + shifted(1))
        for near, far in ((-1, -2), (1, 2)):
            line = 2.0 * shifted(near) - shifted(far)
            predicted = np.where(np.isfinite(predicted), predicted, line)
        jump = np.linalg.norm(pts3d - predicted, axis=-1)  # (T, P), NaN without neighbours
        floor = jump_tolerance * scale if np.isfinite(scale) else 0.0
        thr = _robust_threshold(jump, k_jump, floor, axis=0)  # (1, P)
        with np.errstate(invalid="ignore"):
            ratio = jump / thr
        mask = np.nan_to_num(ratio) > 1.0
        scores["jump"][mask] = ratio[mask]
        note(mask, lambda t, p: f"{jump[t, p]:.3g} off the path of its neighbouring frames")

    # views left out by the robust triangulation, and two-view points
    used_views = np.isfinite(used).all(-1)  # (V, T, P)
    if pts2d_input is not None:
        given = np.isfinite(np.asarray(pts2d_input, dtype=np.float64)).all(-1)
        dropped = given & ~used_views & has3d[None]
        mask = dropped.any(axis=0)
        scores["ransac_drop"][mask] = 1.0
        note(
            mask,
            lambda t, p: (
                f"view(s) {', '.join(map(str, np.flatnonzero(dropped[:, t, p])))} "
                "dropped by the robust triangulation"
            ),
        )
    n_used = used_views.sum(axis=0)
    typical = (
        np.median(np.where(has3d, n_used, np.nan), axis=0) if has3d.any() else np.zeros(n_points)
    )
    mask = has3d & (n_used == 2) & (np.nan_to_num(typical) > 2)
    scores["two_views"][mask] = 0.5
    note(mask, lambda t, p: f"from 2 views (usually {typical[p]:g})")

    total = sum(scores.values())
    if corrected is not None:
        total = np.where(np.asarray(corrected, bool), 0.0, total)
    suspect = total >= 1.0
    frame_score = np.where(suspect, total, 0.0).max(axis=1) if n_points else np.zeros(n_frames)
    ts, ps = np.nonzero(suspect)
    reasons = [";".join(r for r in REASONS if scores[r][t, p] > 0) for t, p in zip(ts, ps)]
    details = ["; ".join(notes.get((int(t), int(p)), [])) for t, p in zip(ts, ps)]
    return Suspects(
        frame=ts.astype(int),
        point=ps.astype(int),
        score=total[ts, ps],
        reasons=reasons,
        details=details,
        frame_score=frame_score,
        point_names=[str(n) for n in (point_names or [])],
    )


def suspects_from_results(path: str | Path, **thresholds) -> Suspects:
    """:func:`find_suspects` on an assembled ``results.h5``.

    The 2D triangulation was given is pictorial structures' when that stage ran, else
    pose2d's; points marked ``triangulation/corrected`` are skipped.

    Raises
    ------
    ResultsError
        If the file is not a flylib results file or has no 3D.
    """
    from .errors import ResultsError
    from .results import PoseResult, open_checked

    result = PoseResult.load(path)
    if result.pts3d is None or result.reproj_error is None:
        raise ResultsError(
            f"{path}: holds no 3D points; run triangulation (or pictorial structures)"
        )
    with open_checked(path) as f:
        source = next(
            f"{s}/points" for s in ("pictorial_structures", "pose2d") if f"{s}/points" in f
        )
        given = f[source][()]
        corrected = f["triangulation/corrected"][()] if "triangulation/corrected" in f else None
        touched = f["triangulation/corrected_2d"][()] if "triangulation/corrected_2d" in f else None
    if touched is not None:
        given = np.where(touched[..., None], np.nan, given)  # a person's call, not ransac's
    return find_suspects(
        result.pts3d,
        result.pts2d,
        result.reproj_error,
        result.skeleton.bones,
        pts2d_input=given,
        corrected=corrected,
        point_names=list(result.skeleton.point_names),
        **thresholds,
    )
