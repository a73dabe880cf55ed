"""``flylib gui`` closed to other web pages, request by request.

Each case is one attack a page on another origin (or a DNS-rebinding host name) can
mount against a server on localhost: its request is refused with one line, and
nothing reaches the session (no edit, no corrections.h5). Through FastAPI's
TestClient, and against a real uvicorn server where the Host/Origin path differs
(a raw HTTP request and a raw WebSocket handshake).
"""

from __future__ import annotations

import json
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the GUI needs fastapi (pip install fastapi uvicorn httpx)")
pytest.importorskip("httpx", reason="FastAPI's TestClient needs httpx")

from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from flylib.gui import ReviewSession, create_app
from flylib.gui.security import MAX_BODY, json_depth, parse_json

from gui_fixtures import make_demo_outputs, rename_hostile

FRAMES = 6
ORIGIN = "http://127.0.0.1:8765"
STATIC = Path(__file__).resolve().parents[2] / "src" / "flylib" / "gui" / "static"


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    return make_demo_outputs(tmp_path_factory.mktemp("gui_security") / "rec", frames=FRAMES)


@pytest.fixture
def app(outdir):
    for name in ("corrections.h5", "corrections.h5.journal"):
        (outdir / name).unlink(missing_ok=True)
    session = ReviewSession(outdir)
    yield create_app(session)
    session.close()
    for name in ("corrections.h5", "corrections.h5.journal"):
        (outdir / name).unlink(missing_ok=True)


def client_for(app, base_url=ORIGIN, **headers):
    return TestClient(app, base_url=base_url, headers=headers)


def an_edit(app, **change):
    session = app.state.session
    view = session.view_names[0]
    height, width = session.image_sizes[view]
    return {
        "op": "move",
        "frame": 1,
        "point": 3,
        "view": view,
        "xy": [width / 2, height / 2],
    } | change


def nothing_changed(app):
    session = app.state.session
    return (
        session.corrections.count() == 0
        and session.revision == 0
        and not (session.corrections_path.exists() or session.journal_path.exists())
    )


def one_line(response):
    text = response.text
    return "\n" not in text.strip() and "Traceback" not in text and len(text) < 400


# -- Host (DNS rebinding) and Origin ---------------------------------------------------


def test_a_rebinding_host_is_refused_everywhere(app):
    with client_for(app, base_url="http://evil.example:8765") as evil:
        for path in ("/", "/api/meta", "/api/points/0", "/static/app.js", "/api/suspects"):
            response = evil.get(path)
            assert response.status_code == 403 and "not this server" in response.text, path
            assert one_line(response) and str(app.state.session.outdir) not in response.text
        token = app.state.token
        response = evil.post("/api/edit", json=an_edit(app), headers={"X-Flylib-Token": token})
        assert response.status_code == 403
        with (
            pytest.raises(WebSocketDisconnect),
            evil.websocket_connect(
                "ws://evil.example:8765/ws", subprotocols=["flylib.v1", f"flylib.token.{token}"]
            ) as ws,
        ):
            ws.receive_json()
    assert nothing_changed(app)
    with client_for(app) as own:  # loopback names are served, any port (ssh -L)
        assert own.get("/api/meta").status_code == 200
        assert own.get("http://localhost:9000/api/meta").status_code == 200
        assert own.get("http://[::1]:8765/api/meta").status_code == 200


