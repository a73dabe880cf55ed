"""The review page's working features in headless Chromium: a layout that
fills the window, the 3D view, undo/redo, the fixed state, the leave warning, a typed
frame number and ``?frame=`` handling, thumbnails, point names on hover.

On a demo recording run through the stage functions (no Snakemake); needs Debian's
``chromium`` and ``chromium-driver`` and ``selenium`` (skips with the apt command).
Set ``FLYLIB_GUI_SCREENSHOT_DIR`` to keep the screenshots.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from tests.gui.test_browser import browser, wait_for

from gui_fixtures import make_demo_outputs, serving

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    return make_demo_outputs(tmp_path_factory.mktemp("gui_features") / "rec", frames=16)


@pytest.fixture
def page(outdir):
    from flylib.gui import ReviewSession

    session = ReviewSession(outdir)
    driver = browser()
    try:
        with serving(session) as url:
            yield driver, url, session
    finally:
        driver.quit()
        session.close()


def _shot(driver, name):
    directory = os.environ.get("FLYLIB_GUI_SCREENSHOT_DIR")
    if directory:
        driver.save_screenshot(os.path.join(directory, name))


def _canvas_spread(driver, selector):
    return driver.execute_script(
        """
        const c = document.querySelector(arguments[0]);
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let lo = 255, hi = 0;
        for (let i = 0; i < d.length; i += 4 * 61) { lo = Math.min(lo, d[i + 1]); hi = Math.max(hi, d[i + 1]); }
        return hi - lo;""",
        selector,
    )


def test_grid_fills_the_window_and_the_3d_view_takes_the_spare_cells(page):
    driver, url, session = page
    driver.get(url)
    wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
    _shot(driver, "grid.png")
    cells = driver.execute_script("return window.flylib.cellFill()")
    assert len(cells) == session.n_views
    # a 960x480 frame fills its tile (the tiles have about the frame's aspect)
    assert min(c["fill"] for c in cells) > 0.8, [round(c["fill"], 2) for c in cells]
    # no empty cell: the 3D tile ends where the rightmost view tile ends
    tile3d = wait_for(
        driver,
        "const t = window.flylib.tile3d(); return t.drawnFrame === '0' && t",
    )
    right = max(c["left"] + c["width"] for c in cells)
    assert abs(tile3d["left"] + tile3d["width"] - right) < 3
    bottom = max(c["top"] + c["height"] for c in cells)
    assert tile3d["top"] + tile3d["height"] >= bottom - 3
    # the 3D view draws the skeleton and the cameras; a drag turns it
    before = _canvas_spread(driver, ".view3d canvas")
    assert before > 40
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    canvas3d = driver.find_element(By.CSS_SELECTOR, ".view3d canvas")
    image = driver.execute_script("return document.querySelector('.view3d canvas').toDataURL()")
    ActionChains(driver).move_to_element(canvas3d).click_and_hold().move_by_offset(
        60, 20
    ).release().perform()
    turned = driver.execute_script("return document.querySelector('.view3d canvas').toDataURL()")
    assert turned != image
    # the legend names every mark and the limbs
    legend = driver.find_element(By.ID, "legend").text
    for word in ("hollow", "reprojected", "edit", "fixed", "suspect", "selected", "invisible"):
        assert word in legend


def test_focus_layout_thumbnails_stay_in_order_rendered_and_clickable(page):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    driver, url, session = page
    driver.get(url)
    wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
    body = driver.find_element(By.TAG_NAME, "body")
    body.send_keys("g")
    body.send_keys("3")
    wait_for(
        driver,
        "return document.querySelector('.view.large canvas')?.dataset.view === arguments[0]".replace(
            "arguments[0]", repr(session.view_names[2])
        ),
    )
    ScrollOrigin = pytest.importorskip("selenium.webdriver.common.actions.wheel_input").ScrollOrigin
    large = driver.find_element(By.CSS_SELECTOR, ".view.large canvas")
    ActionChains(driver).scroll_from_origin(ScrollOrigin.from_element(large), 0, -400).perform()
    wait_for(driver, f"return window.flylib.state.zoom[{session.view_names[2]!r}].scale > 1.5")
    body.send_keys("1")  # the zoomed view becomes a thumbnail
    wait_for(driver, "return document.querySelectorAll('.view.large').length === 1")
    time.sleep(0.3)
    _shot(driver, "focus.png")
    order = driver.execute_script(
        "return [...document.querySelectorAll('.view:not(.large) canvas')]"
        ".map(c => [c.dataset.view || '3d', c.getBoundingClientRect().top, "
        "c.getBoundingClientRect().left])"
    )
    # reading order (a row below the large view, or a column beside it)
    by_place = [name for name, *_ in sorted(order, key=lambda x: (round(x[1]), x[2]))]
    assert by_place == [*session.view_names[1:], "3d"]
    zoomed = f".view canvas[data-view={session.view_names[2]!r}]".replace("'", '"')
    assert _canvas_spread(driver, zoomed) > 20  # still shows footage, not black
    # a click on a thumbnail makes it the large view
    driver.find_element(By.CSS_SELECTOR, zoomed).click()
    wait_for(
        driver,
        f"return document.querySelector('.view.large canvas').dataset.view === {session.view_names[2]!r}",
    )


def test_typed_frame_and_a_bad_frame_parameter(page):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    driver, url, session = page
    driver.get(url + "?frame=abc")
    wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
    assert driver.execute_script("return window.flylib.state.frame") == 0
    assert "not a frame number" in driver.find_element(By.ID, "status").text
    # n: the top item at its worst frame, then the next in the list's order
    items = session.suspects().items()
    body = driver.find_element(By.TAG_NAME, "body")
    body.send_keys("n")
    top = items[0]
    wait_for(
        driver,
        f"return window.flylib.state.frame === {top['peak_frame']} && "
        f"window.flylib.state.selected?.point === {top['point']}",
    )
    body.send_keys("n")
    wait_for(driver, f"return window.flylib.state.selected?.point === {items[1]['point']}")
    assert driver.find_element(By.CSS_SELECTOR, "#suspects tr.current")  # follows the frame
    box = driver.find_element(By.ID, "frame-input")
    box.clear()
    box.send_keys("11", Keys.ENTER)
    wait_for(driver, "return window.flylib.state.frame === 11 && window.flylib.allDrawn()")
    driver.get(url + "?frame=999")
    wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
    assert driver.execute_script("return window.flylib.state.frame") == session.n_frames - 1


def test_undo_redo_fixed_hover_name_and_leave_warning(page):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    driver, url, session = page
    driver.get(url + "?frame=5")
    wait_for(
        driver,
        "return window.flylib && window.flylib.allDrawn() && window.flylib.state.frame === 5",
    )
    data = driver.execute_script("return window.flylib.state.data")
    v = 0
    point = next(i for i, xy in enumerate(data["views"][v]["points2d"]) if xy is not None)
    view = data["views"][v]["name"]
    pos = driver.execute_script(f"return window.flylib.screenPosition({view!r}, {point})")
    canvas = driver.find_element(By.CSS_SELECTOR, f'.view canvas[data-view="{view}"]')
    offset = (round(pos["x"] - pos["width"] / 2), round(pos["y"] - pos["height"] / 2))
    # hover: the point's name in the tooltip and drawn beside it
    ActionChains(driver).move_to_element_with_offset(canvas, *offset).perform()
    name = session.skeleton.point_names[point]
    wait_for(
        driver,
        f"return document.querySelector('.view canvas[data-view=\"{view}\"]').title.startsWith({name!r})",
    )
    leave = "const e = new Event('beforeunload', {cancelable: true}); window.dispatchEvent(e); return e.defaultPrevented;"
    assert not driver.execute_script(leave)  # nothing to lose yet

    body = driver.find_element(By.TAG_NAME, "body")
    tile_before = driver.execute_script(
        "const r = arguments[0].getBoundingClientRect(); return [r.left, r.top, r.width, r.height];",
        canvas,
    )
    body.send_keys("e")
    ActionChains(driver).move_to_element_with_offset(
        canvas, *offset
    ).click_and_hold().move_by_offset(8, 0).move_by_offset(8, 6).release().perform()
    wait_for(
        driver,
        f"return window.flylib.state.data.views[{v}].edited[{point}] && !window.flylib.busy()",
    )
    moved = driver.execute_script(f"return window.flylib.state.data.views[{v}].points2d[{point}]")
    # the tiles did not move under the mouse (the header stays one line when Save counts)
    rect = (
        "const r = arguments[0].getBoundingClientRect(); return [r.left, r.top, r.width, r.height];"
    )
    assert driver.execute_script(rect, canvas) == tile_before
    assert session.corrections.edited[v, 5, point]
    assert driver.execute_script("return window.flylib.history()") == {"undo": 1, "redo": 0}
    assert driver.execute_script(leave)  # unsaved edits: the browser asks

    # f: fixed (the robust triangulation must keep it)
    body.send_keys("f")
    wait_for(
        driver,
        f"return window.flylib.state.data.views[{v}].fixed[{point}] && !window.flylib.busy()",
    )
    assert session.corrections.fixed[v, 5, point]
    assert "fixed" in driver.find_element(By.ID, "selection").text

    # Ctrl+Z twice: not fixed, then not edited, the detection back; Ctrl+Shift+Z redoes
    body.send_keys(Keys.CONTROL, "z")
    wait_for(
        driver,
        f"return !window.flylib.state.data.views[{v}].fixed[{point}] && !window.flylib.busy()",
    )
    assert session.corrections.edited[v, 5, point] and not session.corrections.fixed[v, 5, point]
    body.send_keys(Keys.CONTROL, "z")
    wait_for(
        driver,
        f"return !window.flylib.state.data.views[{v}].edited[{point}] && !window.flylib.busy()",
    )
    assert not session.corrections.edited[v, 5, point]
    # undo is an edit like any other: journaled, and the page follows the revision
    from flylib.gui.journal import read_journal

    last = read_journal(session.journal_path).edits[-1]
    assert (last["op"], last["frame"], last["point"]) == ("reset_point", 5, point)
    assert driver.execute_script("return window.flylib.state.revision") == session.revision
    back = driver.execute_script(f"return window.flylib.state.data.views[{v}].points2d[{point}]")
    np.testing.assert_allclose(back, data["views"][v]["points2d"][point], atol=0.01)
    _shot(driver, "undo.png")
    body.send_keys(Keys.CONTROL, Keys.SHIFT, "z")
    wait_for(
        driver,
        f"return window.flylib.state.data.views[{v}].edited[{point}] && !window.flylib.busy()",
    )
    again = driver.execute_script(f"return window.flylib.state.data.views[{v}].points2d[{point}]")
    np.testing.assert_allclose(again, moved, atol=0.01)
    assert driver.execute_script("return window.flylib.history()") == {"undo": 1, "redo": 1}
    driver.find_element(By.ID, "save").click()
    # a 16 px drag the robust triangulation drops is named before saving: save it anyway
    wait_for(driver, "return window.flylib.saved || !document.querySelector('#save-check').hidden")
    if not driver.execute_script("return window.flylib.saved"):
        assert name in driver.find_element(By.ID, "save-check").text
        driver.find_element(By.ID, "save-anyway").click()
    wait_for(driver, "return window.flylib.saved")
    assert not driver.execute_script(leave)  # saved: leaving loses nothing

    # another tab's edit: undoing from this page's older view could overwrite it, so the
    # history starts again and Ctrl+Z leaves the other edit alone
    import httpx

    token = driver.execute_script(
        "return document.querySelector('meta[name=\"flylib-token\"]').content"
    )
    other = next(
        p for p, xy in enumerate(data["views"][v]["points2d"]) if xy is not None and p != point
    )
    reply = httpx.post(
        url + "api/edit",
        json={
            "op": "invisible",
            "frame": 5,
            "point": other,
            "view": view,
            "revision": session.revision,
        },
        headers={"X-Flylib-Token": token, "Origin": url.rstrip("/")},
    )
    assert reply.status_code == 200, reply.text
    wait_for(driver, f"return window.flylib.state.data.views[{v}].invisible[{other}]")
    assert driver.execute_script("return window.flylib.history()") == {"undo": 0, "redo": 0}
    body.send_keys(Keys.CONTROL, "z")
    wait_for(driver, "return document.getElementById('status').textContent === 'nothing to undo'")
    assert session.corrections.invisible[v, 5, other] and session.corrections.edited[v, 5, point]
