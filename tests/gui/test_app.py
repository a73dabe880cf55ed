"""``flylib gui``'s HTTP/WebSocket API through FastAPI's TestClient, on demo outputs.

Every edit is checked against an independent call of ``flylib.triangulation`` on the
edited 2D, and every reprojection against ``CameraGroup.project``.
"""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the GUI needs fastapi (pip install fastapi uvicorn httpx)")
pytest.importorskip("httpx", reason="FastAPI's TestClient needs httpx")

from fastapi.testclient import TestClient

from flylib.config import Config
from flylib.corrections import Corrections
from flylib.errors import ResultsError
from flylib.gui import ReviewSession, create_app
from flylib.results import Pose2dData, PoseResult
from flylib.triangulation import reconstruct

from gui_fixtures import make_demo_outputs, write_seed_sidecar

FRAMES = 12


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    return make_demo_outputs(tmp_path_factory.mktemp("gui") / "rec", frames=FRAMES)


def page_client(app, **kwargs):
    """A TestClient that talks to ``app`` as the page does: from its own origin, with
    the session token the page gets."""
    return TestClient(
        app,
        base_url="http://127.0.0.1:8765",
        headers={"X-Flylib-Token": app.state.token, "Origin": "http://127.0.0.1:8765"},
        **kwargs,
    )


def page_ws(client, token=None, **kwargs):
    """The page's WebSocket: its own origin, the token as a sub-protocol."""
    token = token or client.app.state.token
    return client.websocket_connect(
        "ws://127.0.0.1:8765/ws", subprotocols=["flylib.v1", f"flylib.token.{token}"], **kwargs
    )


def clean_sidecar(outdir):
    for name in ("corrections.h5", "corrections.h5.journal"):
        (outdir / name).unlink(missing_ok=True)


@pytest.fixture
def client(outdir):
    clean_sidecar(outdir)
    session = ReviewSession(outdir)
    with page_client(create_app(session)) as c:
        c.session = session
        yield c
    session.close()
    clean_sidecar(outdir)


def sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def visible_point(data, min_views=3):
    """A (view index, point) whose point is used in >= min_views views."""
    for p in range(len(data["points3d"])):
        used = [v for v, view in enumerate(data["views"]) if view["used"][p]]
        if len(used) >= min_views and data["points3d"][p] is not None:
            return used[0], p
    raise AssertionError("no point seen by enough views")


def expected_after(outdir, frame, point, change):
    """The 3D point and reprojections flylib.triangulation gives for the edited 2D."""
    config = Config.from_file(outdir / "config.yaml")
    result = PoseResult.load(outdir / "results.h5")
    pose2d = Pose2dData.load(outdir / "results.h5")
    pts = pose2d.pts2d[:, [frame]][:, :, [point]].copy()
    change(pts)
    conf = pose2d.conf[:, [frame]][:, :, [point]]
    pts3d, _, _ = reconstruct(result.cameras, pts, config.triangulation, conf)
    return pts3d[0, 0], result.cameras.project(pts3d[0, 0])


def test_meta_describes_views_skeleton_and_palette(client, outdir):
    meta = client.get("/api/meta").json()
    config = Config.from_file(outdir / "config.yaml")
    skeleton = config.skeleton()
    assert [v["name"] for v in meta["views"]] == config.view_names()
    assert all((v["height"], v["width"], v["footage"]) == (480, 960, True) for v in meta["views"])
    assert meta["frames"] == FRAMES and meta["points"] == list(skeleton.point_names)
    assert meta["bones"] == np.asarray(skeleton.bones).tolist()
    limbs = list(skeleton.limb_names)
    assert meta["point_colors"][0] == skeleton.limb_color(limbs[skeleton.limb_id[0]])
    assert meta["method"] == "ransac"


def test_frames_are_the_footage_frames_as_jpeg_in_any_order(client, outdir):
    from flylib.io import open_reader

    view = client.get("/api/meta").json()["views"][2]["name"]
    footage = sorted((outdir.parent).glob("*.mp4"))
    reader_path = next(
        p for p in footage if p.stem == client.session.frames[view]._frames.reader.path.stem
    )
    truth = open_reader(reader_path)[list(range(FRAMES))]  # RGB
    for frame in (7, 8, 2, 11, 3, 0):  # forward, next, back, far, ...
        response = client.get(f"/api/frame/{view}/{frame}")
        assert response.status_code == 200 and response.headers["content-type"] == "image/jpeg"
        image = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (480, 960, 3)
        diffs = [np.abs(image[..., ::-1].astype(int) - f.astype(int)).mean() for f in truth]
        assert int(np.argmin(diffs)) == frame and diffs[frame] < 3.0


