"""Warm processes: a workflow job's stage script forked from a process that has already
imported flylib and its libraries, instead of a fresh interpreter importing them again.

Why: a recording makes seven CPU jobs, and for a short recording each spends more time
starting (the interpreter, JAX, matplotlib, PyAV, h5py, the compiled JAX kernels read
back from the cache) than computing. ``benchmarks/workflow.py`` measures it.

How: the first job of a run finds no warm process, starts one in the background and runs
itself as before. The warm process imports :data:`PRELOAD` (never initialising JAX's
backend, so forking stays safe) and listens on a Unix socket private to the user. Every
later job's script (``scripts/_cli.py``) connects right after Snakemake's preamble, sends
its script, arguments, working directory, environment and its stdin/stdout/stderr, and
waits: the warm process forks a child that runs the script as ``__main__`` (the job's
own process, log, lock and signal handling, see ``script_main``) and reports its exit
status, which the job exits with. A stop signal the job receives is passed on to the
child; a job killed outright (SIGKILL) takes its child with it. The warm process exits after
:data:`IDLE_SECONDS` without work.

One warm process per code and environment: its socket is named by a hash of the Python,
flylib's source files (their paths, sizes and times) and the environment variables read
while modules import (:data:`IMPORT_TIME_VARIABLES`), so an edit or an upgrade starts a
fresh one; every other variable is the job's own in its child.

Off (``FLYLIB_WARM=0``), and off by itself on a batch scheduler's node (SLURM, LSF, PBS,
SGE: their steps end with their processes), off where there is no ``fork`` (Windows) and
on macOS (fork without exec is unsafe there). What changes for the user: nothing in the
results; a job's Snakemake benchmark file still times it, but its memory and CPU columns
count the waiting job, not the child that computed (``benchmarks/stage_memory.py``
measures the stages' memory).
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import hashlib
import importlib
import json
import os
import runpy
import selectors
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path

#: What the warm process imports before it forks: every stage module and the libraries
#: they import only inside functions (drawing, decoding, reading other tools' files).
PRELOAD = (
    "snakemake.script",  # the job's preamble unpickles its ``snakemake`` object
    "flylib.camera.jax_model",  # JAX in float64, with the compilation cache
    "flylib.pipeline.pose2d",
    "flylib.interop.importer",
    "flylib.interop.dlc",
    "flylib.bundle_adjustment.sequence",
    "flylib.pipeline.bundle_adjustment",
    "flylib.pipeline.triangulation",
    "flylib.pipeline.refinement",
    "flylib.pipeline.assemble",
    "flylib.pipeline.kinematics",
    "flylib.pipeline.visualization",
    "flylib.visualization.summary",
    "flylib.visualization.compose",
    "matplotlib.figure",
    "matplotlib.backends.backend_agg",
    "av",
    "pandas",
)

#: Seconds a warm process waits for work before it exits.
IDLE_SECONDS = 60.0

#: Environment variables that a batch scheduler sets in its jobs.
SCHEDULER_VARIABLES = ("SLURM_JOB_ID", "LSB_JOBID", "PBS_JOBID", "SGE_TASK_ID")

#: Environment variables read while modules import (the warm process reads them once,
#: its children inherit what they did): names, and prefixes ending in ``_``.
IMPORT_TIME_VARIABLES = (
    "FLYLIB_CACHE",
    "FLYLIB_NO_JAX_CACHE",
    "PYTHONPATH",
    "MPLBACKEND",
    "MPLCONFIGDIR",
    "JAX_",
    "XLA_",
    "OMP_",
    "MKL_",
    "OPENBLAS_",
)

_ENABLE = "FLYLIB_WARM"
_CHILD = "FLYLIB_WARM_CHILD"
_HEADER = struct.Struct("!I")
_KEEP_LOGS_SECONDS = 7 * 24 * 3600
_MAX_SOCKET_PATH = 100  # a Unix socket's path has at most 107 bytes on Linux


def off_because() -> str | None:
    """Why this process may not hand its job to a warm process (``None``: it may)."""
    if os.environ.get(_ENABLE, "1") == "0":
        return f"{_ENABLE}=0"
    if os.environ.get(_CHILD):
        return "this process is a warm process's child"
    if not sys.platform.startswith("linux") or not hasattr(socket, "send_fds"):
        return f"Linux only (this is {sys.platform})"
    scheduler = next((name for name in SCHEDULER_VARIABLES if os.environ.get(name)), None)
    if scheduler:
        return f"a batch scheduler's node ({scheduler} is set)"
    return None


def _source_fingerprint() -> str:
    """Paths, sizes and modification times of flylib's Python files."""
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256(str(root).encode())
    for path in sorted(root.rglob("*.py")):
        stat = path.stat()
        digest.update(f"{path}:{stat.st_size}:{stat.st_mtime_ns}".encode())
    return digest.hexdigest()


