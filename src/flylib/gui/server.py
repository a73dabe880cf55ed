"""Run the GUI with uvicorn: ``flylib gui <outdir or results.h5> [--host --port --no-browser]``."""

from __future__ import annotations

import ipaddress
import logging
import secrets
import socket
import sys
import threading
import webbrowser
from pathlib import Path

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (no token needed there)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def free_port(host: str, preferred: int) -> int:
    """``preferred`` if it can be bound on ``host`` (kept after a Stop), else a free port the OS
    picks."""
    for port in (preferred, 0):
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
            if sys.platform != "win32":  # a stopped server's port in TIME_WAIT (uvicorn's too)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((host, port))
            except OSError:
                continue
            return sock.getsockname()[1]
    raise OSError(f"cannot bind {host}; pass another --host")


def serve(
    results: str | Path,
    *,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    open_browser: bool = True,
    token: str | None = None,
    footage_dir: str | Path | None = None,
) -> None:
    """Open the recording (its output directory or ``results.h5``) and serve the GUI until
    interrupted; any ``host`` but localhost requires an access ``token`` (default: random, part of
    the printed URL). A busy ``port`` is replaced by a free one."""
    import uvicorn

    from .app import create_app
    from .security import LOOPBACK_NAMES, MAX_BODY
    from .session import ReviewSession

    session = ReviewSession(results, footage_dir=footage_dir)
    loopback = is_loopback(host)
    if not loopback:
        token = token or secrets.token_urlsafe(24)
    port = free_port(host, port)
    app = create_app(
        session,
        token=token,
        guard_reads=not loopback,
        hosts=LOOPBACK_NAMES if loopback else None,  # elsewhere every request needs the token
    )
    shown = (
        "localhost" if loopback else (socket.gethostname() if host in ("0.0.0.0", "::") else host)
    )
    url = f"http://{shown}:{port}/" + (f"?token={token}" if not loopback else "")
    print(
        f"flylib gui: {session.results_path} ({session.n_frames} frames, {session.n_views} views)"
    )
    if session.notice:
        print(f"flylib gui: {session.notice}")
    if session.footage_missing:
        print(f"flylib gui: {session.footage_missing}")
    print(
        f"flylib gui: open {url}  (Ctrl+C stops; every edit is journaled to "
        f"{session.journal_path} until Save writes {session.corrections_path})"
    )
    if loopback:
        print(
            f"flylib gui: from another machine: ssh -L {port}:localhost:{port} <this host>, "
            f"then open http://localhost:{port}/"
        )
    if open_browser:
        threading.Timer(1.0, lambda: webbrowser.open(url)).start()
    try:
        server = uvicorn.Server(
            uvicorn.Config(app, host=host, port=port, log_level="warning", ws_max_size=MAX_BODY)
        )
        app.state.stop = lambda: setattr(server, "should_exit", True)  # the page's Stop
        server.run()
    finally:
        if session.dirty:
            print(
                f"flylib gui: {sum(session.unsaved())} edit(s) not saved to "
                f"{session.corrections_path} are kept in {session.journal_path}; the next "
                "`flylib gui` on this recording replays them"
            )
        session.close()