def test_one_request_gives_every_view_of_a_frame_in_view_order(client):
    views = [v["name"] for v in client.get("/api/meta").json()["views"]]
    response = client.get("/api/frames/5")
    assert response.status_code == 200
    lengths = [int(n) for n in response.headers["x-lengths"].split(",")]
    assert len(lengths) == len(views) and sum(lengths) == len(response.content)
    at = np.cumsum([0, *lengths])
    for v, view in enumerate(views):  # each part is that view's own JPEG
        assert response.content[at[v] : at[v + 1]] == client.get(f"/api/frame/{view}/5").content
    assert client.get(f"/api/frames/{FRAMES}").status_code == 404


def test_points_are_the_triangulation_input_and_the_reprojected_3d(client, outdir):
    result = PoseResult.load(outdir / "results.h5")
    pose2d = Pose2dData.load(outdir / "results.h5")
    data = client.get("/api/points/4").json()
    assert data["frame"] == 4 and len(data["views"]) == len(result.cameras)
    reproj = result.cameras.project(result.pts3d[4])
    for v, view in enumerate(data["views"]):
        given = np.array([np.nan if p is None else p for p in view["points2d"]], dtype=object)
        for p, xy in enumerate(view["points2d"]):
            if xy is None:
                assert not np.isfinite(pose2d.pts2d[v, 4, p]).all()
            else:
                np.testing.assert_allclose(xy, pose2d.pts2d[v, 4, p], atol=0.01)
            assert view["used"][p] == bool(np.isfinite(result.pts2d[v, 4, p]).all())
            if view["reprojected"][p] is not None:
                np.testing.assert_allclose(view["reprojected"][p], reproj[v, p], atol=0.01)
        assert len(given) == result.n_points


def test_edit_moves_the_point_and_its_3d_and_every_reprojection(client, outdir):
    before = client.get("/api/points/5").json()
    v, p = visible_point(before)
    name = before["views"][v]["name"]
    xy = np.array(before["views"][v]["points2d"][p]) + [7.0, -5.0]
    reply = client.post(
        "/api/edit", json={"op": "move", "frame": 5, "point": p, "view": name, "xy": xy.tolist()}
    ).json()
    assert reply["views"][v]["points2d"][p] == pytest.approx(xy.tolist())
    assert reply["views"][v]["edited"][p] and reply["corrected"][p]

    def change(pts):
        pts[v, 0, 0] = xy

    want3d, want2d = expected_after(outdir, 5, p, change)
    np.testing.assert_allclose(reply["points3d"][p], want3d, atol=1e-5)
    assert np.linalg.norm(np.subtract(reply["points3d"][p], before["points3d"][p])) > 1e-4
    moved = 0
    for u, view in enumerate(reply["views"]):
        np.testing.assert_allclose(view["reprojected"][p], want2d[u], atol=0.01)
        moved += (
            np.linalg.norm(
                np.subtract(view["reprojected"][p], before["views"][u]["reprojected"][p])
            )
            > 0.05
        )
    assert moved == len(reply["views"])  # every view's ghost follows
    assert reply["solve_ms"] < 1000  # (the <= 20 ms target is measured in benchmarks/gui.py)


def test_invisible_drops_the_view_and_reset_restores_the_result(client, outdir):
    before = client.get("/api/points/3").json()
    v, p = visible_point(before)
    name = before["views"][v]["name"]
    with page_ws(client) as ws:
        ws.send_json({"op": "invisible", "frame": 3, "point": p, "view": name})
        reply = ws.receive_json()
        assert reply["op"] == "points" and reply["views"][v]["points2d"][p] is None
        assert reply["views"][v]["invisible"][p] and not reply["views"][v]["used"][p]

        def change(pts):
            pts[v, 0, 0] = np.nan

        want3d, _ = expected_after(outdir, 3, p, change)
        np.testing.assert_allclose(reply["points3d"][p], want3d, atol=1e-5)
        # placing the point again clears invisible (the seed GUI's semantics)
        ws.send_json({"op": "move", "frame": 3, "point": p, "view": name, "xy": [100.0, 100.0]})
        reply = ws.receive_json()
        assert reply["views"][v]["edited"][p] and not reply["views"][v]["invisible"][p]
        ws.send_json({"op": "reset_point", "frame": 3, "point": p, "view": name})
        reply = ws.receive_json()
        assert reply["points3d"][p] == pytest.approx(before["points3d"][p], abs=1e-6)
        assert not reply["corrected"][p]
        # reset a view and a frame
        other = (p + 1) % len(before["points3d"])
        ws.send_json({"op": "invisible", "frame": 3, "point": other, "view": name})
        ws.receive_json()
        ws.send_json({"op": "reset_view", "frame": 3, "view": name})
        assert not any(ws.receive_json()["views"][v]["invisible"])
        ws.send_json({"op": "move", "frame": 3, "point": p, "view": name, "xy": [50.0, 60.0]})
        ws.receive_json()
        ws.send_json({"op": "reset_frame", "frame": 3})
        reply = ws.receive_json()
        assert reply["edits"] == 0 and reply["points3d"] == before["points3d"]
        ws.send_json({"op": "move", "frame": 99, "point": 0, "view": name, "xy": [1, 2]})
        assert "out of range" in ws.receive_json()["error"]