def test_another_origin_cannot_edit_save_or_open_the_websocket(app):
    token = app.state.token
    with client_for(app, Origin="http://evil.example") as evil:
        for path, body in (("/api/edit", an_edit(app)), ("/api/save", {})):
            response = evil.post(path, json=body, headers={"X-Flylib-Token": token})
            assert response.status_code == 403 and "another origin" in response.text
            assert one_line(response)
        assert evil.get("/").status_code == 403  # the page (and the token in it)
        with (
            pytest.raises(WebSocketDisconnect),
            evil.websocket_connect(
                "ws://127.0.0.1:8765/ws",
                subprotocols=["flylib.v1", f"flylib.token.{token}"],
                headers={"Origin": "http://evil.example"},
            ) as ws,
        ):
            ws.send_json(an_edit(app))
            ws.receive_json()
    with client_for(app, **{"Sec-Fetch-Site": "cross-site"}) as evil:
        assert evil.get("/api/meta").status_code == 403
    with client_for(app, Origin="null") as sandboxed:
        assert sandboxed.get("/api/meta").status_code == 403
    assert nothing_changed(app)


def test_the_text_plain_csrf_of_the_issue_is_refused(app):
    """``curl -X POST -H 'Origin: http://evil.example' -H 'Content-Type: text/plain'``."""
    body = json.dumps(an_edit(app))
    with client_for(app) as c:
        evil = c.post(
            "/api/edit",
            content=body,
            headers={"Origin": "http://evil.example", "Content-Type": "text/plain"},
        )
        assert evil.status_code == 403
        # the same body from the page's origin without the token, or with it as text/plain
        assert (
            c.post("/api/edit", content=body, headers={"Content-Type": "text/plain"}).status_code
            == 403
        )
        plain = c.post(
            "/api/edit",
            content=body,
            headers={"Content-Type": "text/plain", "X-Flylib-Token": app.state.token},
        )
        assert plain.status_code == 415 and "application/json" in plain.json()["detail"]
        form = c.post(
            "/api/save",
            content=b"a=1",
            headers={
                "Content-Type": "application/x-www-form-urlencoded",
                "X-Flylib-Token": app.state.token,
            },
        )
        assert form.status_code == 415
    assert nothing_changed(app)


def test_the_session_token_is_needed_for_every_mutation_on_localhost(app):
    token = app.state.token
    assert len(token) >= 24
    with client_for(app) as c:
        assert c.get("/api/meta").status_code == 200  # reads need no token on localhost
        for headers in ({}, {"X-Flylib-Token": "wrong"}, {"X-Flylib-Token": token[:-1]}):
            for path, body in (("/api/edit", an_edit(app)), ("/api/save", {})):
                response = c.post(path, json=body, headers=headers)
                assert response.status_code == 403 and "token" in response.json()["detail"]
        for protocols in (["flylib.v1"], ["flylib.v1", "flylib.token.wrong"]):
            with (
                pytest.raises(WebSocketDisconnect),
                c.websocket_connect("ws://127.0.0.1:8765/ws", subprotocols=protocols) as ws,
            ):
                ws.receive_json()
        assert nothing_changed(app)
        # the page carries it, in a meta element of its own HTML (no inline script)
        page = c.get("/")
        match = re.search(r'<meta name="flylib-token" content="([^"]+)">', page.text)
        assert match and match.group(1) == token
        ok = c.post("/api/edit", json=an_edit(app), headers={"X-Flylib-Token": token})
        assert ok.status_code == 200 and ok.json()["revision"] == 1
        with c.websocket_connect(
            "ws://127.0.0.1:8765/ws", subprotocols=["flylib.v1", f"flylib.token.{token}"]
        ) as ws:
            ws.send_json(an_edit(app, frame=2))
            assert ws.receive_json()["revision"] == 2


# -- what the page may run ----------------------------------------------------------


def test_every_response_carries_a_strict_csp_and_no_sniffing(app):
    with client_for(app) as c:
        for response in (
            c.get("/"),
            c.get("/static/app.js"),
            c.get("/api/meta"),
            c.get("/api/points/99"),
            c.get("/api/frame/nope/0"),
            c.post("/api/edit", json={}),  # refused: no token
        ):
            csp = response.headers["content-security-policy"]
            assert "frame-ancestors 'none'" in csp and "script-src 'self'" in csp
            assert "unsafe-inline" not in csp and "unsafe-eval" not in csp
            assert response.headers["x-content-type-options"] == "nosniff"
            assert response.headers["x-frame-options"] == "DENY"


