"""``flylib gui`` never loses an edit: the journal, revisions, one GUI per
sidecar, save errors.

A real ``flylib gui`` killed with SIGKILL after a few edits comes back with them; a
journal cut short or tampered with replays what it can and says what it skipped; a
stale page is refused and told; a second server on the same output directory is
refused; a save that cannot be written says why and keeps the edits.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import resource
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the GUI needs fastapi (pip install fastapi uvicorn httpx)")
import httpx
from fastapi.testclient import TestClient

from flylib.config import Config
from flylib.corrections import Corrections
from flylib.errors import OutputError
from flylib.gui import ReviewSession, create_app
from flylib.gui.journal import read_journal
from tests.gui.test_server import start

from gui_fixtures import make_demo_outputs

FRAMES = 6
ORIGIN = "http://127.0.0.1:8765"


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    return make_demo_outputs(tmp_path_factory.mktemp("gui_journal") / "rec", frames=FRAMES)


@pytest.fixture(autouse=True)
def no_sidecar(outdir):
    def clean():
        for name in ("corrections.h5", "corrections.h5.journal"):
            path = outdir / name
            if path.is_dir():
                path.rmdir()
            path.unlink(missing_ok=True)

    clean()
    yield
    clean()


def page(app):
    return TestClient(
        app, base_url=ORIGIN, headers={"X-Flylib-Token": app.state.token, "Origin": ORIGIN}
    )


def move(session, frame=1, point=3, dx=0.0, view=0):
    name = session.view_names[view]
    height, width = session.image_sizes[name]
    return {
        "op": "move",
        "frame": frame,
        "point": point,
        "view": name,
        "xy": [width / 2 + dx, height / 2],
    }


# -- a real server killed mid-session ---------------------------------------------------


def start_gui(outdir):
    """``flylib gui`` in a subprocess: it, its port and what it printed."""
    proc, url = start(outdir)
    return proc, int(re.search(r":(\d+)/", url).group(1)), proc.printed


def page_token(base):
    deadline = time.time() + 60
    while True:
        try:
            html = httpx.get(base + "/", timeout=10).text
            return re.search(r'name="flylib-token" content="([^"]+)"', html).group(1)
        except httpx.TransportError:
            if time.time() > deadline:
                raise
            time.sleep(0.2)


def test_edits_survive_kill_9_and_are_replayed_with_a_notice(outdir):
    proc, port, _ = start_gui(outdir)
    base = f"http://127.0.0.1:{port}"
    try:
        headers = {"X-Flylib-Token": page_token(base), "Origin": base}
        meta = httpx.get(base + "/api/meta").json()
        view, other = meta["views"][0]["name"], meta["views"][1]["name"]
        shown = []
        for body in (
            {"op": "move", "frame": 1, "point": 3, "view": view, "xy": [400.5, 200.25]},
            {"op": "move3d", "frame": 2, "point": 5, "view": view, "xy": [420.0, 210.0]},
            {"op": "invisible", "frame": 4, "point": 7, "view": other},
        ):
            reply = httpx.post(base + "/api/edit", json=body, headers=headers, timeout=30)
            assert reply.status_code == 200, reply.text
            shown.append(reply.json())
        assert shown[-1]["revision"] == 3 and shown[-1]["dirty"]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(20)
    assert not (outdir / "corrections.h5").exists()
    assert len(read_journal(outdir / "corrections.h5.journal").edits) == 3

    proc, port, printed = start_gui(outdir)
    base = f"http://127.0.0.1:{port}"
    try:
        assert "3 unsaved edit(s) replayed from" in printed
        headers = {"X-Flylib-Token": page_token(base), "Origin": base}
        meta = httpx.get(base + "/api/meta").json()
        assert meta["revision"] == 3 and meta["dirty"] and "replayed" in meta["notice"]
        frame1 = httpx.get(base + "/api/points/1").json()
        assert frame1["views"][0]["edited"][3]
        assert frame1["views"][0]["points2d"][3] == pytest.approx([400.5, 200.25])
        assert frame1["points3d"][3] == pytest.approx(shown[0]["points3d"][3], abs=1e-6)
        frame2 = httpx.get(base + "/api/points/2").json()
        assert frame2["corrected"][5]
        assert frame2["points3d"][5] == pytest.approx(shown[1]["points3d"][5], abs=1e-6)
        assert httpx.get(base + "/api/points/4").json()["views"][1]["invisible"][7]
        saved = httpx.post(base + "/api/save", json={"revision": 3}, headers=headers)
        assert saved.status_code == 200 and saved.json()["edits"] == 3
    finally:
        proc.terminate()
        proc.wait(20)
    assert not (outdir / "corrections.h5.journal").exists()
    corr = Corrections.load(outdir / "corrections.h5", (7, FRAMES, 38))
    assert corr.edited[0, 1, 3] and corr.edited3d[2, 5] and corr.invisible[1, 4, 7]
    assert corr.revision == 3


def test_a_journal_cut_short_or_tampered_replays_what_it_can(outdir):
    session = ReviewSession(outdir)
    for dx in (0.0, 5.0):
        session.edit(**move(session, dx=dx))
    session.edit(**move(session, frame=3, point=2))
    session.close()
    journal = outdir / "corrections.h5.journal"
    lines = journal.read_bytes().splitlines(keepends=True)
    assert len(lines) == 4  # the header and three edits
    # line 3 (the second edit) tampered with, and a last line cut short by a crash
    tampered = lines[2].replace(b'"frame":1', b'"frame":2')
    journal.write_bytes(lines[0] + lines[1] + tampered + lines[3] + lines[3][:30])
    session = ReviewSession(outdir)
    try:
        assert "2 unsaved edit(s) replayed" in session.notice
        assert "damaged journal line(s) skipped: [3, 5]" in session.notice
        assert session.corrections.edited[0, 1, 3] and session.corrections.edited[0, 3, 2]
        x = session.corrections.points[0, 1, 3, 0]
        assert x == pytest.approx(session.image_sizes[session.view_names[0]][1] / 2)  # dx=0
        assert not session.corrections.edited[:, 2].any()
    finally:
        session.close()


def test_a_journal_line_with_a_valid_checksum_is_still_checked(outdir):
    from flylib.gui.journal import EditJournal

    session = ReviewSession(outdir)
    good = move(session, frame=2)
    session.close()
    journal = EditJournal(outdir / "corrections.h5")
    for record in (
        {**good, "xy": [1e308, 5.0]},
        {**good, "frame": True},
        {"op": "set3d", "frame": 1, "point": 0, "view": None, "xyz": [float("inf"), 0, 0]},
        {"op": "__import__('os').system('false')", "frame": 0},
        good,
    ):
        journal.append(record, 0)
    journal.close()
    session = ReviewSession(outdir)
    try:
        assert "1 unsaved edit(s) replayed" in session.notice
        assert "4 edit(s) refused: xy [1e+308, 5] lies outside" in session.notice
        assert session.corrections.count() == 1 and session.corrections.edited[0, 2, 3]
        assert np.isfinite(session.corrections.points).sum() == 2
    finally:
        session.close()


def test_fixed_is_checked_journaled_revisioned_and_replayed(outdir):
    """The ``fixed`` state (f) goes the way of every edit: a boolean or refused, only on
    ``move``, against the page's revision, journaled, and replayed after a crash."""
    session = ReviewSession(outdir)
    app = create_app(session)
    journal = outdir / "corrections.h5.journal"
    try:
        with page(app) as c:
            for bad, says in (
                ({**move(session), "fixed": "yes"}, "fixed must be true or false"),
                ({**move(session), "fixed": 1}, "fixed must be true or false"),
                (
                    {
                        "op": "invisible",
                        "frame": 1,
                        "point": 3,
                        "view": session.view_names[0],
                        "fixed": True,
                    },
                    "fixed applies to move",
                ),
            ):
                response = c.post("/api/edit", json={**bad, "revision": 0})
                assert response.status_code == 400 and says in response.json()["detail"]
            assert not journal.exists() and session.revision == 0
            assert not session.corrections.fixed.any()
            response = c.post("/api/edit", json={**move(session), "fixed": True, "revision": 0})
            assert response.status_code == 200 and response.json()["revision"] == 1
            assert response.json()["views"][0]["fixed"][3]
            # a stale page cannot unfix it
            response = c.post("/api/edit", json={**move(session), "fixed": False, "revision": 0})
            assert response.status_code == 409
        assert session.corrections.fixed[0, 1, 3]
        assert read_journal(journal).edits[-1]["fixed"] is True
    finally:
        session.close()  # a crash before saving: the journal holds the edit
    # a journal line claiming a non-boolean fixed (valid checksum) is refused on replay
    from flylib.gui.journal import EditJournal

    appended = EditJournal(outdir / "corrections.h5")
    appended.append({**move(session, frame=2), "fixed": "true"}, 0)
    appended.close()
    session = ReviewSession(outdir)
    try:
        assert "1 unsaved edit(s) replayed" in session.notice
        assert "1 edit(s) refused: fixed must be true or false" in session.notice
        assert session.corrections.fixed[0, 1, 3] and session.corrections.edited[0, 1, 3]
        assert not session.corrections.edited[:, 2].any()
        session.save()
    finally:
        session.close()
    assert Corrections.load(outdir / "corrections.h5", (7, FRAMES, 38)).fixed[0, 1, 3]