def test_save_writes_the_sidecar_and_a_new_session_loads_it(client, outdir):
    results_hash = sha256(outdir / "results.h5")
    before = client.get("/api/points/6").json()
    v, p = visible_point(before)
    name = before["views"][v]["name"]
    xy = (np.array(before["views"][v]["points2d"][p]) + [4.0, 4.0]).tolist()
    edited = client.post(
        "/api/edit", json={"op": "move", "frame": 6, "point": p, "view": name, "xy": xy}
    ).json()
    u = (v + 1) % len(before["views"])
    client.post(
        "/api/edit",
        json={"op": "invisible", "frame": 2, "point": 1, "view": before["views"][u]["name"]},
    )
    saved = client.post("/api/save", json={}).json()
    assert saved["saved"] == str(outdir / "corrections.h5") and saved["edits"] == 2
    assert sha256(outdir / "results.h5") == results_hash  # never modified
    assert not list(outdir.glob(".*.tmp*"))
    corr = Corrections.load(outdir / "corrections.h5", (7, FRAMES, 38))
    assert corr.edited.sum() == 1 and corr.edited[v, 6, p]
    np.testing.assert_allclose(corr.points[v, 6, p], xy)
    assert corr.invisible.sum() == 1 and corr.invisible[u, 2, 1]
    assert not corr.fixed.any() and not corr.edited3d.any()
    client.session.close()  # one GUI per sidecar
    reopened = ReviewSession(outdir)
    again = reopened.points(6)
    assert again["views"][v]["edited"][p]
    np.testing.assert_allclose(again["points3d"][p], edited["points3d"][p], atol=1e-6)
    reopened.close()


def test_a_sidecar_in_the_seed_layout_loads(client, outdir):
    data = client.get("/api/points/1").json()
    v, p = visible_point(data)
    xy = (np.array(data["views"][v]["points2d"][p]) + [3.0, 2.0]).tolist()
    q = (p + 2) % 38
    path = write_seed_sidecar(
        outdir / "corrections.h5",
        (7, FRAMES, 38),
        version=3,
        edits2d=[(v, 1, p, *xy)],
        fixed=[(v, 1, p)],
        invisible=[(v, 2, p)],
        edits3d=[(4, q, 0.1, 0.2, 0.3)],
    )
    client.session.close()  # one GUI per sidecar
    session = ReviewSession(outdir)
    frame1 = session.points(1)
    assert frame1["views"][v]["edited"][p] and frame1["views"][v]["points2d"][p] == pytest.approx(
        xy
    )
    assert session.points(2)["views"][v]["invisible"][p]
    assert session.points(4)["points3d"][q] == pytest.approx([0.1, 0.2, 0.3])
    assert session.corrections.fixed[v, 1, p]
    session.close()
    # an older version (no invisible, no fixed) loads with those masks all False
    write_seed_sidecar(path, (7, FRAMES, 38), version=1, edits2d=[(v, 1, p, *xy)])
    old = Corrections.load(path, (7, FRAMES, 38))
    assert old.edited[v, 1, p] and not old.fixed.any() and not old.invisible.any()
    # a sidecar of another recording is one clear error
    write_seed_sidecar(path, (7, FRAMES + 1, 38))
    with pytest.raises(ResultsError, match="corrections.h5: corrects a result of"):
        ReviewSession(outdir)
    path.unlink()


