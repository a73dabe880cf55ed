"""The state behind ``flylib gui``: one recording's result, its footage and the edits.

Every edit re-solves its (frame, point) from the 2D triangulation read (pictorial structures' or
pose2d's), corrections applied, with :func:`~flylib.pipeline.triangulation.compute_triangulation`
and the run's ``triangulation`` table: the page shows what the workflow computes after saving.
``results.h5`` is only read; only the corrections sidecar (inside the output directory), its
journal and lock (:mod:`flylib.gui.journal`) are written. A revision number counts the edits, so a
page that is behind is refreshed instead of overwriting what another tab did."""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..corrections import CORRECTIONS_FILE, Corrections, corrections_path
from ..errors import FlylibError, FootageError, OutputError, ResultsError
from ..pipeline.triangulation import TriangulationInputs, compute_triangulation
from .frames import FrameSource
from .journal import EditJournal, SidecarLock, read_journal

#: Edit ops a page may send; the journal records ``move3d`` as ``set3d`` (its 3D at edit time).
EDIT_OPS = (
    "move",
    "move3d",
    "invisible",
    "reset_point",
    "reset_view",
    "reset_frame",
    "reviewed",
    "unreviewed",
)

#: How much (px) an edit may raise a view's reprojection error before the page says so.
WORSE_PX = 2.0


class StaleRevision(ValueError):
    """An edit or save made against an older revision than the session's."""

    def __init__(self, given: int, current: int):
        super().__init__(
            f"the edits changed since this page loaded them (revision {shown(given)}, now "
            f"{current}: another tab or a replayed journal); the page was refreshed, "
            "look and edit again"
        )
        self.current = current


log = logging.getLogger(__name__)


def resolve_results(path: str | Path) -> Path:
    """``results.h5`` from a recording's output directory or the file itself; else ResultsError."""
    path = Path(path).expanduser()
    if path.is_dir():
        path = path / "results.h5"
    if not path.is_file():
        raise ResultsError(
            f"{path}: no results.h5 here; pass a recording's output directory "
            "(e.g. demo/flylib_outputs) or its results.h5, after the workflow ran"
        )
    return path.resolve()


def _xy_list(arr: np.ndarray, digits: int = 2) -> list:
    """``(P, k)`` coordinates as ``[[x, y, ...] | None]``: ``None`` for a missing point."""
    arr = np.round(np.asarray(arr, dtype=np.float64), digits)
    ok = np.isfinite(arr).all(-1)
    return [row if keep else None for row, keep in zip(arr.tolist(), ok.tolist())]


def _nan_to_none(arr: np.ndarray, digits: int = 3) -> list:
    """A float array as nested lists with ``None`` for NaN (JSON has no NaN)."""
    out = np.round(np.asarray(arr, dtype=np.float64), digits).tolist()

    def clean(x):
        if isinstance(x, list):
            return [clean(y) for y in x]
        return None if x is None or not math.isfinite(x) else x

    return clean(out)