def socket_path() -> Path:
    """The socket of the warm process for this Python, flylib code and environment, in a
    folder only this user can enter."""
    digest = hashlib.sha256()
    digest.update(f"{sys.executable}\0{sys.version}\0{_source_fingerprint()}".encode())
    for name in sorted(os.environ):
        if any(name.startswith(v) if v.endswith("_") else name == v for v in IMPORT_TIME_VARIABLES):
            digest.update(f"\0{name}={os.environ[name]}".encode())
    name = Path(f"flylib-warm-{os.getuid()}") / f"{digest.hexdigest()[:20]}.sock"
    base = Path(os.environ.get("XDG_RUNTIME_DIR") or "/tmp")
    if len(str(base / name)) > _MAX_SOCKET_PATH:
        base = Path("/tmp")
    return base / name


def _private_folder(folder: Path) -> bool:
    """Make ``folder`` (mode 0700); ``False`` when it exists but another user owns it or
    others may enter it (then no warm process is used)."""
    with contextlib.suppress(FileExistsError):
        folder.mkdir(mode=0o700, parents=True)
    stat = folder.stat()
    return stat.st_uid == os.getuid() and not stat.st_mode & 0o077


# --- the job's side --------------------------------------------------------------------


def forward(script: str | Path) -> int | None:
    """Run ``script`` (this job's ``__main__``, with ``sys.argv``) in a child of the warm
    process and return its exit status; ``None`` when there is no warm process to take
    it (one is started for the next jobs) or warm processes are off: the caller runs the
    job itself."""
    if off_because() is not None:
        return None
    path = socket_path()
    try:
        if not _private_folder(path.parent):
            return None
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        conn.connect(str(path))
    except OSError:
        _start(path)
        return None
    with conn:
        request = json.dumps(
            {
                "script": str(Path(script).resolve()),
                "argv": sys.argv,
                "cwd": os.getcwd(),
                "env": dict(os.environ),
                "path": sys.path,
            }
        ).encode()
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            socket.send_fds(conn, [_HEADER.pack(len(request))], [0, 1, 2])
            conn.sendall(request)
            reply = conn.makefile("r")
            first = reply.readline().split()
        except OSError:
            return None
        if first[:1] != ["pid"]:  # refused before a child started: run here
            return None
        child = int(first[1])

        def pass_on(signum: int, frame: object) -> None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(child, signum)

        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(signum, pass_on)
        words = reply.readline().split()
    if words[:1] == ["exit"]:
        return int(words[1])
    if words[:1] == ["signal"]:  # end as the child ended, so Snakemake reads the same
        signum = int(words[1])
        with contextlib.suppress(OSError, ValueError):  # SIGKILL has no handler to reset
            signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
    print(
        f"error: the warm process running this job ended first (set {_ENABLE}=0 to run "
        f"every job in a process of its own); its log: {path.with_suffix('.log')}",
        file=sys.stderr,
    )
    return 1