def test_requests_cannot_name_files_or_leave_the_recording(client):
    assert client.get("/api/frame/..%2F..%2Fetc%2Fpasswd/0").status_code == 404
    assert client.get("/api/frame/rh/-1").status_code == 404
    assert client.get(f"/api/frame/rh/{FRAMES}").status_code == 404
    assert client.get("/api/frame/rh/abc").status_code == 422
    assert client.get("/api/points/100000").status_code == 404
    assert client.get("/static/../results.h5").status_code == 404
    bad = client.post(
        "/api/edit", json={"op": "move", "frame": 0, "point": 0, "view": "../x", "xy": [1, 2]}
    )
    assert bad.status_code == 400 and "unknown camera" in bad.json()["detail"]
    bad = client.post(
        "/api/edit", json={"op": "move", "frame": 0, "point": 0, "view": "rh", "xy": ["a"]}
    )
    assert bad.status_code == 400
    assert client.post("/api/edit", json={"op": "rm -rf", "frame": 0}).status_code == 400


def test_a_token_guards_every_route_when_set(outdir):
    from starlette.websockets import WebSocketDisconnect

    session = ReviewSession(outdir)
    with TestClient(create_app(session, token="s3cret"), base_url="http://127.0.0.1:8765") as c:
        assert c.get("/api/meta").status_code == 403
        assert c.get("/").status_code == 403
        assert c.get("/api/meta?token=wrong").status_code == 403
        assert (
            c.get("/api/meta?token=%C3%A9t%C3%A9").status_code == 403
        )  # non-ASCII: refused, no error
        assert c.get("/api/meta", headers={"X-Flylib-Token": "s3cret"}).status_code == 200
        page = c.get("/?token=s3cret")
        assert page.status_code == 200 and "flylib_token" in page.headers["set-cookie"]
        assert c.get("/static/app.js").status_code == 200  # the cookie now carries it
        c.cookies.clear()
        with pytest.raises(WebSocketDisconnect), page_ws(c, token="wrong") as ws:
            ws.receive_json()
        with page_ws(c, token="s3cret") as ws:
            ws.send_json({"op": "reset_frame", "frame": 0})
            assert ws.receive_json()["op"] == "points"
    session.close()


def test_page_and_modules_are_served_from_the_package(client):
    page = client.get("/")
    assert page.status_code == 200 and '<script type="module" src="/static/app.js">' in page.text
    for name in ("app.js", "api.js", "draw.js", "style.css"):
        response = client.get(f"/static/{name}")
        assert response.status_code == 200 and len(response.content) > 200
        assert "http://" not in response.text and "https://" not in response.text  # no CDN


def test_gui_refuses_a_directory_without_results(tmp_path):
    with pytest.raises(ResultsError, match="no results.h5 here"):
        ReviewSession(tmp_path)


def test_prefetch_fills_the_cache_without_moving_the_request_decoder(outdir):
    clean_sidecar(outdir)
    session = ReviewSession(outdir)
    source = session.frames[session.view_names[0]]
    source.jpeg(3)
    position = source._frames._next
    source.prefetch(9)
    assert source._frames._next == position  # the spare decoder did the work
    assert source._cached(9) == source.jpeg(9)
    from flylib.gui.frames import FrameSource

    fresh = FrameSource(session._find_footage()[session.view_names[0]], source.size)
    reference = fresh.jpeg(9)
    fresh.close()
    image = cv2.imdecode(np.frombuffer(source.jpeg(9), np.uint8), cv2.IMREAD_COLOR)
    again = cv2.imdecode(np.frombuffer(reference, np.uint8), cv2.IMREAD_COLOR)
    assert np.abs(image.astype(int) - again.astype(int)).max() <= 2  # the same frame
    session.close()


def test_the_sidecar_is_never_written_outside_the_outdir(outdir, tmp_path):
    data = dict(Config.from_file(outdir / "config.yaml").data)
    inside = ReviewSession(
        outdir, config=Config.from_dict({**data, "corrections": "mine/{name}.h5"})
    )
    assert inside.corrections_path == (outdir / "mine" / f"{outdir.parent.name}.h5").resolve()
    inside.close()
    elsewhere = tmp_path / "elsewhere.h5"
    clean_sidecar(outdir)
    session = ReviewSession(
        outdir, config=Config.from_dict({**data, "corrections": str(elsewhere)})
    )
    assert session.corrections_path == outdir / "corrections.h5"
    session.edit("invisible", 0, 0, session.view_names[0])
    session.save()
    assert not elsewhere.exists() and (outdir / "corrections.h5").is_file()
    session.close()
    clean_sidecar(outdir)


