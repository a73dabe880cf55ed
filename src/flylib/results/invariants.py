"""What ``results.h5`` must never contradict: :func:`check_results`, :func:`require_consistent`.

A result agrees with itself when, in every group holding 3D (``pictorial_structures``,
``triangulation``, ``refinement``), with the stored rig (``bundle_adjustment/cameras``, else
``pose2d/cameras``):

- ``reproj_error`` is finite exactly where both the group's 2D ``points`` and its ``points3d``
  are, and equals the distance between the stored 2D and the projection of the stored 3D
  (``reprojection``);
- the stored 2D is the 2D the 3D was solved from (``solved-from 2D``): each finite entry of
  ``triangulation/points`` is its input (pictorial structures' points when that group is present,
  else ``pose2d/points``) with the manual corrections applied (``triangulation/corrected_2d``
  marks them, ``triangulation/edited_2d`` holds a person's 2D, NaN = marked invisible);
  ``refinement/points`` likewise over ``pose2d/points``, except at the points it kept from the
  triangulation (flag ``kept_triangulation``), which hold the triangulation's;
- refinement's ``flags`` agree with its NaN patterns (``flags``): ``observed`` where at least one
  view's 2D is kept, ``single_view`` where exactly one, ``missing`` exactly where the 3D is NaN,
  ``filled`` where the 3D is finite with no 2D kept.

``pose2d/points`` is the detection as the detector or the import gave it (no corrections
applied). Indices in the messages are 0-based. The assemble stage checks the file it writes (a
failure is a bug in flylib, reported before the file is put in place); ``flylib inspect --verify
RESULT`` checks any file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import ResultsError
from ..stages import SOLVES_3D
from .datasets import read_json_attrs, read_strings
from .groups import cameras_from_group
from .hdf5 import read_checked
from .pose import apply_edits

__all__ = ["Violation", "check_results", "require_consistent", "REPROJECTION_TOLERANCE_PX"]

#: Largest accepted difference (pixels) between a stored reprojection error and the one
#: recomputed from the stored 2D, 3D and rig (float64 round-off is ~1e-10 px).
REPROJECTION_TOLERANCE_PX = 1e-6
#: Frames read at once: memory stays flat on a long recording.
_WINDOW = 2048


@dataclass(frozen=True)
class Violation:
    """One failed invariant (``reprojection``, ``solved-from 2D`` or ``flags``) of a ``dataset``
    (e.g. ``/refinement/reproj_error``): ``what`` disagrees, in words, at ``count`` entries; the
    ``worst`` entry's index ``(view, frame, point)`` or ``(frame, point)`` (``None`` when the
    invariant could not be checked) and its discrepancy in pixels, when the invariant measures
    one."""

    invariant: str
    dataset: str
    what: str
    count: int
    worst: tuple[int, ...] | None
    amount: float | None = None

    def line(self, views: list[str] | None = None, points: list[str] | None = None) -> str:
        """One line: the dataset, what disagrees, how often, and the worst entry."""
        if self.worst is None:
            return f"{self.invariant}: {self.dataset} {self.what}"
        parts = []
        if len(self.worst) == 3:
            v, t, p = self.worst
            parts.append(f"view {v}" + (f" ({views[v]})" if views and v < len(views) else ""))
        else:
            t, p = self.worst
        parts.append(f"frame {t}")
        parts.append(f"point {p}" + (f" ({points[p]})" if points and p < len(points) else ""))
        amount = "" if self.amount is None else f" by {self.amount:.6g} px"
        return (
            f"{self.invariant}: {self.dataset} {self.what} at {self.count} "
            f"{'entry' if self.count == 1 else 'entries'}; worst"
            f"{amount} at {', '.join(parts)}"
        )


class _Tally:
    """The count and the worst entry of one invariant over the frame windows."""

    def __init__(self, invariant: str, dataset: str, what: str, measured: bool):
        self.invariant, self.dataset, self.what, self.measured = invariant, dataset, what, measured
        self.count, self.worst, self.amount = 0, None, -np.inf

    def add(self, bad: np.ndarray, lo: int, axis: int, amount: np.ndarray | None = None) -> None:
        """``bad``: a boolean array of one window (frames on ``axis``, from frame ``lo``)."""
        n = int(bad.sum())
        if not n:
            return
        self.count += n
        if amount is None:
            if self.worst is not None:
                return
            index = np.argwhere(bad)[0]
            value = -np.inf
        else:
            score = np.where(bad, np.nan_to_num(amount, nan=np.inf), -np.inf)
            index = np.unravel_index(int(np.argmax(score)), bad.shape)
            value = float(score[index])
            if value <= self.amount:
                return
        index = [int(i) for i in index]
        index[axis] += lo
        self.worst, self.amount = tuple(index), value

    def result(self) -> Violation | None:
        if not self.count:
            return None
        amount = self.amount if self.measured and np.isfinite(self.amount) else None
        return Violation(self.invariant, self.dataset, self.what, self.count, self.worst, amount)


def check_results(path: str | Path) -> list[Violation]:
    """One :class:`Violation` per failed invariant and dataset of the ``results.h5`` at ``path``;
    a file that cannot be read or lacks the pose2d group or a rig is a ResultsError."""
    with read_checked(path, "re-run the workflow") as f:
        return _check_file(f, path)


def require_consistent(
    path: str | Path, *, writer: str = "assemble", shown: str | Path | None = None
) -> None:
    """Raise when the results file at ``path`` contradicts itself: its writer has a bug. The
    ResultsError names the file (``shown``, e.g. ``results.h5`` while ``path`` is its temporary
    name; ``path`` by default) and the ``writer``, then one line per failed invariant."""
    found = check_results(path)
    if found:
        views, points = describe(path)
        lines = "\n".join("  " + v.line(views, points) for v in found)
        raise ResultsError(
            f"{shown or path}: {writer} made a result that contradicts itself, so it was not "
            f"written (a bug in flylib; please report it with this message):\n{lines}"
        )


def describe(path: str | Path) -> tuple[list[str] | None, list[str] | None]:
    """The view and point names of a results file, for the messages."""
    with read_checked(path, "re-run the workflow") as f:
        views = read_json_attrs(f["pose2d"]).get("view_names") if "pose2d" in f else None
        points = read_strings(f["skeleton/point_names"]) if "skeleton/point_names" in f else None
        return views, points


def _check_file(f: h5py.File, path) -> list[Violation]:
    if "pose2d/points" not in f:
        raise ResultsError(f"{path}: has no pose2d/points; re-run the workflow")
    rig = next(
        (f[f"{s}/cameras"] for s in ("bundle_adjustment", "pose2d") if f"{s}/cameras" in f), None
    )
    if rig is None:
        raise ResultsError(f"{path}: has no cameras (pose2d/cameras); re-run the assemble stage")
    cameras = cameras_from_group(rig)
    found: list[Violation] = []
    tri = f["triangulation"] if "triangulation" in f else None
    if tri is not None and "corrected_2d" in tri and "edited_2d" not in tri:
        found.append(
            Violation(
                "solved-from 2D",
                "/triangulation/edited_2d",
                "is absent (written by an older flylib: the corrected 2D cannot be "
                "checked; re-run the triangulation stage)",
                1,
                None,
            )
        )
        tri, sources_known = None, False
    else:
        sources_known = True
    tallies = {}
    for name in SOLVES_3D:
        if name not in f or "points3d" not in f[name]:
            continue
        g = f[name]
        tallies[name] = [
            _Tally(
                "reprojection",
                f"/{name}/reproj_error",
                "is NaN where points and points3d are both finite, or finite where either is NaN",
                False,
            ),
            _Tally(
                "reprojection",
                f"/{name}/reproj_error",
                "differs from |points - project(points3d)|",
                True,
            ),
        ]
        if name != "pictorial_structures" and sources_known:
            tallies[name].append(
                _Tally(
                    "solved-from 2D",
                    f"/{name}/points",
                    "differs from the 2D it was solved from (input with corrections applied)",
                    True,
                )
            )
        if name == "refinement" and "flags" in g:
            tallies[name] += [
                _Tally("flags", f"/{name}/flags", f"bit {bit!r} disagrees with {rule}", False)
                for bit, rule in _FLAG_RULES
            ]
    n_frames = f["pose2d/points"].shape[1]
    for lo in range(0, n_frames, _WINDOW):
        hi = min(lo + _WINDOW, n_frames)
        window = _Window(f, tri, lo, hi)
        for name, marks in tallies.items():
            _check_group(f[name], name, window, cameras, marks, lo)
    for marks in tallies.values():
        found += [v for v in (m.result() for m in marks) if v is not None]
    return found


#: The NaN-derived bits of refinement's flags and what each must agree with.
_FLAG_RULES = (
    ("observed", "at least one view's 2D kept in refinement/points"),
    ("single_view", "exactly one view's 2D kept"),
    ("missing", "refinement/points3d being NaN"),
    ("filled", "a finite 3D with no view's 2D kept"),
)


class _Window:
    """The inputs of one frame window: the detections and the triangulation's input, corrected."""

    def __init__(self, f: h5py.File, tri: h5py.Group | None, lo: int, hi: int):
        detected = np.asarray(f["pose2d/points"][:, lo:hi], np.float64)
        tri_input = (
            np.asarray(f["pictorial_structures/points"][:, lo:hi], np.float64)
            if "pictorial_structures/points" in f
            else detected
        )
        if tri is not None and "corrected_2d" in tri:
            touched = np.asarray(tri["corrected_2d"][:, lo:hi], bool)
            edited = np.asarray(tri["edited_2d"][:, lo:hi], np.float64)
            detected = apply_edits(detected, touched, edited)
            tri_input = apply_edits(tri_input, touched, edited)
        self.detected, self.tri_input = detected, tri_input