def test_the_page_has_no_inline_script_and_builds_no_html_from_data():
    page = (STATIC / "index.html").read_text()
    scripts = re.findall(r"<script\b([^>]*)>(.*?)</script>", page, re.S)
    assert scripts and all('src="' in attrs and not body.strip() for attrs, body in scripts)
    assert not re.search(r"\son[a-z]+\s*=", page, re.I)  # no inline handlers either
    assert 'style="' not in page
    sink = re.compile(
        r"\.(innerHTML|outerHTML)\b|insertAdjacentHTML|document\.write|\beval\(|new Function\("
    )
    for path in sorted(STATIC.glob("*.js")):
        found = [line.strip() for line in path.read_text().splitlines() if sink.search(line)]
        assert not found, f"{path.name}: {found}"


def test_hostile_names_in_results_are_served_as_data_only(tmp_path):
    out = make_demo_outputs(tmp_path / "rec", frames=3)
    camera, point = rename_hostile(out)
    session = ReviewSession(out)
    try:
        with client_for(create_app(session)) as c:
            meta = c.get("/api/meta")
            assert meta.headers["content-type"] == "application/json"
            assert meta.json()["views"][0]["name"] == camera and meta.json()["points"][0] == point
            assert camera not in c.get("/").text
            # the name is a lookup key, never a path or markup; an unknown one is refused
            assert c.get(f"/api/frame/{camera}/0").status_code == 200
            assert c.get("/api/frame/%3Cscript%3E/0").status_code == 404
    finally:
        session.close()


# -- bodies ---------------------------------------------------------------------------


def test_a_deep_body_is_one_line_400_over_rest_and_websocket(app):
    deep = b"[" * 100_000 + b"]" * 100_000
    with client_for(app, **{"X-Flylib-Token": app.state.token}) as c:
        # within the size limit but deep: the depth check answers, not the parser
        nested = b'{"op": "move", "xy": ' + b"[" * 5000 + b"]" * 5000 + b"}"
        response = c.post("/api/edit", content=nested, headers={"Content-Type": "application/json"})
        assert response.status_code == 400 and "deeper than" in response.json()["detail"]
        assert one_line(response)
        response = c.post("/api/edit", content=deep, headers={"Content-Type": "application/json"})
        assert response.status_code == 413 and one_line(response)
        with c.websocket_connect(
            "ws://127.0.0.1:8765/ws", subprotocols=["flylib.v1", f"flylib.token.{app.state.token}"]
        ) as ws:
            ws.send_text(nested.decode())
            reply = ws.receive_json()
            assert reply["op"] == "refused" and "deeper than" in reply["error"]
            ws.send_text("not json")
            assert ws.receive_json()["op"] == "refused"
            ws.send_json(an_edit(app))  # the connection still works
            assert ws.receive_json()["op"] == "points"


