"""The GUI's FastAPI app: REST for meta, frames, points and suspects; a WebSocket for edits.

Routes::

    GET  /                          the page (static/index.html, the session token inside)
    GET  /static/{file}             the front-end's ES modules and CSS (package data)
    GET  /api/meta                  views, sizes, skeleton + palette, frame count, revision
    GET  /api/frame/{view}/{frame}  the view's footage frame as JPEG
    GET  /api/frames/{frame}        every view's JPEG, one after another (lengths: X-Lengths),
                                    ?small=1: at half size where made (playback)
    GET  /api/points/{frame}        2D (edits applied), used flags, reprojected 3D, errors
    GET  /api/suspects              suspect (frame, point) pairs, per-frame score, review progress
    GET  /api/save-check            what the edits made worse (said before saving)
    POST /api/edit                  one edit {"op", "frame", "point", "view", "xy", "revision",
                                    "durable", "fixed"} (op: one of session.EDIT_OPS) -> points
    POST /api/save                  write corrections.h5 beside results.h5
    POST /api/stop                  stop the server (the page's Stop button)
    POST /api/reload                read results.h5 again (a re-run rewrote it; edits replayed)
    WS   /ws                        the same edits, or {"op": "save"}; other pages' edits arrive
                                    as {"op": "changed", "revision"}

Every request passes :class:`~flylib.gui.security.RequestGuard`, every response carries a strict
Content-Security-Policy. Camera names are looked up in the rig (never used to build a path) and
frame numbers checked, so no request reaches any other file. Errors are one ``{"detail": ...}``."""

from __future__ import annotations

import html
import logging
import secrets
import time
from asyncio import gather
from collections.abc import Iterable
from importlib import resources
from typing import Any

from fastapi import FastAPI, HTTPException, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from ..errors import FlylibError
from .security import (
    LOOPBACK_NAMES,
    MAX_BODY,
    SECURITY_HEADERS,
    WS_PROTOCOL,
    RequestGuard,
    RequestRefused,
    check_json_content_type,
    parse_json,
)
from .session import ReviewSession, StaleRevision, shown

log = logging.getLogger(__name__)

STATIC = resources.files("flylib.gui") / "static"
CACHED = {"Cache-Control": "private, max-age=3600"}
_TOKEN_SLOT = '<meta name="flylib-token" content="">'


