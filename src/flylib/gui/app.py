"""The GUI's FastAPI app: REST for meta, frames, points and suspects; a WebSocket for edits.

Routes (all under the optional access token, see :func:`create_app`)::

    GET  /                          the page (static/index.html)
    GET  /static/{file}             the front-end's ES modules and CSS (package data)
    GET  /api/meta                  views, sizes, skeleton + palette, frame count
    GET  /api/frame/{view}/{frame}  the view's footage frame as JPEG
    GET  /api/points/{frame}        2D (edits applied), used flags, reprojected 3D, errors
    GET  /api/suspects              suspect (frame, point) pairs and the per-frame score
    POST /api/edit                  one edit (JSON, as on the WebSocket); returns the frame
    POST /api/save                  write corrections.h5 beside results.h5
    WS   /ws                        edits: {"op", "frame", "point", "view", "xy"} -> points
                                    (op: move, move3d, invisible, reset_point, reset_view,
                                    reset_frame; move takes "fixed": true; or {"op": "save"})

Camera names are looked up in the rig (never used to build a path) and frame numbers
are integers checked against the recording, so no request reaches any other file.
"""

from __future__ import annotations

import hmac
import time
from importlib import resources
from typing import Any

from fastapi import FastAPI, HTTPException, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles

from .session import ReviewSession

STATIC = resources.files("flylib.gui") / "static"


def create_app(session: ReviewSession, token: str | None = None) -> FastAPI:
    """The app serving one :class:`ReviewSession`.

    Parameters
    ----------
    session
        The opened recording.
    token
        When set, every request must carry it (query ``?token=``, header
        ``X-Flylib-Token`` or the cookie the page sets); used when the server is
        bound to anything but localhost.
    """
    app = FastAPI(title="flylib gui", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.session = session

    def authorized(request_token: str | None) -> bool:
        return token is None or (
            request_token is not None
            and hmac.compare_digest(request_token.encode(), token.encode())
        )

    @app.middleware("http")
    async def check_token(request: Request, call_next):
        supplied = (
            request.query_params.get("token")
            or request.headers.get("x-flylib-token")
            or request.cookies.get("flylib_token")
        )
        if not authorized(supplied):
            return JSONResponse(
                {"detail": "missing or wrong access token; open the URL `flylib gui` printed"},
                status_code=403,
            )
        response = await call_next(request)
        if token is not None and request.url.path == "/":
            response.set_cookie("flylib_token", token, httponly=True, samesite="strict")
        return response

    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")

    @app.get("/", response_class=HTMLResponse)
    def index() -> HTMLResponse:
        return HTMLResponse(
            (STATIC / "index.html").read_text(), headers={"Cache-Control": "no-store"}
        )

    @app.get("/api/meta")
    def meta() -> dict:
        return session.meta()

    @app.get("/api/frame/{view}/{frame}")
    def frame(view: str, frame: int) -> Response:
        if view not in session.view_names:
            raise HTTPException(404, f"unknown camera {view!r}")
        _check_frame(frame)
        started = time.perf_counter()
        data = session.frames[view].jpeg(frame)
        elapsed = (time.perf_counter() - started) * 1000
        return Response(
            data,
            media_type="image/jpeg",
            headers={
                "Cache-Control": "private, max-age=3600",
                "Server-Timing": f"decode;dur={elapsed:.1f}",
            },
        )

    @app.get("/api/points/{frame}")
    def points(frame: int) -> dict:
        _check_frame(frame)
        reply = session.points(frame)
        session.visit(frame)
        return reply

    @app.get("/api/suspects")
    def suspects() -> dict:
        return session.suspects_payload()

    @app.post("/api/edit")
    async def edit(request: Request) -> dict:
        try:
            message = await request.json()
        except ValueError:
            raise HTTPException(400, "the body must be JSON") from None
        reply = _apply(message)
        if "error" in reply:
            raise HTTPException(400, reply["error"])
        return reply

    @app.post("/api/save")
    def save() -> dict:
        path = session.save()
        return {"saved": str(path), "edits": session.corrections.count()}

    @app.websocket("/ws")
    async def ws(websocket: WebSocket) -> None:
        supplied = websocket.query_params.get("token") or websocket.cookies.get("flylib_token")
        if not authorized(supplied):
            await websocket.close(code=1008)
            return
        await websocket.accept()
        try:
            while True:
                message = await websocket.receive_json()
                if isinstance(message, dict) and message.get("op") == "save":
                    path = session.save()
                    await websocket.send_json(
                        {"op": "saved", "saved": str(path), "edits": session.corrections.count()}
                    )
                    continue
                await websocket.send_json(_apply(message))
        except WebSocketDisconnect:
            return

    def _check_frame(frame: int) -> None:
        if not 0 <= frame < session.n_frames:
            raise HTTPException(404, f"frame {frame} out of range 0..{session.n_frames - 1}")

    def _apply(message: Any) -> dict:
        """One edit message -> the frame's points (plus the server time), or an error."""
        if not isinstance(message, dict):
            return {"error": "an edit is a JSON object with op, frame, point, view, xy"}
        started = time.perf_counter()
        try:
            frame = message.get("frame")
            point = message.get("point")
            if not isinstance(frame, int) or (point is not None and not isinstance(point, int)):
                raise ValueError("frame and point must be integers")
            view = message.get("view")
            if view is not None and not isinstance(view, str):
                raise ValueError("view must be a camera name")
            fixed = message.get("fixed", False)
            if not isinstance(fixed, bool):
                raise ValueError("fixed must be true or false")
            reply = session.edit(
                str(message.get("op")), frame, point, view, message.get("xy"), fixed=fixed
            )
        except (KeyError, IndexError, ValueError, TypeError) as exc:
            return {"error": str(exc).strip("'\"")}
        reply["op"] = "points"
        reply["server_ms"] = round((time.perf_counter() - started) * 1000, 2)
        return reply

    return app