def test_a_25_mb_body_is_refused_and_not_echoed(app):
    marker = b"ECHO-MARKER-"
    big = b'{"op": "move", "pad": "' + marker * (25_000_000 // len(marker)) + b'"}'
    with client_for(app, **{"X-Flylib-Token": app.state.token}) as c:
        response = c.post("/api/edit", content=big, headers={"Content-Type": "application/json"})
        assert response.status_code == 413 and marker not in response.content
        assert one_line(response)

        def chunks():  # no Content-Length: the stream is cut at the limit
            for _ in range(400):
                yield marker * 5000

        response = c.post(
            "/api/save", content=chunks(), headers={"Content-Type": "application/json"}
        )
        assert response.status_code == 413 and marker not in response.content
    assert nothing_changed(app)


def test_depth_and_size_limits_of_the_parser():
    assert json_depth(b'{"a": [1, {"b": "[[[[[[[[[[["}]}') == 3  # brackets in strings ignored
    assert json_depth(b'"\\"[[["') == 0
    assert parse_json(b'{"op": "move"}') == {"op": "move"}
    with pytest.raises(ValueError, match="larger than"):
        parse_json(b" " * (MAX_BODY + 1))


# -- what an edit may say -------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"frame": True}, "frame must be an integer"),
        ({"frame": 1.5}, "frame must be an integer"),
        ({"frame": "1"}, "frame must be an integer"),
        ({"frame": FRAMES}, "out of range"),
        ({"point": True}, "point must be an integer"),
        ({"point": 38}, "out of range"),
        ({"xy": [1e308, 10.0]}, "outside"),
        ({"xy": [-1.0, 10.0]}, "outside"),
        ({"xy": [10.0, 481.0]}, "outside"),
        ({"xy": [10.0]}, "two pixel coordinates"),
        ({"xy": [True, 10.0]}, "two pixel coordinates"),
        ({"xy": "10,10"}, "two pixel coordinates"),
        ({"view": "../results.h5"}, "unknown camera"),
        ({"view": 3}, "camera name"),
        ({"op": "rm -rf"}, "unknown edit"),
        ({"revision": "0"}, "revision must be an integer"),
    ],
)
def test_an_edit_out_of_bounds_is_refused_with_a_reason(app, change, words):
    with client_for(app, **{"X-Flylib-Token": app.state.token}) as c:
        response = c.post("/api/edit", json=an_edit(app, **change))
        assert response.status_code == 400 and words in response.json()["detail"]
        assert one_line(response)
    assert nothing_changed(app)


def test_non_finite_coordinates_are_refused(app):
    with client_for(app, **{"X-Flylib-Token": app.state.token}) as c:
        for token in (b"Infinity", b"-Infinity", b"NaN", b"1e400"):
            body = json.dumps(an_edit(app)).encode()
            body = re.sub(rb'"xy": \[[^\]]*\]', b'"xy": [' + token + b", 10.0]", body)
            response = c.post(
                "/api/edit", content=body, headers={"Content-Type": "application/json"}
            )
            assert response.status_code == 400 and "finite" in response.json()["detail"], token
    assert nothing_changed(app)


HUGE = "9" * 400  # a 400-digit integer: valid JSON, too large for a float or an index


@pytest.mark.parametrize(
    ("key", "value", "words"),
    [
        (
            "xy",
            f"[{HUGE}, 10.0]",
            "xy must be finite pixel coordinates, got 999999999999...(400 digits)",
        ),
        (
            "xy",
            f"[10.0, -{HUGE}]",
            "xy must be finite pixel coordinates, got -99999999999...(400 digits)",
        ),
        ("frame", HUGE, "frame 999999999999...(400 digits) is out of range"),
        ("point", f"-{HUGE}", "point -99999999999...(400 digits) is out of range"),
        ("revision", HUGE, "revision must be an integer from 0 to 2**63 - 1, got 999999999999"),
    ],
)
def test_a_huge_integer_is_a_one_line_400_not_a_500(app, key, value, words):
    """Issue 37 case 15: a 400-digit integer in an edit (REST and WebSocket) is refused
    with one line naming the field, never an OverflowError (500, a dropped socket)."""
    body = json.dumps(an_edit(app, **{key: "SLOT"})).replace('"SLOT"', value)
    with client_for(app, **{"X-Flylib-Token": app.state.token}) as c:
        response = c.post("/api/edit", content=body, headers={"Content-Type": "application/json"})
        assert response.status_code == 400, response.text
        assert words in response.json()["detail"] and one_line(response)
        with c.websocket_connect(
            "ws://127.0.0.1:8765/ws",
            subprotocols=["flylib.v1", f"flylib.token.{app.state.token}"],
            headers={"Origin": ORIGIN},
        ) as ws:
            ws.send_text(body)
            reply = ws.receive_json()
            assert reply["op"] == "refused" and words in reply["error"], reply
    assert nothing_changed(app)


