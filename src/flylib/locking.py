"""One writer per output directory: a lock file held for the duration of each job.

Two Snakemake runs started from different working directories do not know about each
other's jobs (Snakemake locks one working directory; the jobs of one run share it and run
side by side, e.g. visualization and kinematics); both writing one ``outdir`` would
interleave artifacts made with different configs. Every stage script takes
``<outdir>/.flylib.lock`` (created exclusively, holding the holder's host, pid, working
directory and job) before it writes and removes it when done; a second writer fails at once
with one line naming the holder. A lock left by a process that died (same host, pid gone)
is taken over.

A job's lock comes too late to protect a whole run: Snakemake deletes a job's old outputs
before the job starts. The workflow therefore *claims* every output directory of a run
(:func:`claim_outdirs`) once its DAG is built, before any job is scheduled or output
removed, and releases them when the run ends (:func:`release_outdirs`). The claim is the
same lock file, held by the Snakemake process and naming a run id that the run's jobs
inherit through :data:`RUN_ENV` (on a cluster node too): they pass it, every other writer
stops.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
import socket
import time
import uuid
from collections.abc import Iterable, Iterator
from datetime import UTC, datetime
from pathlib import Path

from .errors import OutputError

__all__ = [
    "LOCK_NAME",
    "RUN_ENV",
    "claim_lost",
    "claim_outdirs",
    "held_outdir",
    "lock_holder",
    "outdir_lock",
    "pid_alive",
    "release_outdirs",
]

#: The lock file's name inside an output directory.
LOCK_NAME = ".flylib.lock"
# A lock file found empty or unreadable is being written by its creator; after this many
# seconds it is taken for the remains of a crash.
_UNREADABLE_GRACE_S = 2.0
#: Carries a run's id to its jobs (set when the workflow claims the run's output
#: directories; inherited by local and cluster jobs).
RUN_ENV = "FLYLIB_RUN_ID"
_HELD: contextvars.ContextVar[Path | None] = contextvars.ContextVar("held_outdir", default=None)


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this host (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process; a pid out of range
        return True
    return True


def held_outdir() -> Path | None:
    """The resolved output directory whose lock the running block holds (:func:`outdir_lock`),
    else ``None``. Artifacts record it to tell a copied directory."""
    return _HELD.get()


def claim_lost(path: str | Path) -> str | None:
    """Why this job may no longer put ``path`` in place (one line), or ``None`` when it may.

    A job of a run (:data:`RUN_ENV` set) inside :func:`outdir_lock` writes under its run's
    claim. A killed run's jobs may live on while the next run takes the stale claim over;
    an orphan's output would then replace the new run's, so it is refused. Outside a run,
    outside the held directory, or with no claim file left, nothing is checked.
    """
    run = os.environ.get(RUN_ENV)
    held = _HELD.get()
    if not run or held is None:
        return None
    if not Path(os.path.abspath(path)).resolve().is_relative_to(held):
        return None
    holder = lock_holder(held / LOCK_NAME)
    if holder is None or holder.get("run") == run:
        return None
    return (
        f"{path}: not written: another run took over {held} while this job ran "
        f"({_describe(holder)}); this job's run was stopped or killed, so its result "
        "was discarded and the new run's files are kept"
    )


def lock_holder(path: str | Path) -> dict | None:
    """The holder recorded in a lock file, or ``None`` when it is empty or unreadable."""
    try:
        holder = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return holder if isinstance(holder, dict) else None


def _is_stale(holder: dict) -> bool:
    """Whether the holder is a process of this host that no longer exists."""
    try:
        return holder.get("host") == socket.gethostname() and not pid_alive(int(holder["pid"]))
    except (KeyError, TypeError, ValueError):
        return False


def _same_run(holder: dict, me: dict) -> bool:
    """Whether the holder belongs to this process's run: its run id (on any host), or a live
    process of the same working directory on this host (Snakemake refuses a second run in
    one working directory), e.g. visualization and kinematics running side by side."""
    if me.get("run") and holder.get("run") == me["run"]:
        return True
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
    """Remove a stale lock file, unless another taker replaced it meanwhile: it is moved
    aside under our own name (of two takers only one move succeeds), and put back if what
    was moved is no longer the stale holder."""
    aside = path.with_name(f"{LOCK_NAME}.stale.{os.getpid()}")
    try:
        os.replace(path, aside)
    except FileNotFoundError:
        return
    if lock_holder(aside) != stale:
        with contextlib.suppress(FileExistsError):
            os.link(aside, path)
    aside.unlink(missing_ok=True)


def _me(job: str, run: str | None) -> dict:
    me = {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "cwd": os.getcwd(),
        "job": job,
        "since": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    if run:
        me["run"] = run
    return me


def _acquire(outdir: Path, me: dict) -> bool:
    """Take ``outdir``'s lock for ``me``; ``False`` when this run already holds it, an
    :class:`OutputError` when another live run (or a process on another host) does."""
    outdir.mkdir(parents=True, exist_ok=True)
    path = outdir / LOCK_NAME
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
                return False  # a sibling job of this run, or the run's own claim
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
        return True


def _release(outdir: Path, me: dict) -> None:
    """Remove ``outdir``'s lock if ``me`` (this process) holds it."""
    path = outdir / LOCK_NAME
    holder = lock_holder(path)
    if holder is not None and holder.get("pid") == me["pid"] and holder.get("host") == me["host"]:
        path.unlink(missing_ok=True)


@contextlib.contextmanager
def outdir_lock(outdir: str | Path, job: str) -> Iterator[Path]:
    """Hold ``<outdir>/.flylib.lock`` (yielded) for the block's duration.

    Inside a run that claimed the directory (:data:`RUN_ENV`) the claim stands for the
    job's lock. ``outdir`` is created if missing; ``job`` (e.g. ``triangulation``) is named
    in the message another writer gets. OutputError when a live process of another run (or
    one on another host) holds the lock.
    """
    outdir = Path(outdir)
    me = _me(job, os.environ.get(RUN_ENV))
    owned = _acquire(outdir, me)
    token = _HELD.set(outdir.resolve())
    try:
        yield outdir / LOCK_NAME
    finally:
        _HELD.reset(token)
        if owned:
            _release(outdir, me)


def claim_outdirs(outdirs: Iterable[str | Path], run: str | None = None) -> list[Path]:
    """Claim every output directory of a run for this process, all or none.

    Sets :data:`RUN_ENV` to the run's id (``run``, else :data:`RUN_ENV`, else a new random
    one), so the jobs started from now on pass the claim. ``outdirs`` are created if
    missing. Returns those this call claimed (not those the run held already), for
    :func:`release_outdirs`. OutputError for the first directory another live run holds,
    after releasing those claimed before it.
    """
    run = run or os.environ.get(RUN_ENV) or uuid.uuid4().hex
    os.environ[RUN_ENV] = run
    me = _me("snakemake run", run)
    claimed: list[Path] = []
    try:
        for outdir in dict.fromkeys(Path(o) for o in outdirs):
            if _acquire(outdir, me):
                claimed.append(outdir)
    except BaseException:
        release_outdirs(claimed)
        raise
    return claimed


def release_outdirs(outdirs: Iterable[str | Path]) -> None:
    """Release the claims :func:`claim_outdirs` took (one another process took over since is
    left alone)."""
    me = _me("snakemake run", None)
    for outdir in outdirs:
        _release(Path(outdir), me)
