"""The review page's second pass (issue 34) in headless Chromium: the focused view
takes the window, footage is found or named, a suspect item spanning frames is
corrected at once, review progress survives a restart, the overlay gets out of the way.

On a 30-frame demo recording run through the stage functions, its ``rf_claw`` displaced
in ``camera_2`` at frames 12-14 (one 3-frame suspect item); needs Debian's ``chromium``
and ``chromium-driver`` and ``selenium`` (skips with the apt command).
"""

from __future__ import annotations

import shutil
import time

import pytest

from tests.gui.test_browser import browser, wait_for

from gui_fixtures import make_demo_outputs, serving

pytestmark = pytest.mark.slow

ITEM = ("camera_2", "rf_claw", (12, 13, 14))


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    camera, point, frames = ITEM
    return make_demo_outputs(
        tmp_path_factory.mktemp("gui_review") / "rec",
        frames=30,
        displaced=[(camera, point, frames, (45.0, -35.0))],
    )


@pytest.fixture
def outdir(pristine, tmp_path):
    """A fresh copy of the recording (no corrections yet) for each test."""
    shutil.copytree(pristine.parent, tmp_path / "rec")
    return tmp_path / "rec" / "flylib_outputs"


@pytest.fixture
def page_1280(outdir):
    from flylib.gui import ReviewSession

    session = ReviewSession(outdir)
    driver = browser((1280, 720))
    try:
        with serving(session) as url:
            driver.get(url)
            wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
            yield driver, session
    finally:
        driver.quit()
        session.close()


def test_focus_on_the_selected_point_fills_the_window_at_1280x720(page_1280):
    from selenium.webdriver.common.by import By

    driver, session = page_1280
    body = driver.find_element(By.TAG_NAME, "body")
    # below 1500 px the side panel starts closed: the grid takes the whole width
    assert driver.execute_script("return document.body.classList.contains('panel-closed')")
    cells = driver.execute_script("return window.flylib.cellFill()")
    assert min(c["fill"] for c in cells) > 0.8
    body.send_keys("n")  # the top suspect item: its view large, zoomed to the point
    wait_for(driver, "return window.flylib.state.layout === 'focus' && window.flylib.allDrawn()")
    selected = driver.execute_script("return window.flylib.state.selected")
    large = driver.execute_script(
        "return document.querySelector('.view.large canvas').dataset.view"
    )
    assert large == selected["view"]
    fill = driver.execute_script("return window.flylib.focusFill()")
    assert fill >= 0.6, fill
    zoom = driver.execute_script(f"return window.flylib.state.zoom[{large!r}]")
    assert zoom["scale"] > 2
    pos = wait_for(
        driver,
        f"return window.flylib.screenPosition({large!r}, {selected['point']})",
    )
    # the point is at the centre of its view
    assert abs(pos["x"] - pos["width"] / 2) < 3 and abs(pos["y"] - pos["height"] / 2) < 3
    body.send_keys("g")  # back to the grid
    wait_for(driver, "return window.flylib.state.layout === 'grid'")
    body.send_keys("g")  # the selected point's view again
    wait_for(
        driver,
        "return window.flylib.state.layout === 'focus' && "
        f"document.querySelector('.view.large canvas').dataset.view === {large!r}",
    )
    # b opens the panel; a click on an item focuses its view
    body.send_keys("b")
    wait_for(driver, "return !document.body.classList.contains('panel-closed')")
    camera, point, frames = ITEM
    row = next(
        r
        for r in driver.find_elements(By.CSS_SELECTOR, "#suspects tbody tr")
        if r.text.startswith(f"{frames[0]}") and point in r.text
    )
    row.click()
    wait_for(
        driver,
        f"return window.flylib.state.frame >= {frames[0]} && window.flylib.state.frame <= "
        f"{frames[-1]} && window.flylib.state.selected.point === "
        f"{session.skeleton.point_names.index(point)} && "
        "document.querySelector('.view.large canvas').dataset.view === "
        "window.flylib.state.selected.view",
    )


def test_missing_footage_banner_names_what_is_missing(outdir, tmp_path):
    from selenium.webdriver.common.by import By

    from flylib.gui import ReviewSession

    empty = tmp_path / "no-videos"
    empty.mkdir()
    session = ReviewSession(outdir, footage_dir=empty)
    driver = browser((1280, 720))
    try:
        with serving(session) as url:
            driver.get(url)
            wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
            banner = driver.find_element(By.ID, "footage-banner")
            assert banner.is_displayed()
            assert banner.text == (
                f"no footage for every view: not found in --footage-dir {empty}; the points "
                "are shown without it. Start `flylib gui` with --footage-dir DIR (the folder "
                "holding the videos)"
            )
        session.close()
        session = ReviewSession(outdir)  # found where the result says: no banner
        with serving(session) as url:
            driver.get(url)
            wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
            assert not driver.find_element(By.ID, "footage-banner").is_displayed()
    finally:
        driver.quit()
        session.close()


