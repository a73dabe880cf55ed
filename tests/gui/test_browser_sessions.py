"""``flylib gui`` in headless Chromium when things go wrong: the server stops
in the middle of editing, two tabs edit the same recording, a results.h5 carries
script in its names.

Needs Debian's ``chromium`` and ``chromium-driver`` and the ``selenium`` package;
skips with the reason otherwise (see tests/gui/test_browser.py).
"""

from __future__ import annotations

import socket
import threading
import time

import pytest

from flylib.gui.journal import read_journal
from tests.gui.test_browser import browser, drag, wait_for

from gui_fixtures import make_demo_outputs, rename_hostile

pytestmark = pytest.mark.slow
pytest.importorskip("uvicorn", reason="the GUI needs uvicorn")


class Server:
    """``flylib gui``'s app under uvicorn in a thread, stoppable and restartable."""

    def __init__(self, outdir, port=None):
        import uvicorn

        from flylib.gui import ReviewSession, create_app

        if port is None:
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", 0))
                port = sock.getsockname()[1]
        self.port = port
        self.session = ReviewSession(outdir)
        self.server = uvicorn.Server(
            uvicorn.Config(
                create_app(self.session), host="127.0.0.1", port=port, log_level="warning"
            )
        )
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.time() + 30
        while not self.server.started and time.time() < deadline:
            time.sleep(0.05)
        self.url = f"http://127.0.0.1:{port}/"

    def stop(self):
        self.server.should_exit = True
        self.thread.join(20)
        self.session.close()


@pytest.fixture
def outdir(tmp_path):
    return make_demo_outputs(tmp_path / "rec", frames=8)


def open_page(driver, url):
    driver.get(url)
    wait_for(driver, "return window.flylib && window.flylib.allDrawn()")


def drag_a_point(driver, dx=18, dy=12):
    """Edit 2D on, drag the first drawn point of the first view; returns (view, point)."""
    from selenium.webdriver.common.by import By

    data = driver.execute_script("return window.flylib.state.data")
    view = data["views"][0]["name"]
    point = next(i for i, xy in enumerate(data["views"][0]["points2d"]) if xy is not None)
    pos = driver.execute_script(f"return window.flylib.screenPosition({view!r}, {point})")
    canvas = driver.find_elements(By.CSS_SELECTOR, ".view canvas")[0]
    if not driver.execute_script("return window.flylib.state.editMode"):
        driver.find_element(By.TAG_NAME, "body").send_keys("e")
    drag(driver, canvas, pos, dx, dy)
    return view, point


def test_a_stopped_server_mid_edit_loses_nothing_and_the_page_says_so(outdir):
    server = Server(outdir)
    driver = browser()
    try:
        open_page(driver, server.url)
        view, point = drag_a_point(driver)
        wait_for(
            driver,
            f"return window.flylib.state.data.views[0].edited[{point}] && !window.flylib.busy()",
        )
        shown = driver.execute_script(f"return window.flylib.state.data.views[0].points2d[{point}]")
        server.stop()  # Ctrl+C, a crash: the edit was never saved
        wait_for(driver, "return document.body.classList.contains('offline')")
        alert = driver.execute_script("return window.flylib.alert()")
        assert "flylib gui has stopped" in alert and "journaled" in alert
        # the page no longer takes edits it cannot store
        driver.find_element("tag name", "body").send_keys("e")
        assert not driver.execute_script("return window.flylib.state.editMode")
        journal = read_journal(outdir / "corrections.h5.journal")
        last = [e for e in journal.edits if e["point"] == point][-1]
        assert last["view"] == view and last["xy"] == pytest.approx(shown, abs=0.01)
        assert not (outdir / "corrections.h5").exists()
        # flylib gui runs again: the page reloads and shows the replayed edit
        server = Server(outdir, port=server.port)
        wait_for(
            driver,
            "return window.flylib && window.flylib.state.data && "
            f"window.flylib.state.data.views[0].edited[{point}] && window.flylib.allDrawn()",
            timeout=60,
        )
        assert "replayed" in driver.execute_script("return window.flylib.alert()")
        again = driver.execute_script(f"return window.flylib.state.data.views[0].points2d[{point}]")
        assert again == pytest.approx(shown, abs=0.01)
    finally:
        driver.quit()
        server.stop()


def test_two_tabs_follow_each_other_and_a_stale_one_is_refused(outdir):
    from selenium.webdriver.common.by import By

    server = Server(outdir)
    driver = browser()
    try:
        open_page(driver, server.url)
        tab_a = driver.current_window_handle
        driver.switch_to.new_window("tab")
        open_page(driver, server.url)
        tab_b = driver.current_window_handle

        driver.switch_to.window(tab_a)
        _, point = drag_a_point(driver)
        wait_for(
            driver,
            f"return window.flylib.state.data.views[0].edited[{point}] && !window.flylib.busy()",
        )
        revision = driver.execute_script("return window.flylib.state.revision")
        assert revision == server.session.revision >= 1

        driver.switch_to.window(tab_b)  # B was told and shows A's edit
        wait_for(
            driver,
            f"return window.flylib.state.revision === {revision} && "
            f"window.flylib.state.data.views[0].edited[{point}]",
        )
        # a B that missed the news (its revision behind) is refused, told and refreshed
        driver.execute_script("window.flylib.state.revision = 0")
        driver.find_element(By.TAG_NAME, "body").send_keys("x")  # reset frame
        wait_for(
            driver,
            "return document.querySelector('#status').textContent.includes('not applied') && "
            f"window.flylib.state.revision === {revision}",
        )
        assert server.session.corrections.edited[0, 0, point]  # A's edit survived
        # an up-to-date B resets the frame; A follows
        driver.find_element(By.TAG_NAME, "body").send_keys("x")
        wait_for(driver, f"return !window.flylib.state.data.views[0].edited[{point}]")
        driver.switch_to.window(tab_a)
        wait_for(
            driver,
            f"return window.flylib.state.revision === {revision + 1} && "
            f"!window.flylib.state.data.views[0].edited[{point}]",
        )
        driver.find_element(By.ID, "save").click()
        saved = wait_for(driver, "return window.flylib.saved")
        assert saved["edits"] == 0 and saved["revision"] == revision + 1
    finally:
        driver.quit()
        server.stop()


def test_names_carrying_html_render_as_text(outdir):
    camera, _ = rename_hostile(outdir)
    server = Server(outdir)
    driver = browser()
    try:
        open_page(driver, server.url)
        label = driver.execute_script("return document.querySelector('.view .label').textContent")
        assert label == f"1 {camera}"
        assert driver.execute_script("return document.querySelectorAll('img').length") == 0
        assert driver.execute_script("return window.flylibPwned") is None
    finally:
        driver.quit()
        server.stop()