class ReviewSession:
    """One recording (``results.h5`` or its output directory) opened for review.

    ``config`` defaults to the run's snapshot in the outdir; ``footage`` (``view -> files``) to
    what its ``sources`` find in the recording directory (or ``footage_dir``). When a view has no
    footage, :attr:`footage_missing` is the page's banner (where it looked, the fix)."""

    def __init__(
        self,
        results: str | Path,
        *,
        config: Any = None,
        footage: dict[str, list[Path]] | None = None,
        footage_dir: str | Path | None = None,
        cache_frames: int = 128,
    ):
        from ..config import Config
        from ..results import PoseResult, open_checked

        self._opened = (results, config, footage, footage_dir, cache_frames)  # for reload()
        if footage_dir is not None and not Path(footage_dir).expanduser().is_dir():
            raise FootageError(
                f"--footage-dir {footage_dir}: no such directory; pass the folder holding "
                "the recording's videos"
            )
        self.results_path = resolve_results(results)
        self.outdir = self.results_path.parent
        if config is None:
            config = Config.of_outputs(self.outdir)
        self.config = config
        self.triangulation_inputs = TriangulationInputs.from_config(config)
        self._results_stat = self._stat()
        result = PoseResult.load(self.results_path)
        if result.pts3d is None:
            raise ResultsError(f"{self.results_path}: holds no 3D points; run triangulation first")
        self.result = result
        self.cameras = result.cameras
        self.skeleton = result.skeleton
        self.view_names = list(self.cameras.names)
        with open_checked(self.results_path) as f:
            source = "pictorial_structures" if "pictorial_structures/points" in f else "pose2d"
            self.base2d = np.asarray(f[f"{source}/points"][()], dtype=np.float64)
            self.conf = (
                np.asarray(f["pose2d/conf"][()], dtype=np.float64) if "pose2d/conf" in f else None
            )
        self.recording_dir = result.meta.get("recording")
        self.recording_abspath = result.meta.get("recording_abspath")
        v, t, p = self.base2d.shape[:3]
        self.n_views, self.n_frames, self.n_points = v, t, p
        self.corrections_path = self._sidecar_path()
        sizes = result.image_sizes or {}
        self.image_sizes = {name: tuple(sizes.get(name, (480, 960))) for name in self.view_names}
        self._sidecar_lock = SidecarLock(self.corrections_path)
        self._sidecar_lock.acquire()
        try:
            if self.corrections_path.is_file():
                self.corrections = Corrections.load(
                    self.corrections_path,
                    (v, t, p),
                    [self.image_sizes[name] for name in self.view_names],
                    self.cameras,
                )
            else:
                self.corrections = Corrections.empty(v, t, p)
        except FlylibError:
            self._sidecar_lock.release()
            raise
        self.corrections.source = str(self.results_path)
        self.revision = self.corrections.revision
        self._unsaved: dict[int, Corrections] = {}  # each edited frame as last loaded or saved
        self._journal = EditJournal(self.corrections_path)
        self.pts3d = np.array(result.pts3d)
        self.used2d = np.array(result.pts2d)
        self.error = (
            np.array(result.reproj_error)
            if result.reproj_error is not None
            else np.full((v, t, p), np.nan)
        )
        self.error_before = self.error.copy()  # for the save check
        self._drag_before: tuple | None = None  # ((frame, point, view), errors) at a drag's start
        self._lock = threading.RLock()
        self._suspects = None
        self._suspects_stale = True
        self.dirty = False  # edits not yet saved
        self.notice = ""  # what the page and the terminal say on start (a replayed journal)
        # the result's own suspects, so that "12 / 21 reviewed" counts the same after a restart
        self.review_items = self._find_suspects(self.base2d, None).items()
        self._replay_journal()
        for tt, pp in np.argwhere(self.corrections.corrected_points()):
            self._resolve(int(tt), int(pp))
        self.footage_missing = ""
        self.footage_dir: Path | None = None
        if footage is None:
            footage = self._find_footage(footage_dir)
        self.frames = {
            name: FrameSource(footage.get(name, []), self.image_sizes[name], cache_frames)
            for name in self.view_names
        }
        self._refuse_other_footage(cache_frames)
        self._prefetch_todo: list[int] = []
        self._prefetch_wake = threading.Condition()
        self._closed = False
        self._prefetcher = threading.Thread(
            target=self._prefetch_loop, name="flylib-gui-prefetch", daemon=True
        )
        self._prefetcher.start()

    # -- set-up ------------------------------------------------------------------------

    def _sidecar_path(self) -> Path:
        """The configured sidecar if it lies inside the outdir, else ``<outdir>/corrections.h5``."""
        try:
            path, _ = corrections_path(
                self.config.data.get("corrections"), self.outdir, self.recording_dir
            )
        except FlylibError:  # a bad key is reported by the workflow; the GUI uses the default
            return self.outdir / CORRECTIONS_FILE
        path = path.resolve()
        if not path.is_relative_to(self.outdir.resolve()):
            log.warning(
                "corrections: %s lies outside %s; the GUI reads and writes %s instead",
                path,
                self.outdir,
                self.outdir / CORRECTIONS_FILE,
            )
            return self.outdir / CORRECTIONS_FILE
        return path

    def footage_candidates(self, footage_dir: str | Path | None = None) -> list[Path]:
        """Where the footage may be, in order: ``footage_dir`` alone when given; else the recording
        directory the result names, its ``recording_abspath``, and the named (relative) one from
        the output directory and those above it (the run's working directory is usually one)."""
        if footage_dir is not None:
            return [Path(footage_dir).expanduser()]
        named = Path(self.recording_dir).expanduser() if self.recording_dir else None
        candidates = [named] if named is not None else []
        if self.recording_abspath:
            candidates.append(Path(self.recording_abspath))
        if named is not None and not named.is_absolute():
            candidates += [base / named for base in (self.outdir, *self.outdir.parents[:4])]
        return list(dict.fromkeys(candidates))

    def _find_footage(self, footage_dir: str | Path | None = None) -> dict[str, list[Path]]:
        """Each view's footage from the first candidate holding any; else :attr:`footage_missing`."""
        from ..config.sources import footage_globs
        from ..interop.views import footage_files

        tried = self.footage_candidates(footage_dir)
        found: dict[str, list[Path]] = {}
        problem = ""
        for directory in tried:
            if not directory.is_dir():
                continue
            try:
                found = footage_files(footage_globs(self.config), directory)
            except (FlylibError, OSError) as exc:  # footage is a nicety: points reviewable
                problem = f"{directory}: {exc}"
                continue
            if any(found.values()):
                self.footage_dir = directory
                break
        missing = [name for name in self.view_names if not found.get(name)]
        if missing:
            where = (
                f"--footage-dir {tried[0]}"
                if footage_dir is not None
                else f"the recording directory {self.recording_dir!r} named in "
                f"{self.results_path.name} (looked in {', '.join(map(str, tried)) or 'nowhere'})"
            )
            detail = f" ({problem})" if problem and not any(found.values()) else ""
            views = "every view" if len(missing) == len(self.view_names) else ", ".join(missing)
            self.footage_missing = (
                f"no footage for {views}: not found in {where}{detail}; the points are "
                "shown without it. Start `flylib gui` with --footage-dir DIR (the folder "
                "holding the videos)"
            )
            log.warning("flylib gui: %s", self.footage_missing)
        return found

    def _refuse_other_footage(self, cache_frames: int) -> None:
        """Footage of another frame count or image size is another recording's: dark views
        and a banner naming both, never shown as this recording's."""
        wrong = []
        for name, source in self.frames.items():
            try:
                size = source.frame_size()
            except (FlylibError, OSError) as exc:
                size = exc
            if size is not None and (len(source), size) != (self.n_frames, self.image_sizes[name]):
                had = f"{size[1]}x{size[0]}" if isinstance(size, tuple) else f"unreadable ({size})"
                wrong.append((name, f"{name} has {len(source)} frames of {had}"))
                source.close()
                self.frames[name] = FrameSource([], self.image_sizes[name], cache_frames)
        if wrong:
            h, w = self.image_sizes[wrong[0][0]]
            more = f" (and {len(wrong) - 1} other view(s))" if len(wrong) > 1 else ""
            refused = (
                f"footage in {self.footage_dir or 'the footage given'} does not match "
                f"{self.results_path.name}: {wrong[0][1]}{more}, the result {self.n_frames} "
                f"frames of {w}x{h}; it is not shown. Start `flylib gui` with --footage-dir DIR "
                "(the folder holding this recording's videos)"
            )
            self.footage_missing = "; ".join(filter(None, [self.footage_missing, refused]))
            log.warning("flylib gui: %s", refused)

    # -- reading -----------------------------------------------------------------------

    def view_index(self, view: str) -> int:
        if view not in self.view_names:
            raise KeyError(f"unknown camera {view!r}")
        return self.view_names.index(view)

    def meta(self) -> dict:
        """What the page needs once: views, sizes, skeleton with palette, frame count."""
        sk = self.skeleton
        limb_names = list(sk.limb_names)
        return {
            "results": str(self.results_path),
            "results_changed": self._stat() != self._results_stat,
            "outdir": str(self.outdir),
            "corrections_file": str(self.corrections_path),
            "corrections_loaded": self.corrections.count(),
            "journal": str(self._journal.path),
            "revision": self.revision,
            "dirty": self.dirty,
            "notice": self.notice,
            "footage_missing": self.footage_missing,
            "views": [
                {
                    "name": n,
                    "height": int(self.image_sizes[n][0]),
                    "width": int(self.image_sizes[n][1]),
                    "footage": self.frames[n].has_footage,
                }
                for n in self.view_names
            ],
            "frames": self.n_frames,
            "points": list(sk.point_names),
            "limbs": limb_names,
            "point_limbs": np.asarray(sk.limb_id, int).tolist(),
            "bones": np.asarray(sk.bones, int).tolist(),
            "point_colors": [sk.limb_color(limb_names[i]) for i in np.asarray(sk.limb_id, int)],
            "bone_colors": [
                sk.limb_color(limb_names[int(sk.limb_id[a])]) for a, _ in np.asarray(sk.bones, int)
            ],
            "method": self.triangulation_inputs.triangulation.method,
            # the 3D view draws the rig: each camera's centre and viewing direction
            "rig": [
                {
                    "name": cam.name,
                    "position": np.round(cam.position, 6).tolist(),
                    "axis": np.round(cam.rmat[2], 6).tolist(),
                }
                for cam in self.cameras
            ],
        }

    def points(self, frame: int) -> dict:
        """Everything drawn at one frame: per view ``points2d`` (what triangulation reads, edits
        applied), ``used`` (kept by the solver), ``reprojected`` (the 3D ghost), ``error`` and the
        edit flags; ``points3d``, ``corrected`` and the frame's ``suspects``."""
        t = self._check_frame(frame)
        with self._lock:
            given, _ = self.corrections.subset([t], slice(None)).apply_2d(self.base2d[:, [t]])
            given = given[:, 0]
            reproj = self.cameras.project(self.pts3d[t])  # (V, P, 2)
            used = np.isfinite(self.used2d[:, t]).all(-1)
            views = [
                {
                    "name": name,
                    "points2d": _xy_list(given[v]),
                    "used": used[v].tolist(),
                    "reprojected": _xy_list(reproj[v]),
                    "error": _nan_to_none(self.error[v, t], 2),
                    "edited": self.corrections.edited[v, t].tolist(),
                    "fixed": self.corrections.fixed[v, t].tolist(),
                    "invisible": self.corrections.invisible[v, t].tolist(),
                }
                for v, name in enumerate(self.view_names)
            ]
            c = self.corrections
            corrected = ((c.edited[:, t] | c.invisible[:, t]).any(axis=0) | c.edited3d[t]).tolist()
            # the cached suspects (suspects() re-finds them): an edit's reply stays cheap
            cached = self._suspects if self._suspects is not None else self.suspects()
            suspects = cached.records(frame=t)
            return {
                "frame": t,
                "views": views,
                "points3d": _xy_list(self.pts3d[t], 6),
                "corrected": corrected,
                "suspects": suspects,
                "dirty": self.dirty,
                "edits": self.corrections.count(),
                "unsaved": sum(self.unsaved()),
                "reviewed": self.corrections.reviewed[t].tolist(),
                "revision": self.revision,
            }

    def suspects(self):
        """Suspects of the current state (recomputed lazily after edits)."""
        with self._lock:
            if self._suspects is None or self._suspects_stale:
                self._suspects_stale = False
                self._suspects = self._find_suspects(
                    np.where(self.corrections.touched()[..., None], np.nan, self.base2d),
                    self.corrections.corrected_points(),
                )
            return self._suspects

    def _find_suspects(self, pts2d_input: np.ndarray, corrected: np.ndarray | None):
        from ..suspects import find_suspects

        return find_suspects(
            self.pts3d,
            self.used2d,
            self.error,
            self.skeleton.bones,
            pts2d_input=pts2d_input,
            corrected=corrected,
            point_names=list(self.skeleton.point_names),
            view_names=self.view_names,
        )

    def review(self) -> dict:
        """Each of :attr:`review_items` with ``done`` (all its frames reviewed or corrected)."""
        with self._lock:
            settled = self.corrections.reviewed | self.corrections.corrected_points()
            items = [
                {**item, "done": bool(settled[item["frames"], item["point"]].all())}
                for item in self.review_items
            ]
        return {"items": items, "done": sum(item["done"] for item in items), "total": len(items)}

    def suspects_payload(self) -> dict:
        s = self.suspects()
        return {
            "suspects": s.records(),
            "items": s.items(),
            "frame_score": np.round(s.frame_score, 3).tolist(),
            "review": self.review(),
        }

    def save_check(self, worse_px: float = WORSE_PX) -> dict:
        """What the edits made worse, said before saving: ``worse`` (corrected points whose largest
        error grew by more than ``worse_px``, edits the robust triangulation drops) and
        ``new_suspects``, 10 lines each, their ``frames`` (to jump to), and ``count``."""
        names = self.skeleton.point_names
        with self._lock:
            corrected = self.corrections.corrected_points()
            # the largest error over the views (-1: the point is seen by none)
            error = np.where(np.isfinite(self.error), self.error, -1.0)
            now = error.max(axis=0)
            was = np.where(np.isfinite(self.error_before), self.error_before, -1.0).max(axis=0)
            worse = np.argwhere(corrected & (now > np.maximum(was, 0.0) + worse_px))
            lines, frames = [], []
            for t, p in worse[:10].tolist():
                v = int(error[:, t, p].argmax())
                before = f"{was[t, p]:.1f} px" if was[t, p] >= 0 else "none"
                lines.append(
                    f"{names[p]} at frame {t}: {now[t, p]:.1f} px from its 3D in "
                    f"{self.view_names[v]} (was {before})"
                )
                frames.append(t)
            c, finite = self.corrections, lambda a: np.isfinite(a).all(-1)
            dropped = np.argwhere(
                c.edited & finite(c.points) & ~finite(self.used2d) & finite(self.pts3d)
            )
            for v, t, p in dropped[:10].tolist():
                lines.append(
                    f"{names[p]} at frame {t}: the edit in {self.view_names[v]} is dropped by "
                    f"the robust triangulation ({self._off(v, t, p):.1f} px from its 3D)"
                )
                frames.append(t)
            known = {(f, it["point"]) for it in self.review_items for f in it["frames"]}
            fresh = [r for r in self.suspects().records() if (r["frame"], r["point"]) not in known]
            new = [
                f"{r['point_name']} at frame {r['frame']}: {', '.join(r['reasons'])}"
                for r in fresh[:10]
            ]
        frames += [r["frame"] for r in fresh[:10]]
        count = len(worse) + len(dropped) + len(fresh)
        return {"worse": lines, "new_suspects": new, "frames": frames, "count": count}

    # -- editing -------------------------------------------------------------------------

    def _check_frame(self, frame: int) -> int:
        return _in_range("frame", frame, self.n_frames)

    def _resolve(self, t: int, p: int) -> None:
        """Re-solve one (frame, point) from the base 2D with the current corrections."""
        sub = self.corrections.subset([t], [p])
        conf = None if self.conf is None else self.conf[:, [t]][:, :, [p]]
        solved = compute_triangulation(
            self.triangulation_inputs, self.cameras, self.base2d[:, [t]][:, :, [p]], conf, sub
        )
        self.pts3d[t, p] = solved.points3d[0, 0]
        self.used2d[:, t, p] = solved.points[:, 0, 0]
        self.error[:, t, p] = solved.reproj_error[:, 0, 0]
        self._suspects_stale = True

    def edit(
        self,
        op: str,
        frame: int,
        point: int | None = None,
        view: str | None = None,
        xy: Any = None,
        *,
        fixed: bool = False,
        revision: int | None = None,
        durable: bool = True,
    ) -> dict:
        """Check one edit, journal it, apply it and re-solve what it touched; :meth:`points` of
        the frame plus ``solve_ms`` and ``journal_ms``.

        ``op``: ``move`` (Edit 2D: place the point at ``xy`` in ``view``), ``move3d`` (Edit 3D: the
        3D point to the closest point on ``xy``'s ray), ``invisible`` (drop it in ``view``),
        ``reset_point`` (in ``view``, else everywhere with its 3D edit), ``reset_view``,
        ``reset_frame``, ``reviewed`` / ``unreviewed`` (the review mark, nothing re-solved).
        ``xy``: raw-frame pixels inside the view's image. ``fixed`` (``move``): the robust
        triangulation always keeps the point. ``revision``: the page's; an older one raises
        :class:`StaleRevision`. ``durable=False`` (a drag's intermediate positions) only flushes
        the journal line. Bad arguments raise KeyError / IndexError / ValueError; a journal that
        cannot be written, OutputError (the edit is not applied)."""
        with self._lock:
            self._check_revision(revision)
            started = time.perf_counter()
            record = self._plan(op, frame, point, view, xy, fixed)
            planned = time.perf_counter()
            self._journal.append(record, self.corrections.revision, durable=durable)
            journaled = time.perf_counter()
            t, p, view = record["frame"], record.get("point"), record.get("view")
            # a drag's steps (durable only at its end) are compared with the state before it
            same = self._drag_before and self._drag_before[0] == (t, p, view)
            before = self._drag_before[1] if same else self.error[:, t, p].copy()
            self._drag_before = None if durable else ((t, p, view), before)
            points = self._apply_record(record)
            self.revision += 1
            for q in points:
                self._resolve(t, q)
            solve_ms = (time.perf_counter() - journaled + planned - started) * 1000
            self.dirty = True
            reply = self.points(t)
            if record["op"] in ("move", "set3d"):
                reply["consequence"] = self._consequence(t, p, self.view_index(view), before)
            reply["solve_ms"] = round(solve_ms, 2)
            reply["journal_ms"] = round((journaled - planned) * 1000, 2)
            return reply

    def _consequence(self, t: int, p: int, v: int, before: np.ndarray) -> dict:
        """What an edit of point ``p`` in view ``v`` did: ``rose``, the other views whose error
        grew by more than :data:`WORSE_PX` (``after`` None: now dropped), and ``dropped``, how
        far its own 2D lies from the 3D that the robust triangulation solved without it."""
        pairs = zip(before.round(1).tolist(), self.error[:, t, p].round(1).tolist())
        rose = [
            {"view": self.view_names[u], "before": b, "after": None if math.isnan(a) else a}
            for u, (b, a) in enumerate(pairs)
            if u != v and math.isfinite(b) and not a <= b + WORSE_PX
        ]
        return {"point": p, "view": self.view_names[v], "rose": rose, "dropped": self._off(v, t, p)}

    def _off(self, v: int, t: int, p: int) -> float | None:
        """How far the edited 2D of ``p`` in view ``v`` lies from its 3D when the robust
        triangulation left it out; None when it is used, not edited, or has no 3D."""
        xy, xyz = self.corrections.points[v, t, p], self.pts3d[t, p]
        if np.isfinite(self.used2d[v, t, p]).all() or not np.isfinite([*xy, *xyz]).all():
            return None
        return round(float(np.linalg.norm(self.cameras[v].project(xyz) - xy)), 1)

    @property
    def journal_path(self) -> Path:
        """Where this session's unsaved edits are journaled."""
        return self._journal.path

    def _check_revision(self, revision: Any) -> None:
        if revision is None:
            return
        if type(revision) is not int or not 0 <= revision <= _MAX_INT:
            raise ValueError(
                f"revision must be an integer from 0 to 2**63 - 1, got {shown(revision)}"
            )
        if revision != self.revision:
            raise StaleRevision(revision, self.revision)

    def _plan(
        self, op: Any, frame: Any, point: Any, view: Any, xy: Any, fixed: Any = False
    ) -> dict:
        """The journal record of an edit, every argument checked; nothing changes yet."""
        if op not in EDIT_OPS:
            raise ValueError(
                f"unknown edit {str(op)[:40]!r}; use move, move3d, invisible, reset_point, "
                "reset_view, reset_frame, reviewed or unreviewed"
            )
        if type(fixed) is not bool:
            raise ValueError(f"fixed must be true or false, got {str(fixed)[:40]}")
        if fixed and op != "move":
            raise ValueError(f"fixed applies to move (Edit 2D) only, not to {op}")
        t = self._check_frame(_integer("frame", frame))
        if view is not None and not isinstance(view, str):
            raise ValueError("view must be a camera name")
        v = None if view is None else self.view_index(view)
        record: dict[str, Any] = {"op": op, "frame": t, "view": view}
        if op in ("move", "move3d", "invisible", "reset_point", "reviewed", "unreviewed"):
            record["point"] = p = _in_range("point", _integer("point", point), self.n_points)
            if op in ("move", "move3d", "invisible") and v is None:
                raise ValueError(f"{op} needs a view")
        elif op == "reset_view" and v is None:
            raise ValueError("reset_view needs a view")
        if op in ("move", "move3d"):
            record["xy"] = self._check_xy(view, xy)
        if fixed:
            record["fixed"] = True
        if op == "move3d":
            record["op"] = "set3d"
            record["xyz"] = self._onto_ray(v, t, p, np.asarray(record["xy"])).tolist()
        return record

    def _check_xy(self, view: str, xy: Any) -> list[float]:
        """Two finite pixel coordinates inside ``view``'s image, as floats."""
        if isinstance(xy, np.ndarray) and xy.dtype.kind == "f":
            xy = xy.tolist()
        if (
            not isinstance(xy, (list, tuple))
            or len(xy) != 2
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in xy)
        ):
            raise ValueError(f"xy must be two pixel coordinates [x, y], got {str(xy)[:60]}")
        x, y = (_finite("xy", c, "pixel coordinates") for c in xy)
        height, width = self.image_sizes[view]
        if not (0 <= x <= width and 0 <= y <= height):
            raise ValueError(f"xy [{x:.6g}, {y:.6g}] lies outside {view}'s {width}x{height} image")
        return [x, y]

    def _apply_record(self, record: dict) -> range | list[int]:
        """Change the corrections as a checked record says; the points to re-solve."""
        op, t = record["op"], record["frame"]
        self._unsaved.setdefault(t, self.corrections.subset([t], slice(None)))
        view, p = record.get("view"), record.get("point")
        v = None if view is None else self.view_index(view)
        if op == "move":
            self.corrections.set_point(v, t, p, record["xy"], fixed=record.get("fixed", False))
        elif op == "set3d":
            self.corrections.set_point3d(t, p, record["xyz"])
        elif op == "invisible":
            self.corrections.set_invisible(v, t, p)
        elif op == "reset_point":
            self.corrections.reset(t, point=p, view=v)
        elif op in ("reviewed", "unreviewed"):
            self.corrections.reviewed[t, p] = op == "reviewed"
            return []
        elif op == "reset_view":
            self.corrections.reset(t, view=v)
            return range(self.n_points)
        else:
            self.corrections.reset(t)
            return range(self.n_points)
        return [p]

    def _replay_journal(self) -> None:
        """Apply the edits a previous session journaled but did not save."""
        replay = read_journal(self._journal.path)
        if not replay.edits and not replay.damaged:
            return
        applied, refused = 0, []
        for record in replay.edits:
            try:
                checked = self._checked_journal_record(record)
                self._apply_record(checked)
            except (KeyError, IndexError, ValueError, TypeError) as exc:
                refused.append(str(exc).strip("'\""))
                continue
            applied += 1
        self.revision += applied
        self.dirty = applied > 0
        # counted as Save counts them (points), not journal lines (a drag journals each position)
        changed, marks = self.unsaved()
        steps = f", {applied} journal steps" if applied != changed else ""
        marks_text = f" and {marks} review mark(s)" if marks else ""
        parts = [
            f"{changed} unsaved edit(s){marks_text} replayed from {self._journal.path} "
            f"(a previous session stopped before saving{steps}); press Save to keep them"
        ]
        if (
            replay.sidecar_revision is not None
            and replay.sidecar_revision != self.corrections.revision
        ):
            parts.append(
                f"they were made on revision {replay.sidecar_revision} of "
                f"{self.corrections_path.name}, which is now at {self.corrections.revision}"
            )
        if replay.damaged:
            parts.append(f"damaged journal line(s) skipped: {replay.damaged[:10]}")
        if refused:
            parts.append(f"{len(refused)} edit(s) refused: {refused[0]}")
        self.notice = "; ".join(parts)
        log.warning("flylib gui: %s", self.notice)

    def _checked_journal_record(self, record: dict) -> dict:
        """A journal line through the same checks as an edit from the page."""
        if not isinstance(record, dict):
            raise ValueError("not an edit")
        if record.get("op") != "set3d":
            return self._plan(
                record.get("op"),
                record.get("frame"),
                record.get("point"),
                record.get("view"),
                record.get("xy"),
                record.get("fixed", False),
            )
        checked = self._plan(
            "invisible", record.get("frame"), record.get("point"), record.get("view"), None
        )
        xyz = record.get("xyz")
        if (
            not isinstance(xyz, list)
            or len(xyz) != 3
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in xyz)
        ):
            raise ValueError(f"a 3D edit must be three finite numbers, got {str(xyz)[:60]}")
        return {**checked, "op": "set3d", "xyz": [_finite("a 3D edit", c, "numbers") for c in xyz]}

    def _onto_ray(self, v: int, t: int, p: int, xy: np.ndarray) -> np.ndarray:
        """The point on pixel ``xy``'s ray in view ``v`` closest to the current 3D point."""
        from ..camera.jax_model import closest_point_on_ray

        target = self.pts3d[t, p]
        if not np.isfinite(target).all():
            raise ValueError(
                f"point {self.skeleton.point_names[p]} has no 3D at frame {t}; "
                "place it in 2D (Edit 2D) first"
            )
        origin, direction = self.cameras[v].backproject_ray(xy)
        return np.asarray(closest_point_on_ray(origin, direction, target), dtype=np.float64)

    def save(self, *, revision: int | None = None) -> Path:
        """Write the corrections sidecar atomically, then drop the journal; a page that is
        behind gets :class:`StaleRevision`, an unwritable sidecar OutputError (edits kept)."""
        with self._lock:
            self._check_revision(revision)
            self.corrections.revision = self.revision
            try:
                path = self.corrections.save(self.corrections_path)
            except OSError as err:  # atomic_path's OutputError already names the file and why
                said = (
                    err
                    if isinstance(err, OutputError)
                    else f"{self.corrections_path}: cannot save ({err.strerror or err})"
                )
                raise OutputError(
                    f"{said}; the edits are kept in {self._journal.path.name} and in this "
                    "session: make the directory writable or free space, then save again"
                ) from None
            self._journal.discard()
            self.dirty = False
            self._unsaved.clear()
            self.notice = ""  # a replayed journal's: saved now
        log.info("corrections saved to %s (%d edits)", path, self.corrections.count())
        return path

    def unsaved(self) -> tuple[int, int]:
        """Point edits and review marks changed since the sidecar was loaded or saved."""
        counts = [
            _changes(before, self.corrections.subset([t], slice(None)))
            for t, before in self._unsaved.items()
        ]
        return tuple(map(sum, zip((0, 0), *counts)))

    def _stat(self) -> tuple | None:
        """What tells a rewritten results.h5 (a re-run) from the one this session read."""
        try:
            st = self.results_path.stat()
        except OSError:
            return None
        return st.st_ino, st.st_mtime_ns, st.st_size

    def reload(self) -> None:
        """Read results.h5 again (a re-run rewrote it); unsaved edits come back from the journal."""
        with self._lock:
            self.close()
            results, config, footage, footage_dir, cache = self._opened
            self.__init__(
                results, config=config, footage=footage, footage_dir=footage_dir, cache_frames=cache
            )

    # -- background prefetch ---------------------------------------------------------------

    def visit(self, frame: int) -> None:
        """The user is at ``frame``: prefetch the neighbouring suspect frames (``n`` / ``p``)."""
        if self._suspects is None:
            return
        frames = self._suspects.frames
        later = frames[frames > frame]
        earlier = frames[frames < frame]
        todo = [int(f) for f in (*later[:2], *earlier[-1:])]
        with self._prefetch_wake:
            self._prefetch_todo = todo
            self._prefetch_wake.notify()

    def _prefetch_loop(self) -> None:
        while True:
            with self._prefetch_wake:
                while not self._prefetch_todo and not self._closed:
                    self._prefetch_wake.wait()
                if self._closed:
                    return
                frame = self._prefetch_todo.pop(0)
            for name in self.view_names:
                if self._closed:
                    return
                try:
                    self.frames[name].prefetch(frame)
                except (FlylibError, OSError, ValueError, IndexError) as exc:  # reported on request
                    log.debug("prefetch of %s frame %d failed: %s", name, frame, exc)

    def close(self) -> None:
        self._journal.close()
        self._sidecar_lock.release()
        with self._prefetch_wake:
            self._closed = True
            self._prefetch_wake.notify()
        self._prefetcher.join(timeout=5)
        for source in self.frames.values():
            source.close()