def until(condition, timeout=30.0):
    deadline = time.time() + timeout
    while not condition():
        assert time.time() < deadline, "timed out"
        time.sleep(0.05)


def _pick_item(driver, body):
    """Open the panel and click the displaced item's row; returns (view, point index)."""
    from selenium.webdriver.common.by import By

    camera, point, frames = ITEM
    if driver.execute_script("return document.body.classList.contains('panel-closed')"):
        body.send_keys("b")
    row = next(
        r
        for r in driver.find_elements(By.CSS_SELECTOR, "#suspects tbody tr")
        if r.text.startswith(f"{frames[0]}") and point in r.text
    )
    row.click()
    selected = wait_for(driver, "return window.flylib.allDrawn() && window.flylib.state.selected")
    return selected["view"], selected["point"]


def _step_to(driver, body, frame):
    from selenium.webdriver.common.keys import Keys

    while (here := driver.execute_script("return window.flylib.state.frame")) != frame:
        body.send_keys(Keys.ARROW_RIGHT if frame > here else Keys.ARROW_LEFT)
        wait_for(driver, "return window.flylib.allDrawn()")


def test_snap_to_ghost_and_apply_to_item_over_3_frames_then_undo(page_1280):
    import numpy as np
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    driver, session = page_1280
    body = driver.find_element(By.TAG_NAME, "body")
    view, point = _pick_item(driver, body)
    v = session.view_names.index(view)
    first, middle, last = ITEM[2]
    placed = {}
    for frame in (first, last):
        _step_to(driver, body, frame)
        ghost = driver.execute_script(
            f"return window.flylib.state.data.views[{v}].reprojected[{point}]"
        )
        body.send_keys("c")  # onto its 3D ghost
        wait_for(
            driver,
            f"return !window.flylib.busy() && window.flylib.state.data.views[{v}].edited[{point}]",
        )
        np.testing.assert_allclose(session.corrections.points[v, frame, point], ghost, atol=0.01)
        placed[frame] = session.corrections.points[v, frame, point].copy()
    assert not session.corrections.edited[v, middle, point]
    body.send_keys("a")  # the middle frame interpolated, one journaled move
    applied = wait_for(driver, "return !window.flylib.busy() && window.flylib.state.applied")
    assert applied["frames"] == [middle] and applied["errors"][0] is not None
    assert session.corrections.edited[v, middle, point]
    np.testing.assert_allclose(
        session.corrections.points[v, middle, point],
        (placed[first] + placed[last]) / 2,
        atol=0.01,
    )
    status = driver.find_element(By.ID, "status").text
    assert status.startswith(f"applied to frames {first}\u2013{last} of rf_claw in {view}")

    # one undo takes the whole application back, the next the snap at the last frame
    def edited():
        return session.corrections.edited[v, [first, middle, last], point].tolist()

    ActionChains(driver).key_down(Keys.CONTROL).send_keys("z").key_up(Keys.CONTROL).perform()
    until(lambda: edited() == [True, False, True])
    wait_for(driver, "return !window.flylib.busy() && window.flylib.history().undo === 2")
    ActionChains(driver).key_down(Keys.CONTROL).send_keys("z").key_up(Keys.CONTROL).perform()
    until(lambda: edited() == [True, False, False])
    np.testing.assert_allclose(session.corrections.points[v, first, point], placed[first])