# -- one revision per session: two tabs ------------------------------------------------


def test_a_stale_tab_is_refused_and_told_and_the_other_tab_is_notified(outdir):
    session = ReviewSession(outdir)
    app = create_app(session)
    try:
        with page(app) as c:
            subprotocols = ["flylib.v1", f"flylib.token.{app.state.token}"]
            with (
                c.websocket_connect(
                    f"{ORIGIN.replace('http', 'ws')}/ws", subprotocols=subprotocols
                ) as tab_a,
                c.websocket_connect(
                    f"{ORIGIN.replace('http', 'ws')}/ws", subprotocols=subprotocols
                ) as tab_b,
            ):
                tab_a.send_json({**move(session), "revision": 0})
                reply = tab_a.receive_json()
                assert reply["op"] == "points" and reply["revision"] == 1
                # A's next edit sent before that reply (keys typed ahead): only A edited since
                tab_a.send_json({**move(session, dx=1.0), "revision": 0})
                assert tab_a.receive_json()["revision"] == 2
                # tab B hears of them ...
                assert tab_b.receive_json() == {"op": "changed", "revision": 1, "frame": 1}
                assert tab_b.receive_json() == {"op": "changed", "revision": 2, "frame": 1}
                # ... and an edit B sends from what it showed before is refused, not applied
                tab_b.send_json({"op": "reset_frame", "frame": 1, "revision": 0})
                stale = tab_b.receive_json()
                assert stale["op"] == "stale" and stale["revision"] == 2
                assert "another tab" in stale["error"]
                assert session.corrections.edited[0, 1, 3]  # A's edit is still there
                # a save from the stale page is refused too; from the current one it works
                tab_b.send_json({"op": "save", "revision": 0})
                assert tab_b.receive_json()["op"] == "stale"
                assert not session.corrections_path.exists()
            response = c.post("/api/edit", json={**move(session, dx=3.0), "revision": 0})
            assert response.status_code == 409 and "revision 0, now 2" in response.json()["detail"]
            response = c.post("/api/save", json={"revision": 2})
            assert response.status_code == 200 and response.json()["revision"] == 2
    finally:
        session.close()


