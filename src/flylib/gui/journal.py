"""Edits that survive anything: an fsync'd journal beside ``corrections.h5``, and one GUI per
sidecar.

Every edit is appended to ``<sidecar>.journal`` (a JSON line with a CRC-32, fsync'd) *before* it
is applied, so a stopped server, a crash or a closed tab loses nothing: the next ``flylib gui``
replays the journal on top of the sidecar (each line checked like an edit from the page) and says
so. Saving writes the sidecar, then removes the journal. ``<sidecar>.lock`` (``fcntl.flock``,
released by the kernel even on ``kill -9``) refuses a second server on the same output directory."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import zlib
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ..errors import OutputError, one_line

JOURNAL_FORMAT = 1


def journal_path(sidecar: Path) -> Path:
    """``<sidecar>.journal``: the unsaved edits of ``sidecar``."""
    return sidecar.with_name(sidecar.name + ".journal")


def lock_path(sidecar: Path) -> Path:
    """``<sidecar>.lock``: held by the GUI editing ``sidecar``."""
    return sidecar.with_name(sidecar.name + ".lock")


def _crc(record: dict) -> int:
    return zlib.crc32(json.dumps(record, sort_keys=True, separators=(",", ":")).encode())


@dataclass
class Replay:
    """What a journal held: its edits in order, and the lines that could not be used."""

    edits: list[dict] = field(default_factory=list)
    damaged: list[int] = field(default_factory=list)  # 1-based line numbers
    sidecar_revision: int | None = None  # the sidecar revision the journal started from


def read_journal(path: Path) -> Replay:
    """A journal's edits; a line that is not JSON or fails its CRC-32 is listed in ``damaged``."""
    replay = Replay()
    if not path.is_file():
        return replay
    with open(path, "rb") as f:
        for number, raw in enumerate(f, 1):
            if not raw.strip():
                continue
            try:
                line = json.loads(raw)
                record, crc = line["record"], line["crc"]
                ok = isinstance(record, dict) and crc == _crc(record)
            except (ValueError, TypeError, KeyError, RecursionError):
                ok = False
            if not ok:
                replay.damaged.append(number)
            elif "journal" in record:
                replay.sidecar_revision = record.get("sidecar_revision")
            else:
                replay.edits.append(record)
    return replay


class EditJournal:
    """Appends edits to ``<sidecar>.journal``, each one durable before it returns."""

    def __init__(self, sidecar: Path):
        self.sidecar = Path(sidecar)
        self.path = journal_path(self.sidecar)
        self._file = None

    def append(self, record: dict, sidecar_revision: int, *, durable: bool = True) -> None:
        """Write one edit and flush it (survives the server's death); fsync it too when
        ``durable`` (survives the machine's: all but a drag's intermediate positions)."""
        try:
            if self._file is None:
                new = not self.path.exists() or self.path.stat().st_size == 0
                self._file = open(self.path, "ab")  # noqa: SIM115 (kept open across edits)
                if new:
                    header = {
                        "journal": JOURNAL_FORMAT,
                        "sidecar": str(self.sidecar),
                        "sidecar_revision": int(sidecar_revision),
                        "created_utc": datetime.now(UTC).isoformat(),
                    }
                    self._write(header, durable=True)
                    _fsync_dir(self.path.parent)
            self._write(record, durable=durable)
        except OSError as err:
            self.close()
            raise OutputError(
                f"{self.path}: cannot store the edit ({one_line(err)}); it was not applied. "
                "Free disk space or make the directory writable, then edit again"
            ) from None

    def _write(self, record: dict, *, durable: bool) -> None:
        line = json.dumps({"record": record, "crc": _crc(record)}, separators=(",", ":"))
        self._file.write(line.encode() + b"\n")
        self._file.flush()
        if durable:
            os.fsync(self._file.fileno())

    def discard(self) -> None:
        """Remove the journal (its edits are in the saved sidecar now)."""
        self.close()
        self.path.unlink(missing_ok=True)

    def close(self) -> None:
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None


def _fsync_dir(directory: Path) -> None:
    """Make a new file's name durable too (its directory entry)."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class SidecarLock:
    """One ``flylib gui`` per sidecar: an exclusive ``flock`` on ``<sidecar>.lock``; a lock that
    cannot be created (read-only directory) is no error: such a session cannot save either."""

    def __init__(self, sidecar: Path):
        self.path = lock_path(Path(sidecar))
        self._fd: int | None = None

    def acquire(self) -> None:
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _read_holder(fd)
            os.close(fd)
            raise OutputError(
                f"{self.path.with_suffix('')}: another flylib gui ({holder}) is editing these "
                "corrections; use that one, or stop it first, so neither overwrites the "
                "other's saves"
            ) from None
        info: dict[str, Any] = {"host": socket.gethostname(), "pid": os.getpid()}
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(info).encode(), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._fd, fcntl.LOCK_UN)
                os.close(self._fd)
            self._fd = None


def _read_holder(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
        return f"pid {int(info['pid'])} on {str(info['host'])[:100]}"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"