def test_reviewed_state_survives_a_restart_and_save_says_what_got_worse(outdir):
    from selenium.webdriver.common.by import By

    from flylib.corrections import Corrections
    from flylib.gui import ReviewSession

    session = ReviewSession(outdir)
    total = len(session.review_items)
    driver = browser((1280, 720))
    try:
        with serving(session) as url:
            driver.get(url)
            wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
            progress = driver.find_element(By.ID, "progress")
            assert progress.text == f"0 / {total} reviewed"
            body = driver.find_element(By.TAG_NAME, "body")
            view, point = _pick_item(driver, body)
            body.send_keys("k")  # reviewed / OK, at frames 12-14; then the next unreviewed
            wait_for(
                driver,
                f"return document.querySelector('#progress').textContent === '1 / {total} reviewed'",
            )
            assert session.corrections.reviewed[list(ITEM[2]), point].all()
            assert session.corrections.reviewed.sum() == 3
            nxt = wait_for(
                driver,
                "const s = window.flylib.state; return !window.flylib.busy() && "
                f"s.selected && (s.selected.point !== {point} || s.frame < 12 || s.frame > 14) "
                "&& [s.frame, s.selected.point]",
            )
            items = session.review()["items"]
            here = next(
                i for i, it in enumerate(items) if it["point"] == point and 12 in it["frames"]
            )
            item = next(it for it in items[here + 1 :] + items if not it["done"])
            assert nxt == [item["peak_frame"], item["point"]]
            # an edit that makes a point worse: dragged far from its 3D
            sel = driver.execute_script("return window.flylib.state.selected")
            body.send_keys("e")
            canvas = driver.find_element(By.CSS_SELECTOR, f'canvas[data-view="{sel["view"]}"]')
            pos = driver.execute_script(
                f"return window.flylib.screenPosition({sel['view']!r}, {sel['point']})"
            )
            from tests.gui.test_browser import drag

            drag(driver, canvas, pos, 60, 45)
            wait_for(driver, "return !window.flylib.busy() && window.flylib.state.data.dirty")
            body.send_keys("s")
            box = driver.find_element(By.ID, "save-check")
            wait_for(driver, "return !document.querySelector('#save-check').hidden")
            name = session.skeleton.point_names[sel["point"]]
            assert f"made worse: {name} at frame {nxt[0]}: " in box.text
            assert not (outdir / "corrections.h5").exists()
            driver.find_element(By.ID, "save-anyway").click()
            wait_for(driver, "return window.flylib.saved")
            assert box.is_displayed() is False
    finally:
        driver.quit()
        session.close()
    saved = Corrections.load(outdir / "corrections.h5")
    assert saved.reviewed.sum() == 3
    # a restart: the same progress, the item marked in the list
    session = ReviewSession(outdir)
    driver = browser((1600, 1000))
    try:
        with serving(session) as url:
            driver.get(url)
            wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
            # the reviewed item, and the dragged point's item (corrected) when it was one
            done = session.review()["done"]
            assert done == 1 + any(it["point"] == nxt[1] and nxt[0] in it["frames"] for it in items)
            text = driver.find_element(By.ID, "progress").text
            assert text == f"{done} / {total} reviewed"
            body = driver.find_element(By.TAG_NAME, "body")
            body.send_keys("u")  # the first item not yet reviewed nor corrected
            first_open = next(it for it in session.review()["items"] if not it["done"])
            wait_for(
                driver,
                f"return window.flylib.state.frame === {first_open['peak_frame']} && "
                f"window.flylib.state.selected?.point === {first_open['point']}",
            )
    finally:
        driver.quit()
        session.close()


def _pixels(driver, view):
    """The sum of a view canvas's RGB values (what it draws, as one number)."""
    return driver.execute_script(
        """const c = document.querySelector(`canvas[data-view="${arguments[0]}"]`);
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let s = 0; for (let i = 0; i < d.length; i += 4) s += d[i] + d[i + 1] + d[i + 2];
        return s;""",
        view,
    )


def test_overlay_controls_and_the_display_kept_for_the_recording(page_1280):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    driver, session = page_1280
    body = driver.find_element(By.TAG_NAME, "body")
    view = session.view_names[0]
    drawn = _pixels(driver, view)
    body.send_keys("o")  # skeleton and ghost off: less drawn over the footage
    wait_for(driver, "return window.flylib.state.display.overlay === false")
    without = _pixels(driver, view)
    assert without != drawn
    ActionChains(driver).key_down("h").perform()  # hold h: the footage alone
    wait_for(driver, "return window.flylib.state.peek")
    footage = _pixels(driver, view)
    assert footage != without
    ActionChains(driver).key_up("h").perform()
    wait_for(driver, "return !window.flylib.state.peek")
    assert _pixels(driver, view) == without
    body.send_keys("o")
    body.send_keys("l")  # every point's name
    wait_for(driver, "return window.flylib.state.display.labels")
    labelled = _pixels(driver, view)
    assert labelled != drawn
    body.send_keys("]")  # one limb: the first
    wait_for(driver, "return window.flylib.state.display.limb === 0")
    limbs = driver.execute_script("return window.flylib.state.meta.limbs")
    assert driver.find_element(By.ID, "limb").get_attribute("value") == "0"
    assert limbs[0] in driver.find_element(By.ID, "status").text
    # brightness: the footage brighter (compared in the same layout: the panel open)
    body.send_keys("b")
    wait_for(driver, "return !document.body.classList.contains('panel-closed')")
    body.send_keys("o")
    time.sleep(0.3)
    ActionChains(driver).key_down("h").perform()
    wait_for(driver, "return window.flylib.state.peek")
    footage = _pixels(driver, view)
    ActionChains(driver).key_up("h").perform()
    wait_for(driver, "return !window.flylib.state.peek")
    driver.execute_script(
        "const s = document.querySelector('#brightness'); s.value = '200';"
        "s.dispatchEvent(new Event('input'))"
    )
    wait_for(driver, "return window.flylib.state.display.brightness === 200")
    ActionChains(driver).key_down("h").perform()
    wait_for(driver, "return window.flylib.state.peek")
    assert _pixels(driver, view) > 1.3 * footage
    ActionChains(driver).key_up("h").perform()
    # kept for this recording in this browser: a reload shows the same display
    driver.refresh()
    wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
    display = driver.execute_script("return window.flylib.state.display")
    assert display == {
        "overlay": False,
        "labels": True,
        "limb": 0,
        "brightness": 200,
        "contrast": 100,
        "gamma": 1,
    }
    assert driver.find_element(By.ID, "brightness-value").text == "200%"


