"""``flylib gui`` as a command: it serves the page, prints the URL, and asks for a token
when bound to anything but localhost."""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import sys
import time

import pytest

pytest.importorskip("uvicorn", reason="the GUI needs uvicorn")
import h5py
import httpx

from flylib.gui.server import free_port, is_loopback

from gui_fixtures import make_demo_outputs


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    return make_demo_outputs(tmp_path_factory.mktemp("gui_cli") / "rec", frames=6)


def start(outdir, *args, cwd=None):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "flylib.cli",
            "gui",
            str(outdir),
            "--no-browser",
            "--port",
            "0",
            *args,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=cwd,
    )
    lines = []
    deadline = time.time() + 120
    while time.time() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        match = re.search(r"open (http://\S+)", line)
        if match:
            proc.printed = "".join(lines)  # what it said before the URL
            return proc, match.group(1)
        if proc.poll() is not None:
            break
    proc.kill()
    raise AssertionError("flylib gui printed no URL:\n" + "".join(lines))


def get(url, **kwargs):
    deadline = time.time() + 60
    while True:
        try:
            return httpx.get(url, timeout=10, **kwargs)
        except httpx.TransportError:
            if time.time() > deadline:
                raise
            time.sleep(0.2)


def test_serves_on_localhost_without_a_token(outdir):
    proc, url = start(outdir)
    try:
        assert url.startswith("http://localhost:") and "token" not in url
        port = int(url.rsplit(":", 1)[1].strip("/"))
        meta = get(f"http://127.0.0.1:{port}/api/meta")
        assert meta.status_code == 200 and meta.json()["frames"] == 6
        assert get(f"http://127.0.0.1:{port}/").status_code == 200
    finally:
        proc.terminate()
        proc.wait(20)


def test_any_other_address_needs_the_printed_token(outdir):
    proc, url = start(outdir, "--host", "0.0.0.0")
    try:
        token = re.search(r"token=([\w-]+)", url).group(1)
        assert len(token) >= 24
        port = int(re.search(r":(\d+)/", url).group(1))
        assert get(f"http://127.0.0.1:{port}/api/meta").status_code == 403
        assert get(f"http://127.0.0.1:{port}/api/meta?token={token}").status_code == 200
    finally:
        proc.terminate()
        proc.wait(20)


def test_a_missing_recording_is_one_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "flylib.cli", "gui", str(tmp_path), "--no-browser"],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0 and "no results.h5 here" in proc.stderr


def test_loopback_detection():
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert (
        not is_loopback("0.0.0.0")
        and not is_loopback("192.168.1.4")
        and not is_loopback("example.org")
    )