def test_edit_3d_moves_the_point_onto_the_dragged_pixels_ray(client, outdir):
    from flylib.camera.jax_model import closest_point_on_ray

    before = client.get("/api/points/7").json()
    v, p = visible_point(before)
    name = before["views"][v]["name"]
    target = np.array(before["views"][v]["reprojected"][p]) + [6.0, -4.0]
    reply = client.post(
        "/api/edit",
        json={"op": "move3d", "frame": 7, "point": p, "view": name, "xy": target.tolist()},
    ).json()
    cameras = client.session.cameras
    origin, direction = cameras[v].backproject_ray(target)
    want = np.asarray(closest_point_on_ray(origin, direction, before["points3d"][p]))
    np.testing.assert_allclose(reply["points3d"][p], want, atol=1e-5)
    np.testing.assert_allclose(
        reply["views"][v]["reprojected"][p], target, atol=0.02
    )  # lands there
    assert reply["corrected"][p] and not any(view["edited"][p] for view in reply["views"])
    np.testing.assert_allclose(
        [view["reprojected"][p] for view in reply["views"]],
        cameras.project(np.asarray(want)),
        atol=0.02,
    )  # every view follows
    client.post("/api/save", json={})
    corr = Corrections.load(outdir / "corrections.h5")
    assert corr.edited3d[7, p] and corr.edited3d.sum() == 1
    np.testing.assert_allclose(corr.points3d[7, p], want, atol=1e-6)  # (the reply rounds to 1e-6)
    # resetting the point in one view keeps the 3D edit; in every view removes it
    kept = client.post(
        "/api/edit", json={"op": "reset_point", "frame": 7, "point": p, "view": name}
    ).json()
    assert kept["corrected"][p]
    gone = client.post("/api/edit", json={"op": "reset_point", "frame": 7, "point": p}).json()
    assert not gone["corrected"][p] and gone["points3d"][p] == pytest.approx(
        before["points3d"][p], abs=1e-6
    )


def test_image_sequence_footage_and_missing_footage(tmp_path):
    from flylib.gui.frames import FrameSource

    files = []
    for i in range(3):
        image = np.full((48, 64, 3), 40 * (i + 1), np.uint8)  # BGR grey levels 40, 80, 120
        files.append(tmp_path / f"camera_0_img_{i}.png")
        cv2.imwrite(str(files[-1]), image)
    source = FrameSource(files, (48, 64))
    for i in (2, 0, 1):
        decoded = cv2.imdecode(np.frombuffer(source.jpeg(i), np.uint8), cv2.IMREAD_COLOR)
        assert decoded.shape == (48, 64, 3) and abs(float(decoded.mean()) - 40 * (i + 1)) < 2
    blank = FrameSource([], (30, 40))
    assert not blank.has_footage
    assert cv2.imdecode(np.frombuffer(blank.jpeg(5), np.uint8), cv2.IMREAD_COLOR).shape == (
        30,
        40,
        3,
    )


def test_stop_needs_the_token_and_a_server_that_can_stop(client):
    """POST /api/stop (the page's Stop button): refused without the page's token;
    stops only a server that handed the app a way to stop."""
    foreign = TestClient(client.app, base_url="http://127.0.0.1:8765")
    refused = foreign.post("/api/stop", json={})
    assert refused.status_code == 403
    reply = client.post("/api/stop", json={})
    assert reply.status_code == 409
    assert reply.json() == {"detail": "this server cannot be stopped from the page; press Ctrl+C"}
    stopped = []
    client.app.state.stop = lambda: stopped.append(True)
    reply = client.post("/api/stop", json={})
    assert reply.status_code == 200 and reply.json() == {"op": "stopping", "dirty": False}
    assert stopped == [True]


def test_save_check_names_an_edit_that_raised_the_error(client):
    data = client.get("/api/points/3").json()
    v, p = visible_point(data)
    assert client.get("/api/save-check").json() == {
        "worse": [],
        "new_suspects": [],
        "frames": [],
        "count": 0,
    }
    x, y = data["views"][v]["points2d"][p]
    view = data["views"][v]["name"]
    edit = {"op": "move", "frame": 3, "point": p, "view": view, "xy": [x + 80, y + 60]}
    assert client.post("/api/edit", json={**edit, "fixed": True}).status_code == 200
    check = client.get("/api/save-check").json()
    name = client.session.skeleton.point_names[p]
    assert check["count"] >= 1
    assert check["worse"][0].startswith(f"{name} at frame 3: ")
    assert " px from its 3D in " in check["worse"][0]