def _start(path: Path) -> None:
    """Start a warm process on ``path`` in the background (its own session, so the job's
    end does not stop it), unless one holds its lock (it is still importing)."""
    import fcntl

    with contextlib.suppress(OSError), open(path.with_suffix(".lock"), "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return
        fcntl.flock(lock, fcntl.LOCK_UN)
        with open(path.with_suffix(".log"), "ab") as log:
            subprocess.Popen(
                [sys.executable, "-m", __name__, str(path)],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                start_new_session=True,
                close_fds=True,
                env={k: v for k, v in os.environ.items() if k != _CHILD},
            )


# --- the warm process's side -----------------------------------------------------------


def _backend_started() -> bool:
    """Whether JAX has set up its backend (threads a fork would not copy)."""
    from jax._src import xla_bridge

    return bool(getattr(xla_bridge, "_backends", None))


def _receive(conn: socket.socket) -> tuple[dict, list[int]]:
    """A job's request and its three file descriptors."""
    header, fds, _, _ = socket.recv_fds(conn, _HEADER.size, 3)
    if len(header) != _HEADER.size or len(fds) != 3:
        for fd in fds:
            os.close(fd)
        raise OSError("incomplete request")
    (size,) = _HEADER.unpack(header)
    data = b""
    while len(data) < size:
        chunk = conn.recv(size - len(data))
        if not chunk:
            raise OSError("incomplete request")
        data += chunk
    return json.loads(data), fds


def _child(request: dict, fds: list[int], inherited: list) -> None:
    """In the forked child: become the job's process and run its script; never returns.
    ``inherited``: the warm process's sockets and pipes, closed here."""
    code = 1
    try:
        signal.set_wakeup_fd(-1)
        for thing in inherited:
            with contextlib.suppress(OSError):
                os.close(thing) if isinstance(thing, int) else thing.close()
        for signum in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD):
            signal.signal(signum, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
            os.close(fd)
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        os.environ[_CHILD] = "1"
        sys.argv = list(request["argv"])
        sys.path[:] = request["path"]
        try:
            runpy.run_path(request["script"], run_name="__main__")
            code = 0
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) else (stop.code is not None)
            if isinstance(stop.code, str):
                print(stop.code, file=sys.stderr)
        except BaseException:  # the job's traceback, as its own process would print it
            traceback.print_exc()
        threading._shutdown()  # join the job's threads, as the interpreter's exit does
        atexit._run_exitfuncs()
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def serve(path: Path, idle: float = IDLE_SECONDS) -> None:
    """Import :data:`PRELOAD`, then fork a child for each job that connects to ``path``
    until ``idle`` seconds pass without work. Exits at once when another warm process
    serves ``path``."""
    import fcntl

    lock = open(path.with_suffix(".lock"), "w")  # noqa: SIM115 - held for the life of the process
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return
    lock.write(f"{os.getpid()}\n")  # who serves (benchmarks/workflow.py reads its CPU time)
    lock.flush()
    os.environ[_CHILD] = "1"  # this process never forwards
    for log in path.parent.glob("*.log"):  # of earlier code or environments
        with contextlib.suppress(OSError):
            if time.time() - log.stat().st_mtime > _KEEP_LOGS_SECONDS:
                log.unlink()
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    # Listening before importing: a job that connects meanwhile waits for the imports
    # rather than starting another warm process.
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen(64)
    started = time.perf_counter()
    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except Exception as exc:  # an optional library missing: its jobs import it themselves
            _log(f"not preloaded {name}: {exc}")
    if _backend_started():
        _log("JAX's backend started while importing; not forking")
        path.unlink()
        return
    gc.collect()
    gc.freeze()  # the children share the imported objects' pages instead of copying them
    _log(f"ready in {time.perf_counter() - started:.2f} s (pid {os.getpid()})")
    wake_read, wake_write = os.pipe()
    os.set_blocking(wake_write, False)
    signal.set_wakeup_fd(wake_write)
    signal.signal(signal.SIGCHLD, lambda signum, frame: None)
    selector = selectors.DefaultSelector()
    selector.register(listener, selectors.EVENT_READ, "accept")
    selector.register(wake_read, selectors.EVENT_READ, "child")
    children: dict[int, socket.socket] = {}  # child pid -> its job's connection
    last_work = time.monotonic()
    try:
        while children or time.monotonic() - last_work < idle:
            for key, _ in selector.select(timeout=1.0):
                if key.data == "accept":
                    conn, _ = listener.accept()
                    last_work = time.monotonic()
                    inherited = [listener, selector, wake_read, wake_write, *children.values()]
                    _fork_job(conn, inherited, selector, children)
                elif key.data == "child":
                    os.read(wake_read, 512)
                    _reap(children, selector)
                    last_work = time.monotonic()
                else:  # a job's connection readable: the job died (SIGKILL) first
                    pid = key.data
                    if pid in children:  # as its own process would have: at once
                        with contextlib.suppress(ProcessLookupError):
                            os.kill(pid, signal.SIGKILL)
                    selector.unregister(key.fileobj)
            _reap(children, selector)
    finally:
        for own in (path, path.with_suffix(".lock")):  # held by this process: its own
            with contextlib.suppress(FileNotFoundError):
                own.unlink()
        listener.close()
        _log("idle: leaving")


def _fork_job(conn: socket.socket, inherited: list, selector, children: dict) -> None:
    """Fork the child that runs ``conn``'s job (``inherited``: what it closes), and tell
    the job its pid."""
    try:
        conn.settimeout(10)
        request, fds = _receive(conn)
        conn.settimeout(None)
    except (OSError, ValueError):
        conn.close()
        return
    pid = os.fork()
    if pid == 0:
        _child(request, fds, [*inherited, conn])
    for fd in fds:
        os.close(fd)
    try:
        conn.sendall(f"pid {pid}\n".encode())
    except OSError:
        os.kill(pid, signal.SIGTERM)
    children[pid] = conn
    selector.register(conn, selectors.EVENT_READ, pid)
    _log(f"{Path(request['script']).name} in {request['cwd']}: pid {pid}")


def _reap(children: dict, selector) -> None:
    """Send each ended child's status to its job."""
    while children:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        conn = children.pop(pid, None)
        if conn is None:
            continue
        if os.WIFSIGNALED(status):
            message = f"signal {os.WTERMSIG(status)}\n"
        else:
            message = f"exit {os.waitstatus_to_exitcode(status)}\n"
        _log(f"pid {pid}: {message.strip()}")
        with contextlib.suppress(OSError):
            conn.sendall(message.encode())
        with contextlib.suppress(KeyError, ValueError):
            selector.unregister(conn)
        conn.close()


def _log(message: str) -> None:
    """A line in the warm process's log (its stderr: ``<socket>.log``)."""
    print(f"{time.strftime('%Y-%m-%d %H:%M:%S')} warm: {message}", file=sys.stderr, flush=True)


if __name__ == "__main__":  # python -m flylib.warm SOCKET [IDLE_SECONDS]
    serve(Path(sys.argv[1]), *(float(a) for a in sys.argv[2:3]))
