"""One writer per output directory: a lock file held for the duration of each job.

Two Snakemake runs started from different working directories do not know about
each other's jobs (one working directory is locked by Snakemake itself, and the jobs of
one run share the lock: they run side by side, e.g. visualization and kinematics); both writing one ``outdir`` would interleave artifacts made with
different configs. Every stage script takes ``<outdir>/.flylib.lock`` (created
exclusively, holding the holder's host, pid, working directory and job) before it
writes and removes it when done; a second writer fails at once with one line naming
the holder. A lock left by a process that died (same host, pid gone) is taken over.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

from .errors import OutputError

__all__ = ["LOCK_NAME", "lock_holder", "outdir_lock"]

#: The lock file's name inside an output directory.
LOCK_NAME = ".flylib.lock"
# A lock file found empty or unreadable is being written by its creator; after this
# many seconds it is taken for the remains of a crash.
_UNREADABLE_GRACE_S = 2.0


def lock_holder(path: str | Path) -> dict | None:
    """The holder recorded in a lock file, or ``None`` when it is empty or unreadable."""
    try:
        holder = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return holder if isinstance(holder, dict) else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def _is_stale(holder: dict) -> bool:
    """Whether the holder is a process of this host that no longer exists."""
    try:
        return holder.get("host") == socket.gethostname() and not _alive(int(holder["pid"]))
    except (KeyError, TypeError, ValueError):
        return False


def _same_run(holder: dict, me: dict) -> bool:
    """Whether the holder is a live job of the same working directory on this host: the
    same Snakemake run (Snakemake itself refuses a second run in one working directory),
    e.g. visualization and kinematics of one recording running side by side."""
    return (
        holder.get("host") == me["host"]
        and holder.get("cwd") == me["cwd"]
        and not _is_stale(holder)
    )


def _describe(holder: dict) -> str:
    return (
        f"pid {holder.get('pid')} on {holder.get('host')}, working directory {holder.get('cwd')}, "
        f"job {holder.get('job')}, since {holder.get('since')}"
    )


def _take_over(path: Path, stale: dict | None) -> None:
    """Remove a stale lock file, unless another taker replaced it meanwhile.

    The file is first moved aside under a name of our own (of two takers only one
    move succeeds); if what was moved is no longer the stale holder (another taker
    already put its live lock there), it is put back.
    """
    aside = path.with_name(f"{LOCK_NAME}.stale.{os.getpid()}")
    try:
        os.replace(path, aside)
    except FileNotFoundError:
        return
    if lock_holder(aside) != stale:
        with contextlib.suppress(FileExistsError):
            os.link(aside, path)
    aside.unlink(missing_ok=True)


@contextlib.contextmanager
def outdir_lock(outdir: str | Path, job: str) -> Iterator[Path]:
    """Hold ``<outdir>/.flylib.lock`` for the block's duration.

    Parameters
    ----------
    outdir
        The recording's output directory (created if missing).
    job
        What holds the lock, for the message another writer gets (e.g. ``triangulation``).

    Yields
    ------
    Path
        The lock file.

    Raises
    ------
    OutputError
        When a live process (or one on another host) holds the lock: one line naming
        it, its working directory and the lock file.
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    path = outdir / LOCK_NAME
    me = {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "cwd": os.getcwd(),
        "job": job,
        "since": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    first_unreadable = None
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = lock_holder(path)
            if holder is None:  # being written right now, or left empty by a crash
                first_unreadable = first_unreadable or time.monotonic()
                if time.monotonic() - first_unreadable < _UNREADABLE_GRACE_S:
                    time.sleep(0.05)
                    continue
            elif _same_run(holder, me):
                break  # a sibling job of this run (Snakemake locks a working directory itself)
            elif not _is_stale(holder):
                raise OutputError(
                    f"{outdir}: another run is writing this output directory ({_describe(holder)}); "
                    f"wait for it to finish, or give each run its own outdir; if that process is gone, "
                    f"delete {path}"
                ) from None
            _take_over(path, holder)
            first_unreadable = None
            continue
        with os.fdopen(fd, "w") as handle:
            json.dump(me, handle)
        break
    try:
        yield path
    finally:
        holder = lock_holder(path)
        if (
            holder is not None
            and holder.get("pid") == me["pid"]
            and holder.get("host") == me["host"]
        ):
            path.unlink(missing_ok=True)
