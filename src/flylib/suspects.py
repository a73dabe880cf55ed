"""Suspect (frame, point) pairs: where a 3D pose most likely needs a person's look.

Five reasons, each against the recording's own robust statistics (median and MAD-sigma), so the
same settings work on any rig, frame rate and fly size:

``reprojection``
    A view's reprojection error far above that view's typical error.
``bone_length``
    A bone's length far from its median. The end with more evidence (more bad bones at that frame,
    or another reason) is flagged, both on a tie: a wrong claw does not make its tarsus a suspect.
``jump``
    The 3D point far from every prediction of its neighbouring frames, so one wrong frame makes no
    suspect of its neighbours.
``ransac_drop``
    A view detected the point but the robust triangulation left it out (or left out every view).
``two_views``
    Triangulated from two views though usually seen by more. Scores 0.5: dropouts make it common,
    so it makes a suspect only with another reason.

Other reasons score at least 1 (more the further past the threshold); a pair scoring >= 1 is a
suspect, unless a person corrected it. A frame's score is its largest pair score. A person works
through *items*: a point's suspect pairs in consecutive frames (one detector mistake usually lasts
a few frames), ranked by their largest score, so a wrong 3D comes first (gross 3D errors score far
above 1; a view RANSAC already left out scores 1 to 1.5).

Every index is 0-based, as in ``results.h5``'s view-leading arrays: ``suspects.csv``'s ``frame`` and
``point`` columns and the views its ``detail`` names, ``"view 1 (lm)"``."""

from __future__ import annotations

import csv
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .paths import atomic_path

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float, Int

__all__ = [
    "REASONS",
    "SUSPECTS_FILE",
    "Suspects",
    "find_suspects",
    "suspects_from_results",
    "view_label",
]

SUSPECTS_FILE = "suspects.csv"
REASONS = ("reprojection", "bone_length", "jump", "ransac_drop", "two_views")
_MAD_SCALE = 1.4826  # MAD -> standard deviation of a normal distribution


def view_label(index: int, view_names: list[str] | None = None) -> str:
    """How a person reads view ``index``: ``"5 (lm)"`` (0-based, as frames and points and the
    arrays' V axis; the GUI's tiles and number keys count from 1, so the name is given too)."""
    names = view_names or []
    return f"{index} ({names[index]})" if index < len(names) else f"{index}"


@dataclass
class Suspects:
    """Suspect (frame, point) pairs of one recording, sorted by frame then point.

    ``score`` ``(N,)`` >= 1; ``reasons``: names joined by ``;``; ``details``: the numbers behind
    them; ``frame_score`` ``(T,)`` (0 where nothing is odd); ``item`` ``(N,)``: the rank of each
    pair's item (0 = look first), computed from the pairs when not given."""

    frame: Int[np.ndarray, " N"]
    point: Int[np.ndarray, " N"]
    score: Float[np.ndarray, " N"]
    reasons: list[str]
    details: list[str]
    frame_score: Float[np.ndarray, " T"]
    point_names: list[str] = field(default_factory=list)
    item: Int[np.ndarray, " N"] | None = None

    def __post_init__(self) -> None:
        if self.item is None:
            self.item = _rank_items(self.frame, self.point, self.score)

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def n_items(self) -> int:
        """Number of items (runs of consecutive suspect frames of one point)."""
        return int(self.item.max()) + 1 if len(self.item) else 0

    def items(self) -> list[dict]:
        """The items, best first (JSON-able); ``peak_frame`` holds the largest ``score`` (where
        to look), ``reasons`` cover all frames, ``detail`` is the peak frame's."""
        out = []
        for rank in range(self.n_items):
            rows = np.flatnonzero(self.item == rank)
            rows = rows[np.argsort(self.frame[rows], kind="stable")]
            peak = rows[int(np.argmax(self.score[rows]))]
            p = int(self.point[peak])
            seen = {r for i in rows for r in self.reasons[i].split(";")}
            out.append(
                {
                    "rank": rank,
                    "point": p,
                    "point_name": self.point_names[p] if p < len(self.point_names) else str(p),
                    "first_frame": int(self.frame[rows[0]]),
                    "last_frame": int(self.frame[rows[-1]]),
                    "frames": [int(f) for f in self.frame[rows]],
                    "peak_frame": int(self.frame[peak]),
                    "score": round(float(self.score[peak]), 3),
                    "reasons": [r for r in REASONS if r in seen],
                    "detail": self.details[peak],
                }
            )
        return out

    @property
    def frames(self) -> Int[np.ndarray, " F"]:
        """Sorted unique frames holding at least one suspect."""
        return np.unique(self.frame)

    def records(self, frame: int | None = None) -> list[dict]:
        """One dict per suspect (JSON-able): frame, point, point_name, score, reasons, detail,
        item (its item's rank); only those of ``frame`` when given."""
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
                    "item": int(self.item[i]),
                }
            )
        return out

    def to_csv(self, path: str | Path) -> Path:
        """Write ``item,frame,point,point_name,score,reasons,detail`` rows atomically in review
        order (item rank, then frame); every index is 0-based."""
        order = sorted(self.records(), key=lambda rec: (rec["item"], rec["frame"]))
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(["item", "frame", "point", "point_name", "score", "reasons", "detail"])
            for rec in order:
                writer.writerow(
                    [
                        rec["item"],
                        rec["frame"],
                        rec["point"],
                        rec["point_name"],
                        f"{rec['score']:.3f}",
                        ";".join(rec["reasons"]),
                        rec["detail"],
                    ]
                )
        return Path(path)