#: The largest integer a request may carry (frames, points and revisions are far below).
_MAX_INT = 2**63 - 1


def shown(value: Any) -> str:
    """``value`` quoted in a message: at most 40 characters, a long number shortened."""
    text = str(value)
    if isinstance(value, int) and len(text) > 24:
        return f"{text[:12]}...({len(text.lstrip('-'))} digits)"
    return text[:40]


def _in_range(name: str, value: Any, n: int) -> int:
    """``value`` as an index below ``n``; ``IndexError`` outside ``0..n - 1``."""
    i = int(value)
    if not 0 <= i < n:
        raise IndexError(f"{name} {shown(value)} out of range 0..{n - 1}")
    return i


def _integer(name: str, value: Any) -> int:
    """``value`` when it is an integer (JSON ``true`` is not one) within +-2**63."""
    if type(value) is not int and not isinstance(value, np.integer):
        raise ValueError(f"{name} must be an integer, got {shown(value)}")
    if not -_MAX_INT <= int(value) <= _MAX_INT:
        raise ValueError(f"{name} {shown(value)} is out of range (at most 2**63 - 1)")
    return int(value)


def _finite(name: str, value: int | float, what: str) -> float:
    """``value`` as a finite float; else a ``ValueError`` (never an ``OverflowError``)."""
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise ValueError(f"{name} must be finite {what}, got {shown(value)}")
    return number


def _changes(before: Corrections, after: Corrections) -> tuple[int, int]:
    """How many point edits (as ``Corrections.count`` counts them) and review marks differ."""

    def differ(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return ~((a == b) | (np.isnan(a) & np.isnan(b))).all(-1)

    observations = (
        (before.edited != after.edited)
        | (before.fixed != after.fixed)
        | (before.invisible != after.invisible)
        | differ(before.points, after.points)
    )
    points3d = (before.edited3d != after.edited3d) | differ(before.points3d, after.points3d)
    return int(observations.sum() + points3d.sum()), int((before.reviewed != after.reviewed).sum())