def test_a_huge_number_in_a_path_or_a_save_is_one_line(app):
    with client_for(app, **{"X-Flylib-Token": app.state.token}) as c:
        view = app.state.session.view_names[0]
        for url in (f"/api/points/{HUGE}", f"/api/frame/{view}/-{HUGE}"):
            response = c.get(url)
            assert response.status_code == 404 and "(400 digits) out of range" in response.text
            assert one_line(response)
        response = c.get(f"/api/frame/{view}/1e400")
        assert response.status_code == 422 and one_line(response)
        assert response.json()["detail"].startswith("frame: Input should be a valid integer")
        response = c.post(
            "/api/save",
            content=f'{{"revision": {HUGE}}}',
            headers={"Content-Type": "application/json"},
        )
        assert response.status_code == 400 and one_line(response)
        assert "revision must be an integer" in response.json()["detail"]
    assert nothing_changed(app)


# -- a real server: the Host/Origin path through uvicorn ------------------------------


@pytest.fixture
def real_server(app):
    import uvicorn

    from flylib.gui.security import MAX_BODY as limit

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", ws_max_size=limit)
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.time() + 30
    while not server.started and time.time() < deadline:
        time.sleep(0.05)
    yield port
    server.should_exit = True
    thread.join(10)


def raw_request(port, lines):
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
            if b"\r\n\r\n" in data and (b"101 " in data.split(b"\r\n")[0] or len(data) > 200):
                break
    return data.decode("latin-1")


def handshake(port, host, origin, token):
    return raw_request(
        port,
        [
            "GET /ws HTTP/1.1",
            f"Host: {host}",
            "Upgrade: websocket",
            "Connection: Upgrade",
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
            "Sec-WebSocket-Version: 13",
            f"Sec-WebSocket-Protocol: flylib.v1, flylib.token.{token}",
            f"Origin: {origin}",
        ],
    )


def test_a_real_server_refuses_rebinding_and_foreign_websockets(app, real_server):
    port, token = real_server, app.state.token
    rebound = raw_request(
        port, ["GET /api/meta HTTP/1.1", f"Host: evil.example:{port}", "Connection: close"]
    )
    assert rebound.startswith("HTTP/1.1 403") and "results.h5" not in rebound
    own = raw_request(
        port, ["GET /api/meta HTTP/1.1", f"Host: 127.0.0.1:{port}", "Connection: close"]
    )
    assert own.startswith("HTTP/1.1 200")
    assert handshake(port, f"evil.example:{port}", f"http://evil.example:{port}", token).startswith(
        "HTTP/1.1 403"
    )
    assert handshake(port, f"127.0.0.1:{port}", "http://evil.example", token).startswith(
        "HTTP/1.1 403"
    )
    assert handshake(port, f"127.0.0.1:{port}", f"http://127.0.0.1:{port}", "wrong").startswith(
        "HTTP/1.1 403"
    )
    accepted = handshake(port, f"127.0.0.1:{port}", f"http://127.0.0.1:{port}", token)
    assert accepted.startswith("HTTP/1.1 101") and "flylib.v1" in accepted
    assert nothing_changed(app)
    assert np.isfinite(app.state.session.pts3d).any()


def test_bound_elsewhere_any_host_name_works_but_only_with_the_token(outdir):
    session = ReviewSession(outdir)
    try:
        app = create_app(session, token="s3cret", hosts=None)
        with client_for(app, base_url="http://node17.cluster:8765") as c:
            assert c.get("/api/meta").status_code == 403  # a rebinding page has no token
            assert c.get("/api/meta?token=s3cret").status_code == 200
            foreign = c.get("/api/meta?token=s3cret", headers={"Origin": "http://evil.example"})
            assert foreign.status_code == 403
    finally:
        session.close()