def _rank_items(frame: np.ndarray, point: np.ndarray, score: np.ndarray) -> np.ndarray:
    """``(N,)`` item rank per pair: runs of consecutive frames of one point, ranked by their
    largest score (ties: earlier frame, then point)."""
    frame = np.asarray(frame, dtype=int)
    point = np.asarray(point, dtype=int)
    if not len(frame):
        return np.zeros(0, int)
    order = np.lexsort((frame, point))
    f, p = frame[order], point[order]
    new_run = np.ones(len(order), bool)
    new_run[1:] = (p[1:] != p[:-1]) | (f[1:] != f[:-1] + 1)
    run = np.cumsum(new_run) - 1  # run id in (point, frame) order
    run_of = np.empty(len(order), int)
    run_of[order] = run
    n_runs = int(run[-1]) + 1
    peak = np.full(n_runs, -np.inf)
    np.maximum.at(peak, run_of, np.asarray(score, dtype=np.float64))
    first = np.full(n_runs, np.iinfo(int).max)
    np.minimum.at(first, run_of, frame)
    start_point = np.empty(n_runs, int)
    start_point[run_of] = point
    ranked = np.lexsort((start_point, first, -peak))  # run ids, best first
    rank_of_run = np.empty(n_runs, int)
    rank_of_run[ranked] = np.arange(n_runs)
    return rank_of_run[run_of]


def _robust_threshold(values: np.ndarray, k: float, floor: float, axis=None) -> np.ndarray:
    """``median + k * MAD-sigma`` of the finite values, at least ``median + floor``."""
    with np.errstate(all="ignore"), _quiet():
        med = np.nanmedian(values, axis=axis, keepdims=axis is not None)
        mad = _MAD_SCALE * np.nanmedian(np.abs(values - med), axis=axis, keepdims=axis is not None)
    return med + np.maximum(k * np.nan_to_num(mad), floor)


def _quiet() -> warnings.catch_warnings:
    """Silence numpy's all-NaN slice warnings (all-NaN columns simply flag nothing)."""
    return warnings.catch_warnings(action="ignore", category=RuntimeWarning)


