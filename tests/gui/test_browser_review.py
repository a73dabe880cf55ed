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
    large = driver.execute_script("return document.querySelector('.view.large canvas').dataset.view")
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
    selected = wait_for(
        driver, "return window.flylib.allDrawn() && window.flylib.state.selected"
    )
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