def test_footage_dir_from_another_directory(outdir, tmp_path):
    """Started elsewhere, the recording's videos moved: the terminal names what is
    missing and the fix; ``--footage-dir`` finds them; a wrong one is one line."""
    recording = tmp_path / "rec"
    shutil.copytree(outdir.parent, recording)
    videos = tmp_path / "videos"
    videos.mkdir()
    for video in recording.glob("*.mp4"):
        video.rename(videos / video.name)
    moved = recording / "flylib_outputs"
    # its results.h5 names the original recording (with its videos): point it here
    with h5py.File(moved / "results.h5", "a") as f:
        meta = json.loads(f.attrs["meta"])
        meta.update(recording="rec", recording_abspath=str(recording))
        f.attrs["meta"] = json.dumps(meta)
    proc, url = start(moved, cwd=tmp_path / "videos")
    try:
        assert "no footage for every view: not found in the recording directory 'rec'" in (
            proc.printed
        )
        assert "--footage-dir DIR" in proc.printed
        port = int(url.rsplit(":", 1)[1].strip("/"))
        meta = get(f"http://127.0.0.1:{port}/api/meta").json()
        assert meta["footage_missing"].startswith("no footage for every view")
    finally:
        proc.terminate()
        proc.wait(20)
    proc, url = start(moved, "--footage-dir", str(videos), cwd=tmp_path / "videos")
    try:
        assert "no footage" not in proc.printed
        port = int(url.rsplit(":", 1)[1].strip("/"))
        meta = get(f"http://127.0.0.1:{port}/api/meta").json()
        assert meta["footage_missing"] == "" and all(v["footage"] for v in meta["views"])
    finally:
        proc.terminate()
        proc.wait(20)
    wrong = subprocess.run(
        [sys.executable, "-m", "flylib.cli", "gui", str(moved), "--no-browser"]
        + ["--footage-dir", str(tmp_path / "nowhere")],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert wrong.returncode == 1 and wrong.stderr.strip().count("\n") == 0
    assert f"--footage-dir {tmp_path / 'nowhere'}: no such directory" in wrong.stderr


def test_restart_after_stop_keeps_the_port(outdir):
    """The page's Stop, then ``flylib gui`` again with the port it had: the same port, so
    the stopped page's reload finds it, though the closed connections hold it in TIME_WAIT;
    a port another server listens on is still replaced."""
    proc, url = start(outdir)
    port = int(url.rsplit(":", 1)[1].strip("/"))
    try:
        # a page's connections stay open through Stop: the server closes them (TIME_WAIT)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as page:
            get(f"http://127.0.0.1:{port}/api/meta")
            html = page.get("/").text
            token = re.search(r'name="flylib-token" content="([^"]+)"', html).group(1)
            stop = page.post("/api/stop", json={}, headers={"X-Flylib-Token": token})
            assert stop.status_code == 200
            proc.wait(30)
    finally:
        proc.kill()
    proc, url = start(outdir, "--port", str(port))
    try:
        assert url == f"http://localhost:{port}/"
        with socket.socket() as busy:  # listening as uvicorn does
            busy.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            busy.bind(("127.0.0.1", 0))
            busy.listen()
            taken = busy.getsockname()[1]
            assert free_port("127.0.0.1", taken) != taken
    finally:
        proc.terminate()
        proc.wait(20)


def test_footage_of_another_recording_is_refused(outdir, tmp_path):
    """``--footage-dir`` at another recording's videos (more frames than the result, or
    another image size): the terminal and the page's banner name both, and the views
    stay dark instead of showing someone else's fly as this recording's (issue 47)."""
    import cv2
    import numpy as np

    from flylib.io import VideoWriter

    longer = make_demo_outputs(tmp_path / "longer", frames=20).parent
    smaller = tmp_path / "smaller"
    smaller.mkdir()
    for video in outdir.parent.glob("*.mp4"):  # this recording's frame count, half the size
        with VideoWriter(smaller / video.name, fps=10) as writer:
            for _ in range(6):
                writer.write_frame(np.full((240, 480, 3), 200, np.uint8))
    for videos, said in [(longer, "20 frames of 960x480"), (smaller, "6 frames of 480x240")]:
        proc, url = start(outdir, "--footage-dir", str(videos))
        try:
            line = next(s for s in proc.printed.splitlines() if "does not match" in s)
            assert f"footage in {videos} does not match" in line and said in line, line
            assert "6 frames of 960x480" in line and "--footage-dir" in line, line
            port = int(url.rsplit(":", 1)[1].strip("/"))
            meta = get(f"http://127.0.0.1:{port}/api/meta").json()
            assert said in meta["footage_missing"] and not any(v["footage"] for v in meta["views"])
            view = meta["views"][0]["name"]
            jpeg = get(f"http://127.0.0.1:{port}/api/frame/{view}/3").content
            image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
            assert image.shape[:2] == (480, 960) and image.max() < 40  # the dark placeholder
        finally:
            proc.terminate()
            proc.wait(20)


def page(url):
    """GET-as-JSON and POST (with the page's token) against the server at ``url``."""
    base = url.rstrip("/")
    token = re.search(r'name="flylib-token" content="([^"]+)"', get(base + "/").text)[1]
    post = lambda path, body: httpx.post(  # noqa: E731
        base + path, json=body, headers={"X-Flylib-Token": token}, timeout=60
    )
    return (lambda path: get(base + path).json()), post


def test_counts_and_notices_describe_the_state_now(outdir, tmp_path):
    """Issue 47: after Save the replayed journal's "press Save" is gone (on reload too),
    Save's count and the Ctrl+C line count the edits since the last save, not all of them,
    and a results.h5 a re-run rewrote is noticed and read again on request."""
    import signal

    from flylib.results import PoseResult

    shutil.copytree(outdir.parent, tmp_path / "rec")
    out = tmp_path / "rec" / "flylib_outputs"

    def move(post, frame, dx):
        view = get_json("/api/meta")["views"][0]["name"]
        data = get_json(f"/api/points/{frame}")
        p = next(i for i, xy in enumerate(data["views"][0]["points2d"]) if xy)
        xy = [data["views"][0]["points2d"][p][0] + dx, data["views"][0]["points2d"][p][1]]
        reply = post(
            "/api/edit", {"op": "move", "frame": frame, "point": p, "view": view, "xy": xy}
        )
        assert reply.status_code == 200, reply.text

    proc, url = start(out)
    try:
        get_json, post = page(url)
        move(post, 1, 3.0)
        assert post("/api/stop", {}).status_code == 200
        proc.wait(30)
    finally:
        proc.kill()
    proc, url = start(out)
    try:
        assert "1 unsaved edit(s) replayed" in proc.printed
        get_json, post = page(url)
        assert "press Save" in get_json("/api/meta")["notice"]
        assert post("/api/save", {}).status_code == 200
        assert get_json("/api/meta")["notice"] == ""  # what a reloaded page is told
        move(post, 2, 4.0)
        data = get_json("/api/points/2")
        assert (data["edits"], data["unsaved"]) == (2, 1)
        # a re-run rewrites results.h5: the page is told, and a reload reads the new 3D
        assert get_json("/api/meta")["results_changed"] is False
        result = PoseResult.load(out / "results.h5")
        result.pts3d[3] += 0.01
        result.save(out / "results.h5")
        assert get_json("/api/meta")["results_changed"] is True
        before = get_json("/api/points/3")["points3d"]
        assert post("/api/reload", {}).status_code == 200
        assert get_json("/api/meta")["results_changed"] is False
        assert get_json("/api/points/3")["points3d"] != before
        data = get_json("/api/points/2")  # the unsaved edit replayed onto the new result
        assert (data["edits"], data["unsaved"]) == (2, 1)
        proc.send_signal(signal.SIGINT)
        said = proc.communicate(timeout=30)[0]
    finally:
        proc.kill()
    assert "flylib gui: 1 edit(s) not saved to" in said, said


def test_an_edit_says_at_once_what_it_made_worse(outdir, tmp_path):
    """Issue 47: an edit's reply says which other view's error it raised (before and after,
    a drag compared with the state before it) and how far from its 3D an edit lies that the
    robust triangulation dropped; Save's check lists the dropped edit with its frame."""
    shutil.copytree(outdir.parent, tmp_path / "rec")
    proc, url = start(tmp_path / "rec" / "flylib_outputs")
    try:
        get_json, post = page(url)
        point = get_json("/api/meta")["points"].index("lf_tibia_tarsus")
        views = get_json("/api/points/3")["views"]
        lm = next(i for i, v in enumerate(views) if v["name"] == "lm")
        x, y = views[lm]["points2d"][point]

        def move(dx, durable=True):
            edit = {"op": "move", "frame": 3, "point": point, "view": "lm", "xy": [x + dx, y]}
            reply = post("/api/edit", {**edit, "durable": durable})
            assert reply.status_code == 200, reply.text
            return reply.json()

        move(4.0, durable=False)  # a drag: its steps, then its end
        reply = move(10.0)
        rose = {r["view"]: (r["before"], r["after"]) for r in reply["consequence"]["rose"]}
        assert rose and "lm" not in rose and reply["consequence"]["dropped"] is None
        for view, (before, after) in rose.items():
            i = next(i for i, v in enumerate(views) if v["name"] == view)
            assert before == round(views[i]["error"][point], 1)
            assert after == round(reply["views"][i]["error"][point], 1) > before + 2
        reply = move(400.0)
        assert reply["views"][lm]["used"][point] is False
        assert 390 < reply["consequence"]["dropped"] < 410
        check = get_json("/api/save-check")
        said = "lf_tibia_tarsus at frame 3: the edit in lm is dropped by the robust triangulation"
        assert check["count"] == 1 and check["frames"] == [3]
        assert check["worse"][0].startswith(said), check
    finally:
        proc.terminate()
        proc.wait(20)