def _check_group(g: h5py.Group, name: str, window: _Window, cameras, marks, lo: int) -> None:
    hi = lo + window.detected.shape[1]
    pts2d = np.asarray(g["points"][:, lo:hi], np.float64)
    pts3d = np.asarray(g["points3d"][lo:hi], np.float64)
    error = np.asarray(g["reproj_error"][:, lo:hi], np.float64)
    seen2d = np.isfinite(pts2d).all(-1)
    seen3d = np.isfinite(pts3d).all(-1)
    with np.errstate(invalid="ignore"):
        projected = cameras.project(pts3d)
        distance = np.linalg.norm(pts2d - projected, axis=-1)
    marks[0].add(np.isfinite(error) != (seen2d & seen3d[None]), lo, 1)
    gap = np.abs(error - distance)
    both = np.isfinite(error) & np.isfinite(distance)
    marks[1].add(both & (gap > REPROJECTION_TOLERANCE_PX * np.maximum(1.0, distance)), lo, 1, gap)
    if name == "pictorial_structures":
        return
    flags = np.asarray(g["flags"][lo:hi], np.uint8) if "flags" in g else None
    if len(marks) > 2 and marks[2].invariant == "solved-from 2D":
        _check_source(name, window, pts2d, seen2d, flags, marks[2], lo)
        marks = [marks[0], marks[1], *marks[3:]]
    if name != "refinement" or flags is None:
        return
    from ..refinement.solver import FLAG_BITS

    views = seen2d.sum(0)
    expect = {
        "observed": views > 0,
        "single_view": views == 1,
        "missing": ~seen3d,
        "filled": seen3d & (views == 0),
    }
    for mark, (bit, _) in zip(marks[2:], _FLAG_RULES):
        has = (flags & np.uint8(FLAG_BITS[bit][0])) != 0
        mark.add(has != expect[bit], lo, 0)


def _check_source(name, window: _Window, pts2d, seen2d, flags, mark: _Tally, lo: int) -> None:
    """Stored 2D is its input, corrected; at refinement's kept points, the triangulation's."""
    if name == "triangulation":
        expected = window.tri_input
    else:
        expected = window.detected
        if flags is not None:
            from ..refinement.solver import FLAG_BITS

            kept = (flags & np.uint8(FLAG_BITS["kept_triangulation"][0])) != 0
            expected = np.where(kept[None, ..., None], window.tri_input, expected)
    moved = np.linalg.norm(pts2d - expected, axis=-1)
    mark.add(seen2d & ~(moved <= REPROJECTION_TOLERANCE_PX), lo, 1, moved)