def find_suspects(
    pts3d: Float[np.ndarray, "T P 3"],
    pts2d_used: Float[np.ndarray, "V T P 2"],
    reproj_error: Float[np.ndarray, "V T P"],
    bones: Int[np.ndarray, "B 2"],
    *,
    pts2d_input: Float[np.ndarray, "V T P 2"] | None = None,
    corrected: Bool[np.ndarray, "T P"] | None = None,
    point_names: list[str] | None = None,
    view_names: list[str] | None = None,
    k_reproj: float = 6.0,
    min_reproj_px: float = 3.0,
    k_bone: float = 6.0,
    bone_tolerance: float = 0.2,
    k_jump: float = 6.0,
    jump_tolerance: float = 0.2,
) -> Suspects:
    """Find the suspect (frame, point) pairs of a reconstruction.

    ``pts3d`` (NaN = not reconstructed) was solved from ``pts2d_used`` (triangulation's cleaned 2D);
    ``pts2d_input``: the 2D triangulation was given (for ``ransac_drop``); ``corrected``: points a
    person corrected (never suspects).

    Thresholds: per view, reprojection median + ``k_reproj`` MAD-sigmas, at least
    ``min_reproj_px`` above it; per bone, ``k_bone`` MAD-sigmas, at least ``bone_tolerance`` x the
    median length; per point, jump median + ``k_jump`` MAD-sigmas, at least ``jump_tolerance`` x
    the median bone length."""
    pts3d = np.asarray(pts3d, dtype=np.float64)
    used = np.asarray(pts2d_used, dtype=np.float64)
    error = np.asarray(reproj_error, dtype=np.float64)
    bones = np.asarray(bones, dtype=int).reshape(-1, 2)
    n_frames, n_points = pts3d.shape[:2]
    has3d = np.isfinite(pts3d).all(-1)  # (T, P)
    scores = {r: np.zeros((n_frames, n_points)) for r in REASONS}
    notes: dict[tuple[int, int], list[str]] = {}
    names = [str(n) for n in (point_names or [])]

    _score_reprojection(scores, notes, error, has3d, k_reproj, min_reproj_px, view_names)
    _score_views_used(scores, notes, used, has3d, pts2d_input, view_names)
    if n_frames >= 2:
        _score_jumps(scores, notes, pts3d, bones, k_jump, jump_tolerance)
    if len(bones):
        _score_bones(scores, notes, pts3d, bones, k_bone, bone_tolerance, names)

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
        point_names=names,
    )


def _note(notes: dict[tuple[int, int], list[str]], mask, text_of) -> None:
    """Add ``text_of(t, p)`` to the details of every (frame, point) where ``mask``."""
    for t, p in np.argwhere(mask):
        notes.setdefault((int(t), int(p)), []).append(text_of(t, p))


def _score_reprojection(scores, notes, error, has3d, k_reproj, min_reproj_px, view_names):
    """Reason ``reprojection``: a view's error past that view's robust threshold."""
    thr = _robust_threshold(error.reshape(len(error), -1), k_reproj, min_reproj_px, axis=1)[
        :, :, None
    ]
    with np.errstate(invalid="ignore"):
        excess = np.nanmax(np.where(np.isfinite(error), error / thr.reshape(-1, 1, 1), 0.0), axis=0)
    mask = (excess > 1.0) & has3d
    scores["reprojection"][mask] = excess[mask]
    worst = np.nanargmax(np.where(np.isfinite(error), error, -1.0), axis=0)
    _note(
        notes,
        mask,
        lambda t, p: (
            f"view {view_label(worst[t, p], view_names)} reprojects "
            f"{error[worst[t, p], t, p]:.1f} px off"
        ),
    )


def _score_views_used(scores, notes, used, has3d, pts2d_input, view_names):
    """Reasons ``ransac_drop`` (views left out by the robust triangulation, given ``pts2d_input``)
    and ``two_views`` (two-view points usually seen by more)."""
    n_points = has3d.shape[1]
    used_views = np.isfinite(used).all(-1)  # (V, T, P)
    if pts2d_input is not None:
        given = np.isfinite(np.asarray(pts2d_input, dtype=np.float64)).all(-1)
        dropped = given & ~used_views & has3d[None]
        mask = dropped.any(axis=0)
        scores["ransac_drop"][mask] = 1.0
        _note(
            notes,
            mask,
            lambda t, p: (
                f"{_views(np.flatnonzero(dropped[:, t, p]), view_names)} "
                "dropped by the robust triangulation"
            ),
        )
        # seen by two or more views that no 3D point fits: every view was dropped
        unsolved = ~has3d & (given.sum(axis=0) >= 2)
        scores["ransac_drop"][unsolved] = 1.0
        _note(
            notes,
            unsolved,
            lambda t, p: (
                f"{_views(np.flatnonzero(given[:, t, p]), view_names)} disagree: "
                "the robust triangulation found no 3D that fits them"
            ),
        )
    n_used = used_views.sum(axis=0)
    typical = (
        np.median(np.where(has3d, n_used, np.nan), axis=0) if has3d.any() else np.zeros(n_points)
    )
    mask = has3d & (n_used == 2) & (np.nan_to_num(typical) > 2)
    scores["two_views"][mask] = 0.5
    _note(notes, mask, lambda t, p: f"from 2 views (usually {typical[p]:g})")