def create_app(
    session: ReviewSession,
    token: str | None = None,
    *,
    guard_reads: bool | None = None,
    hosts: Iterable[str] | None = LOOPBACK_NAMES,
    port: int | None = None,
) -> FastAPI:
    """The app serving one :class:`ReviewSession`.

    ``token`` (default: random; in the page's HTML) must come with every mutating request;
    ``guard_reads`` (default: when ``token`` is given) requires it on reads too. Any ``Host`` but
    ``hosts`` (and ``port``) is refused (DNS rebinding); ``hosts=None``: any, with ``guard_reads``.
    """
    if guard_reads is None:
        guard_reads = token is not None
    token = token or secrets.token_urlsafe(24)
    guard = RequestGuard(token, hosts, port, guard_reads)
    app = FastAPI(title="flylib gui", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.session = session
    app.state.token = token
    app.state.stop = None  # what POST /api/stop calls: set by whoever runs the server
    _add_request_checks(app, guard, token)
    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")
    edits = _Edits(session)
    _add_read_routes(app, session, token)
    _add_edit_routes(app, edits)
    _add_edit_socket(app, guard, edits)
    return app


def _refused(status: int, message: str) -> JSONResponse:
    return JSONResponse({"detail": message}, status_code=status, headers=SECURITY_HEADERS)


def _add_request_checks(app: FastAPI, guard: RequestGuard, token: str) -> None:
    """Every request through ``guard``, every response with the security headers."""

    @app.middleware("http")
    async def check_request(request: Request, call_next):
        try:
            guard.check_origin(request.headers)
            if guard.guard_reads and not guard.token_matches(
                request.query_params.get("token")
                or request.headers.get("x-flylib-token")
                or request.cookies.get("flylib_token")
            ):
                raise RequestRefused(
                    403, "missing or wrong access token; open the URL `flylib gui` printed"
                )
            if request.method not in ("GET", "HEAD"):
                guard.check_mutation_token(request.headers.get("x-flylib-token"))
                check_json_content_type(request.headers.get("content-type"))
                length = request.headers.get("content-length")
                if length is not None and (not length.isdigit() or int(length) > MAX_BODY):
                    raise RequestRefused(
                        413, f"refused: the body is larger than {MAX_BODY // 1024} KiB"
                    )
        except RequestRefused as exc:
            return _refused(exc.status, str(exc))
        response = await call_next(request)
        response.headers.update(SECURITY_HEADERS)
        if guard.guard_reads and request.url.path == "/":
            response.set_cookie("flylib_token", token, httponly=True, samesite="strict")
        return response

    @app.exception_handler(HTTPException)
    async def one_line_error(request: Request, exc: HTTPException) -> JSONResponse:
        return _refused(exc.status_code, str(exc.detail))

    @app.exception_handler(RequestValidationError)
    async def one_line_invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        # a path number that is not an integer ("1e400"): one line, not pydantic's list
        problem = (exc.errors() or [{}])[0]
        where = ".".join(str(part) for part in problem.get("loc", ())[1:]) or "request"
        return _refused(
            422, f"{where}: {problem.get('msg', 'invalid')} ({shown(problem.get('input'))})"
        )


def _add_read_routes(app: FastAPI, session: ReviewSession, token: str) -> None:

    def check_frame(frame: int) -> None:
        if not 0 <= frame < session.n_frames:
            raise HTTPException(404, f"frame {shown(frame)} out of range 0..{session.n_frames - 1}")

    @app.get("/", response_class=HTMLResponse)
    def index() -> HTMLResponse:
        page = (STATIC / "index.html").read_text()
        page = page.replace(
            _TOKEN_SLOT, f'<meta name="flylib-token" content="{html.escape(token, quote=True)}">'
        )
        return HTMLResponse(page, headers={"Cache-Control": "no-store"})

    @app.get("/api/meta")
    def meta() -> dict:
        return session.meta()

    @app.get("/api/frame/{view}/{frame}")
    def frame(view: str, frame: int) -> Response:
        if view not in session.view_names:
            raise HTTPException(404, f"unknown camera {view[:80]!r}")
        check_frame(frame)
        return Response(session.frames[view].jpeg(frame), media_type="image/jpeg", headers=CACHED)

    @app.get("/api/frames/{frame}")
    async def frames(frame: int, small: bool = False) -> Response:
        # one request a frame, not one per view: each costs the browser more than its decode
        check_frame(frame)
        views, names = session.frames, session.view_names
        jpegs = await gather(*(run_in_threadpool(views[v].jpeg, frame, small) for v in names))
        lengths = ",".join(str(len(j)) for j in jpegs)
        return Response(b"".join(jpegs), headers={**CACHED, "X-Lengths": lengths})

    @app.get("/api/points/{frame}")
    def points(frame: int) -> dict:
        check_frame(frame)
        reply = session.points(frame)
        session.visit(frame)
        return reply

    @app.get("/api/suspects")
    def suspects() -> dict:
        return session.suspects_payload()

    @app.get("/api/save-check")
    def save_check() -> dict:
        return session.save_check()


def _add_edit_routes(app: FastAPI, edits: _Edits) -> None:

    @app.post("/api/edit")
    async def edit(request: Request) -> JSONResponse:
        reply = edits.apply(await _read_json(request))
        if reply["op"] != "points":
            return _refused(_STATUS[reply["op"]], reply["error"])
        await edits.broadcast(None, reply["revision"], reply["frame"])
        return JSONResponse(reply)

    @app.post("/api/stop")
    async def stop(request: Request) -> JSONResponse:
        await _read_json(request)
        if request.app.state.stop is None:
            return _refused(409, "this server cannot be stopped from the page; press Ctrl+C")
        request.app.state.stop()
        return JSONResponse({"op": "stopping", "dirty": edits.session.dirty})

    @app.post("/api/reload")
    async def reload(request: Request) -> JSONResponse:
        await _read_json(request)
        try:
            edits.session.reload()
        except FlylibError as exc:
            return _refused(409, f"{exc}; stop and start `flylib gui` again")
        return JSONResponse({"op": "reloaded", "revision": edits.session.revision})

    @app.post("/api/save")
    async def save(request: Request) -> JSONResponse:
        reply = edits.save(await _read_json(request))
        if reply["op"] != "saved":
            return _refused(_STATUS[reply["op"]], reply["error"])
        return JSONResponse(reply)


def _add_edit_socket(app: FastAPI, guard: RequestGuard, edits: _Edits) -> None:

    @app.websocket("/ws")
    async def ws(websocket: WebSocket) -> None:
        try:
            guard.check_origin(websocket.headers)
            offered = _offered_protocols(websocket)
            guard.check_mutation_token(guard.ws_token(offered, websocket.query_params.get("token")))
        except RequestRefused as exc:
            log.warning("flylib gui: WebSocket %s", exc)
            await websocket.close(code=1008)
            return
        await websocket.accept(subprotocol=WS_PROTOCOL if WS_PROTOCOL in offered else None)
        edits.sockets[websocket] = edits.session.revision
        try:
            while True:
                raw = await websocket.receive()
                if raw["type"] == "websocket.disconnect":
                    return
                data = raw.get("bytes") or (raw.get("text") or "").encode()
                try:
                    message = parse_json(data, "the message")
                except RequestRefused as exc:
                    await websocket.send_json({"op": "refused", "error": str(exc)})
                    continue
                if isinstance(message, dict) and message.get("op") == "save":
                    await websocket.send_json(edits.save(message))
                    continue
                reply = edits.apply(message, websocket)
                await websocket.send_json(reply)
                if reply["op"] == "points":
                    await edits.broadcast(websocket, reply["revision"], reply["frame"])
        except WebSocketDisconnect:
            return
        finally:
            edits.sockets.pop(websocket, None)


async def _read_json(request: Request) -> Any:
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_BODY:
            raise HTTPException(413, f"refused: the body is larger than {MAX_BODY // 1024} KiB")
    try:
        return parse_json(bytes(body)) if body else {}
    except RequestRefused as exc:
        raise HTTPException(exc.status, str(exc)) from None


class _Edits:
    """The session's edit path shared by REST and the WebSocket, and the open pages."""

    def __init__(self, session: ReviewSession):
        self.session = session
        # each open page: the revision after the latest edit from anywhere else; its own edits
        # since then are not stale (typed-ahead keys send before the previous reply arrives)
        self.sockets: dict[WebSocket, int] = {}

    async def broadcast(self, origin: WebSocket | None, revision: int, frame: int) -> None:
        """Tell every other open page that the edits changed (it refreshes)."""
        for other in list(self.sockets):
            if other is origin:
                continue
            try:
                await other.send_json({"op": "changed", "revision": revision, "frame": frame})
            except (RuntimeError, OSError, WebSocketDisconnect):
                self.sockets.pop(other, None)

    def apply(self, message: Any, origin: WebSocket | None = None) -> dict:
        """One edit message (from page ``origin``) -> the frame's points (plus the server
        time), or an error."""
        if not isinstance(message, dict):
            return {
                "op": "refused",
                "error": "an edit is a JSON object with op, frame, point, view, xy",
            }
        started = time.perf_counter()
        revision = message.get("revision")
        mine = self.sockets.get(origin)  # None: REST, or not a page
        if type(revision) is int and mine is not None and mine <= revision < self.session.revision:
            revision = self.session.revision  # only this page edited since
        try:
            reply = self.session.edit(
                message.get("op"),
                message.get("frame"),
                message.get("point"),
                message.get("view"),
                message.get("xy"),
                fixed=message.get("fixed", False),
                revision=revision,
                durable=message.get("durable", True) is not False,
            )
        except StaleRevision as exc:
            return {"op": "stale", "error": str(exc), "revision": exc.current}
        except FlylibError as exc:  # the journal cannot be written: not applied
            return {"op": "not_stored", "error": str(exc)}
        except (KeyError, IndexError, ValueError, TypeError, OverflowError) as exc:
            return {"op": "refused", "error": str(exc).strip("'\"")}
        reply["op"] = "points"
        for other in self.sockets:
            if other is not origin:
                self.sockets[other] = reply["revision"]
        reply["server_ms"] = round((time.perf_counter() - started) * 1000, 2)
        return reply

    def save(self, message: Any) -> dict:
        revision = message.get("revision") if isinstance(message, dict) else None
        try:
            path = self.session.save(revision=revision)
        except StaleRevision as exc:
            return {"op": "stale", "error": str(exc), "revision": exc.current}
        except (FlylibError, OSError) as exc:
            return {"op": "save_failed", "error": str(exc)}
        except ValueError as exc:
            return {"op": "refused", "error": str(exc)}
        return {
            "op": "saved",
            "saved": str(path),
            "edits": self.session.corrections.count(),
            "revision": self.session.revision,
        }


def _offered_protocols(websocket: WebSocket) -> list[str]:
    offered = websocket.scope.get("subprotocols") or (
        websocket.headers.get("sec-websocket-protocol") or ""
    ).split(",")
    return [str(p).strip() for p in offered]


#: HTTP status of each refusal a REST edit or save can meet.
_STATUS = {"refused": 400, "stale": 409, "not_stored": 507, "save_failed": 507}
