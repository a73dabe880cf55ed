"""Video frame counts, read from a container's header once and kept in the user's cache for as long
as the file is unchanged: planning a batch again opens none of its videos."""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import sqlite3
import struct
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import FootageError
from ..paths import cache_dir

log = logging.getLogger(__name__)


def video_frame_count(path: Path) -> int | None:
    """Frame count a video container reports (header only, no decoding), or ``None`` when it stores
    none; kept in the user's cache (:class:`FrameCountCache`) while the file is unchanged. A file
    that cannot be opened as a video is a :class:`FootageError`."""
    return FRAME_COUNTS.count(path, header_frame_count)


def header_frame_count(path: Path) -> int | None:
    """A video's frame count from its header (MP4 sample table, else av)."""
    return mp4_frame_count(path) or _av_frame_count(path)


def _mp4_boxes(data: bytes, start: int, end: int):
    """``(type, payload start, end)`` of the MP4 boxes in ``data[start:end]``."""
    while start + 8 <= end:
        size, kind = struct.unpack_from(">I4s", data, start)
        head = 16 if size == 1 else 8
        size = struct.unpack_from(">Q", data, start + 8)[0] if size == 1 else size or end - start
        if size < head or start + size > end:
            return
        yield kind, start + head, start + size
        start += size


def mp4_frame_count(path: Path) -> int | None:
    """Sample count of an MP4/QuickTime file's first video track, summed from its ``stts`` table as
    FFmpeg does (a 60th of the time of opening it with av, which decodes); ``None`` for any other
    file, a fragmented one or anything unexpected: av reads those."""
    if path.suffix.lower() not in (".mp4", ".mov", ".m4v"):
        return None
    try:
        with open(path, "rb") as f:
            size, pos = os.fstat(f.fileno()).st_size, 0
            while pos + 16 <= size:  # the top level, to the moov box, without reading mdat
                f.seek(pos)
                kind, start, end = next(_mp4_boxes(f.read(16) + bytes(8), 0, 1 << 62))
                if kind == b"moov":
                    f.seek(pos)
                    moov = f.read(min(end, size - pos))
                    break
                pos += end
            else:
                return None
    except (OSError, StopIteration):
        return None
    for kind, start, end in _mp4_boxes(moov, 8, len(moov)):
        if kind == b"mvex":
            return None
        if kind == b"trak":
            boxes: dict = {}  # the first of each: a QuickTime minf has a data-handler hdlr too
            for kind_, span in _nested(moov, start, end):
                boxes.setdefault(kind_, span)
            hdlr, stts = boxes.get(b"hdlr"), boxes.get(b"stts")
            if hdlr and moov[hdlr[0] + 8 : hdlr[0] + 12] == b"vide":
                if not stts or stts[1] - stts[0] < 8:
                    return None
                n = struct.unpack_from(">I", moov, stts[0] + 4)[0]
                if stts[0] + 8 + 8 * n > stts[1]:
                    return None
                return sum(struct.unpack_from(f">{2 * n}I", moov, stts[0] + 8)[::2]) or None
    return None


def _nested(data: bytes, start: int, end: int):
    """``(type, (payload start, end))`` of every box under a ``trak``'s media boxes."""
    for kind, s, e in _mp4_boxes(data, start, end):
        yield kind, (s, e)
        if kind in (b"mdia", b"minf", b"stbl"):
            yield from _nested(data, s, e)


def _av_frame_count(path: Path) -> int | None:
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise FootageError(f"{path}: holds no video stream; replace the file")
            n = container.streams.video[0].frames
    except av.error.FFmpegError as exc:
        raise FootageError(f"{path}: cannot be read as a video ({exc}); replace the file") from exc
    return int(n) if n and n > 0 else None


class FrameCountCache:
    """Video frame counts already read, in ``<cache>/frame_counts.sqlite3``
    (:func:`flylib.paths.cache_dir`), by path and file identity (device, inode, size, modification
    time): a file rewritten or replaced is read again. Opening a video with av costs some 3 ms, 20 s
    for the 7,000 videos of a 1,000-recording batch, which Snakemake plans again on every call. A
    cache that cannot be opened, locked or written is passed by: the count is then read from the
    file."""

    def __init__(self, folder: Callable[[], Path] = cache_dir) -> None:
        self._folder = folder
        self._lock = threading.Lock()
        self._db: Any = None
        self._pid = -1
        self._pending: dict[str, tuple[str, int | None]] = {}  # written in batches

    def _connection(self):
        """The database of this process (a forked child opens its own), or ``None``."""
        if self._pid != os.getpid():
            self._pid, self._db = os.getpid(), None
            try:
                folder = self._folder()
                folder.mkdir(parents=True, exist_ok=True)
                db = sqlite3.connect(
                    folder / "frame_counts.sqlite3",
                    timeout=1.0,
                    isolation_level=None,
                    check_same_thread=False,
                )
                db.execute("PRAGMA synchronous=OFF")
                db.execute(
                    "CREATE TABLE IF NOT EXISTS counts "
                    "(path TEXT PRIMARY KEY, identity TEXT NOT NULL, frames INTEGER)"
                )
                self._db = db
                self._pending = {}
                atexit.register(self.flush)
            except (OSError, sqlite3.Error) as exc:
                log.debug("frame-count cache not used: %s", exc)
        return self._db

    def count(self, path: Path, read: Callable[[Path], int | None]) -> int | None:
        """``path``'s count: cached for the file as it is now, else ``read(path)``, kept (written
        with the next few hundred, or at exit: one transaction each, not one per video)."""
        try:
            st = os.stat(path)
        except OSError:
            return read(path)  # it says what is wrong with the path
        key = os.path.abspath(path)  # the identity below tells a replaced or relinked file
        identity = f"{st.st_dev}:{st.st_ino}:{st.st_size}:{st.st_mtime_ns}"
        with self._lock:
            db = self._connection()
            if db is None:
                return read(path)
            row = self._pending.get(key)
            if row is None:
                with contextlib.suppress(sqlite3.Error):
                    row = db.execute(
                        "SELECT identity, frames FROM counts WHERE path = ?", (key,)
                    ).fetchone()
        if row is not None and row[0] == identity:
            return row[1]
        frames = read(path)
        with self._lock:
            self._pending[key] = (identity, frames)
            full = len(self._pending) >= 500
        if full:
            self.flush()
        return frames

    def flush(self) -> None:
        """Write the counts kept since the last write."""
        with self._lock:
            rows = [(path, *row) for path, row in self._pending.items()]
            self._pending = {}
            if not rows or self._db is None or self._pid != os.getpid():
                return
            try:
                self._db.execute("BEGIN")
                self._db.executemany("INSERT OR REPLACE INTO counts VALUES (?, ?, ?)", rows)
                self._db.execute("COMMIT")
            except sqlite3.Error as exc:
                log.debug("frame-count cache not written: %s", exc)
                with contextlib.suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")


#: The process's frame-count cache (:func:`video_frame_count`).
FRAME_COUNTS = FrameCountCache()