def _score_jumps(scores, notes, pts3d, bones, k_jump, jump_tolerance):
    """Reason ``jump``: the point far from every prediction of its neighbouring frames."""

    def shifted(k):  # pts3d[t + k] at t, NaN outside the recording
        out = np.full_like(pts3d, np.nan)
        if k > 0:
            out[:-k] = pts3d[k:]
        else:
            out[-k:] = pts3d[:k]
        return out

    # the midpoint of both sides and the line through either side's two frames; a first
    # difference alone would measure speed, not a jump
    predictions = [
        0.5 * (shifted(-1) + shifted(1)),
        2.0 * shifted(-1) - shifted(-2),
        2.0 * shifted(1) - shifted(2),
    ]
    with _quiet():
        jump = np.nanmin(
            np.stack([np.linalg.norm(pts3d - q, axis=-1) for q in predictions]), axis=0
        )  # (T, P), NaN without neighbours
    with np.errstate(all="ignore"), _quiet():
        scale = (
            float(
                np.nanmedian(np.linalg.norm(pts3d[:, bones[:, 0]] - pts3d[:, bones[:, 1]], axis=-1))
            )
            if len(bones)
            else np.nan
        )
    floor = jump_tolerance * scale if np.isfinite(scale) else 0.0
    thr = _robust_threshold(jump, k_jump, floor, axis=0)  # (1, P)
    with np.errstate(invalid="ignore"):
        ratio = jump / thr
    mask = np.nan_to_num(ratio) > 1.0
    scores["jump"][mask] = ratio[mask]
    _note(notes, mask, lambda t, p: f"{jump[t, p]:.3g} off the path of its neighbouring frames")


def _score_bones(scores, notes, pts3d, bones, k_bone, bone_tolerance, names):
    """Reason ``bone_length``: the end with more evidence (more bad bones there, or another
    reason) is the suspect, both ends when it is a tie."""
    n_frames, n_points = pts3d.shape[:2]

    def name(p: int) -> str:
        return names[p] if p < len(names) else str(p)

    lengths = np.linalg.norm(pts3d[:, bones[:, 0]] - pts3d[:, bones[:, 1]], axis=-1)  # (T, B)
    with np.errstate(all="ignore"), _quiet():
        median = np.nanmedian(lengths, axis=0)
        sigma = _MAD_SCALE * np.nanmedian(np.abs(lengths - median), axis=0)
        allowed = np.maximum(k_bone * np.nan_to_num(sigma), bone_tolerance * median)
        ratio = np.abs(lengths - median) / allowed  # (T, B)
    bad = np.nan_to_num(ratio) > 1.0
    evidence = np.zeros((n_frames, n_points))
    np.add.at(evidence.T, bones[:, 0], bad.T)
    np.add.at(evidence.T, bones[:, 1], bad.T)
    evidence += sum(scores[r] for r in ("reprojection", "jump", "ransac_drop")) > 0
    for b in np.flatnonzero(bad.any(axis=0)):
        i, j = (int(x) for x in bones[b])
        for end, other in ((i, j), (j, i)):
            rows = bad[:, b] & (evidence[:, end] >= evidence[:, other])
            scores["bone_length"][rows, end] = np.maximum(
                scores["bone_length"][rows, end], ratio[rows, b]
            )
            _note(
                notes,
                rows[:, None] & (np.arange(n_points) == end)[None],
                lambda t, p, i=i, j=j, b=b: (
                    f"bone {name(i)}-{name(j)} {lengths[t, b]:.3g} vs median {median[b]:.3g}"
                ),
            )


def _views(indices, view_names: list[str] | None) -> str:
    labels = [view_label(int(v), view_names) for v in indices]
    return ("view " if len(labels) == 1 else "views ") + ", ".join(labels)


def suspects_from_results(path: str | Path, **thresholds) -> Suspects:
    """:func:`find_suspects` on an assembled ``results.h5`` (input 2D: pictorial structures' if it
    ran, else pose2d's; ``triangulation/corrected`` points skipped; ResultsError without 3D)."""
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
        view_names=list(result.cameras.names) if result.cameras is not None else None,
        **thresholds,
    )
