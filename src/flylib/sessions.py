"""Sessions: recordings made on one unchanged rig, bundle-adjusted together.

With ``bundle_adjustment.session: true`` the recordings of a batch are grouped into sessions:
by the ``session`` their entry (or the sheet's ``session`` column) names, else by the folder
that holds them. Each session is solved once (:mod:`flylib.pipeline.session_calibration`) and
gets its own folder, ``<the members' common folder>/flylib_sessions/<name>/``, holding the
session's rig (``calibration.toml``, Anipose format, and ``session_calibration.h5``) and its
summary (``session_summary.json``: the held-out-view error of the per-recording and session
rigs side by side).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from .errors import ConfigError
from .paths import file_name, name_problem
from .recordings import Recording

__all__ = ["SESSIONS_DIR", "Session", "plan_sessions", "session_lines"]

#: The folder, beside the members' output folders, that holds one folder per session.
SESSIONS_DIR = "flylib_sessions"


@dataclass(frozen=True)
class Session:
    """Recordings sharing one rig: ``members`` in the batch's order, ``outdir`` the session's
    folder (:data:`SESSIONS_DIR`). ``name`` is the ``session`` key, else the folder's name
    (folders of one name get a path hash)."""

    name: str
    members: tuple[Recording, ...]
    outdir: Path

    @property
    def ids(self) -> list[str]:
        """The members' recording ids."""
        return [r.id for r in self.members]

    @property
    def calibration(self) -> Path:
        """The session's rig in Anipose format."""
        return self.outdir / "calibration.toml"

    @property
    def artifact(self) -> Path:
        """The session's rig as a bundle-adjustment artifact (what the stages read)."""
        return self.outdir / "session_calibration.h5"

    @property
    def summary(self) -> Path:
        """Per-recording and session rigs side by side."""
        return self.outdir / "session_summary.json"


def plan_sessions(recordings: Sequence[Recording]) -> list[Session]:
    """Group ``recordings`` into sessions (by ``session`` name, else by the folder holding
    them), in the order of their first member. ConfigError for a name that is no folder name,
    two sessions of one folder (names compared as file names, ignoring case) or a session
    folder that is a recording's output folder."""
    groups: dict[tuple[str, str], list[Recording]] = {}
    for rec in recordings:
        problem = rec.session and name_problem(rec.session)
        if problem:
            raise ConfigError(
                f"{rec.extra.get('where', 'recordings')}: session {rec.session!r} cannot "
                f"be a folder name: {problem}; rename it (e.g. day1)"
            )
        key = ("name", rec.session) if rec.session else ("folder", _folder(rec))
        groups.setdefault(key, []).append(rec)
    names = {k: k[1] if k[0] == "name" else (Path(k[1]).name or "session") for k in groups}
    taken: dict[str, int] = {}
    for name in names.values():
        taken[_fold(name)] = taken.get(_fold(name), 0) + 1
    for key, name in names.items():
        if key[0] == "folder" and taken[_fold(name)] > 1:  # two folders of one name
            names[key] = f"{name}-{hashlib.sha1(key[1].encode()).hexdigest()[:8]}"
    outdirs = {str(Path(r.outdir).resolve()): r.id for r in recordings}
    sessions: dict[str, Session] = {}
    for key, members in groups.items():
        name = names[key]
        parents = [os.path.abspath(Path(r.outdir).parent) for r in members]
        common = Path(os.path.commonpath(parents))
        folder = common / SESSIONS_DIR / file_name(name, "session")
        if str(folder.resolve()) in outdirs:
            raise ConfigError(
                f"recordings: session {name!r}'s folder {folder} is the output folder of "
                f"recording {outdirs[str(folder.resolve())]!r}; give that recording another outdir"
            )
        other = sessions.setdefault(str(folder).casefold(), Session(name, tuple(members), folder))
        if other.members != tuple(members):
            raise ConfigError(
                f"recordings: sessions {other.name!r} and {name!r} would both be solved in "
                f"{folder} (a session's name is its folder's, as a file name and ignoring "
                "case); rename one of them"
            )
    return list(sessions.values())


def _fold(name: str) -> str:
    return file_name(name, "session").casefold()


def _folder(rec: Recording) -> str:
    return os.path.abspath(Path(rec.path).parent)


def session_lines(sessions: Sequence[Session]) -> list[str]:
    """One line per session whose summary exists: the held-out-view error (median px) with
    the per-recording rigs and with the session's, and where its rig is."""
    import json

    lines = []
    for s in sessions:
        try:
            summary = json.loads(s.summary.read_text())
        except (OSError, ValueError):
            continue
        held = summary.get("held_out_error_px", {})
        trial = (held.get("per_recording") or {}).get("median")
        whole = (held.get("session") or {}).get("median")
        if trial is None or whole is None:
            continue
        better = {"session": "session better", "per_recording": "per-recording better"}
        n = len(s.members)
        lines.append(
            f"session {s.name} ({n} recording{'s' * (n != 1)}): held-out median "
            f"{trial:.2f} px with each recording's own rig, {whole:.2f} px with the "
            f"session's ({better.get(summary.get('better'), 'equal')}); the rig the results "
            f"use: {s.calibration}"
        )
    return lines