def test_small_items(page_1280):
    """Favicon (no console error), the View mode's own tooltip, a press on a point in
    View mode selects without panning, playback at the chosen fps, timeline labels,
    the Stop button."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    driver, session = page_1280
    body = driver.find_element(By.TAG_NAME, "body")
    view_tip = driver.find_element(By.XPATH, "//input[@id='mode-view']/..").get_attribute("title")
    edit_tip = driver.find_element(By.XPATH, "//input[@id='edit-mode']/..").get_attribute("title")
    assert view_tip != edit_tip and "nothing is edited" in view_tip
    # View mode: a drag that starts on a point selects it and leaves the view where it was
    view = session.view_names[0]
    point = driver.execute_script(
        "return window.flylib.state.data.views[0].points2d.findIndex(p => p !== null)"
    )
    pos = driver.execute_script(f"return window.flylib.screenPosition({view!r}, {point})")
    canvas = driver.find_element(By.CSS_SELECTOR, f'canvas[data-view="{view}"]')
    ActionChains(driver).move_to_element_with_offset(
        canvas, round(pos["x"] - pos["width"] / 2), round(pos["y"] - pos["height"] / 2)
    ).click_and_hold().move_by_offset(30, 20).release().perform()
    assert driver.execute_script("return window.flylib.state.selected") == {
        "view": view,
        "point": point,
    }
    assert driver.execute_script(f"return window.flylib.state.zoom[{view!r}]") == {
        "scale": 1,
        "x": 0,
        "y": 0,
    }
    assert not session.dirty
    # the timeline names frames: light label pixels along its top
    light = driver.execute_script(
        """const c = document.querySelector('#timeline');
        const d = c.getContext('2d').getImageData(0, 0, c.width, 12).data;
        let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i] > 120) n++; return n;"""
    )
    assert light > 20
    # stepping: the next frames' images and points were fetched before they are asked for
    body.send_keys(Keys.ARROW_RIGHT)
    wait_for(driver, "return window.flylib.state.frame === 1 && window.flylib.allDrawn()")
    # (fetched ahead two frames at a time: wait for the four, nobody asking for them)
    # (every view's image of a frame in one request)
    wait_for(
        driver,
        "const asked = performance.getEntriesByType('resource').map(e => new URL(e.name).pathname);"
        "return [2, 3, 4, 5].every(f => asked.includes(`/api/points/${f}`)"
        " && asked.includes(`/api/frames/${f}`))",
    )
    # playback at 20 fps to the end, where it stops: never faster than asked, and every
    # frame it shows drawn (under load it skips frames rather than slowing down)
    fps = driver.find_element(By.ID, "fps")
    fps.send_keys(Keys.CONTROL, "a")  # (clear() would leave "10" typed before the "20")
    fps.send_keys("20")
    driver.execute_script("document.activeElement.blur()")
    assert fps.get_attribute("value") == "20"
    last = session.n_frames - 1
    assert all(source.wait_filled(len(source), 60) for source in session.frames.values())
    started = time.perf_counter()
    body.send_keys(" ")
    wait_for(driver, f"return !window.flylib.state.playing && window.flylib.state.frame === {last}")
    assert time.perf_counter() - started >= (last - 2) / 20 * 0.9
    wait_for(driver, "return window.flylib.allDrawn()")
    # frames fetched at half size while playing; one of them, shown paused: at full size
    played = driver.execute_script(
        "return [...window.flylib.state.ahead.frames].filter(([f, e]) => e.small).map(([f]) => f)"
    )
    assert played, "playback fetched no frame at half size"
    driver.execute_script(f"window.flylib.goto({played[-1]})")
    wait_for(
        driver,
        f"const s = window.flylib.state; return s.frame === {played[-1]} && window.flylib.allDrawn()"
        " && s.views.every(v => s.images[v.name].bitmap.width === v.width)",
    )
    # the favicon is served: no console error at all
    errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert errors == []
    # Stop: asked, then the server ends and the page says so
    driver.find_element(By.ID, "stop-server").click()
    driver.switch_to.alert.accept()
    wait_for(driver, "return window.flylib.alert().startsWith('flylib gui has stopped')")