def test_a_second_server_on_the_same_outdir_is_refused(outdir):
    first = ReviewSession(outdir)
    try:
        with pytest.raises(OutputError, match=rf"another flylib gui \(pid {os.getpid()} on "):
            ReviewSession(outdir)
        proc = subprocess.run(
            [sys.executable, "-m", "flylib.cli", "gui", str(outdir), "--no-browser", "--port", "0"],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert proc.returncode == 1 and proc.stderr.strip().count("\n") == 0
        assert f"another flylib gui (pid {os.getpid()}" in proc.stderr
    finally:
        first.close()
    ReviewSession(outdir).close()  # free again once the first one stopped


# -- save errors -------------------------------------------------------------------------


def test_a_save_that_cannot_be_written_says_why_and_keeps_the_edits(outdir):
    session = ReviewSession(outdir)
    app = create_app(session)
    try:
        with page(app) as c:
            assert c.post("/api/edit", json=move(session)).status_code == 200
            (outdir / "corrections.h5").mkdir()  # the save cannot replace it
            response = c.post("/api/save", json={"revision": 1})
            assert response.status_code == 507
            detail = response.json()["detail"]
            assert (
                "corrections.h5: cannot be written (is a directory)" in detail
                and "journal" in detail
            )
            assert "\n" not in detail
            assert session.dirty and session.corrections.edited[0, 1, 3]
            assert len(read_journal(session.journal_path).edits) == 1
            (outdir / "corrections.h5").rmdir()
            assert c.post("/api/save", json={"revision": 1}).status_code == 200
    finally:
        session.close()


def test_a_full_disk_refuses_the_edit_or_the_save_with_the_reason(outdir):
    # in a child process: libhdf5 keeps the half-created file of the failed save in its
    # own state, which crashed a later test's h5py close in the same process
    child = multiprocessing.get_context("spawn").Process(target=_full_disk_case, args=(outdir,))
    child.start()
    child.join(300)
    assert child.exitcode == 0, f"the full-disk case failed in its process ({child.exitcode})"


def _full_disk_case(outdir):
    warnings.simplefilter("ignore")  # the failed save's unraisable h5py cleanup
    session = ReviewSession(outdir)
    app = create_app(session)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    try:
        with page(app) as c:
            assert c.post("/api/edit", json=move(session)).status_code == 200
            size = session.journal_path.stat().st_size
            resource.setrlimit(resource.RLIMIT_FSIZE, (size + 10, old_limit[1]))
            response = c.post("/api/edit", json={**move(session, frame=2), "revision": 1})
            assert response.status_code == 507
            assert "cannot store the edit" in response.json()["detail"]
            assert "it was not applied" in response.json()["detail"]
            assert not session.corrections.edited[:, 2].any() and session.revision == 1
            response = c.post("/api/save", json={"revision": 1})
            assert response.status_code == 507 and "corrections.h5" in response.json()["detail"]
            resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
            assert not session.corrections_path.exists()
            assert c.post("/api/save", json={"revision": 1}).status_code == 200
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
        signal.signal(signal.SIGXFSZ, old_handler)
        session.close()


def test_an_unwritable_directory_refuses_each_edit_with_the_reason(outdir):
    data = dict(Config.from_file(outdir / "config.yaml").data)
    blocker = outdir / "blocked"
    blocker.write_text("a file where the sidecar's directory should be")
    session = ReviewSession(
        outdir, config=Config.from_dict({**data, "corrections": "blocked/corrections.h5"})
    )
    try:
        with page(create_app(session)) as c:
            response = c.post("/api/edit", json=move(session))
            assert response.status_code == 507
            detail = response.json()["detail"]
            assert "corrections.h5.journal: cannot store the edit" in detail
            assert session.corrections.count() == 0 and not session.dirty
            assert json.loads(c.get("/api/points/1").text)["views"][0]["edited"][3] is False
    finally:
        session.close()
        blocker.unlink()


def test_drag_steps_are_flushed_and_the_last_one_fsynced(outdir, monkeypatch):
    session = ReviewSession(outdir)
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    try:
        session.edit(**move(session, dx=1.0), durable=False)
        after_header = len(synced)  # the new journal's header and directory entry
        session.edit(**move(session, dx=2.0), durable=False)
        assert len(synced) == after_header
        # flushed: another reader sees both positions at once (what kill -9 leaves)
        assert len(read_journal(session.journal_path).edits) == 2
        session.edit(**move(session, dx=3.0))
        assert len(synced) == after_header + 1
    finally:
        session.close()
