"""Issue 47: each edit says at once what it made worse, in headless Chromium. A drag that
raises another view's error names the view and both numbers, one the robust triangulation
drops says how far it lies from its 3D; Ctrl+Z takes either back and the line goes; a line
of Save's check goes to its frame. Needs Debian's ``chromium`` and ``chromium-driver``."""

from __future__ import annotations

import re

import pytest

from tests.gui.test_browser import drag, opened, wait_for

from gui_fixtures import make_demo_outputs

pytestmark = pytest.mark.slow

POINT, VIEW, FRAME = "lf_tibia_tarsus", "lm", 3
IDLE = "return !window.flylib.busy() && !window.flylib.state.dragging"
SAID = IDLE + " && document.querySelector('#consequence:not([hidden])')?.textContent"


@pytest.fixture
def page(tmp_path):
    from flylib.gui import ReviewSession

    session = ReviewSession(make_demo_outputs(tmp_path / "rec", frames=6))
    with opened(session, (1280, 720), query=f"?frame={FRAME}") as (driver, url):
        yield driver, session


def test_an_edit_says_what_it_made_worse_and_undo_takes_it_back(page):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    driver, session = page
    body = driver.find_element(By.TAG_NAME, "body")
    line = driver.find_element(By.ID, "consequence")
    point = session.skeleton.point_names.index(POINT)
    canvas = driver.find_element(By.CSS_SELECTOR, f'canvas[data-view="{VIEW}"]')

    def at_point():
        return driver.execute_script(f"return window.flylib.screenPosition({VIEW!r}, {point})")

    pos = at_point()
    ActionChains(driver).move_to_element_with_offset(
        canvas, round(pos["x"] - pos["width"] / 2), round(pos["y"] - pos["height"] / 2)
    ).click().perform()
    selected = wait_for(driver, "return window.flylib.state.selected")
    assert selected == {"view": VIEW, "point": point}
    before = session.points(FRAME)["views"]
    # fixed, the point dragged away: the other views' errors rise, said with both numbers
    body.send_keys("f")
    wait_for(driver, IDLE + " && window.flylib.history().undo === 1")
    body.send_keys("e")
    drag(driver, canvas, at_point(), 30, 21)
    text = wait_for(driver, SAID)
    after = session.points(FRAME)["views"]
    rose = re.findall(r"view (\w+)'s error rose ([\d.]+) \u2192 ([\d.]+) px", text)
    assert text.startswith(f"{POINT} in {VIEW} at frame {FRAME}: view ") and rose, text
    assert text.endswith(" \u2014 Ctrl+Z to undo"), text
    for view, was, now in rose:
        i = session.view_index(view)
        assert (float(was), float(now)) == (
            round(before[i]["error"][point], 1),
            round(after[i]["error"][point], 1),
        )
    body.send_keys(Keys.CONTROL, "z")  # the drag, then the fixing
    wait_for(driver, IDLE + " && window.flylib.history().undo === 1")
    assert not line.is_displayed()
    body.send_keys(Keys.CONTROL, "z")
    wait_for(driver, IDLE + " && window.flylib.history().undo === 0")
    # dragged far: the robust triangulation leaves the view out, said with the distance
    drag(driver, canvas, at_point(), 150, 0)
    text = wait_for(driver, SAID)
    off = session._off(session.view_index(VIEW), FRAME, point)
    assert off > 100
    assert text == (
        f"{POINT} in {VIEW} at frame {FRAME}: dropped by the robust triangulation "
        f"({off:.1f} px from its 3D) \u2014 Ctrl+Z to undo"
    )
    # Save's check lists it; a click on the line goes to its frame
    body.send_keys(Keys.HOME)
    wait_for(driver, IDLE + " && window.flylib.state.frame === 0")
    body.send_keys("s")
    box = driver.find_element(By.ID, "save-check")
    wait_for(driver, "return !document.querySelector('#save-check').hidden")
    entry = box.find_element(By.CSS_SELECTOR, "li")
    assert entry.text == (
        f"made worse: {POINT} at frame {FRAME}: the edit in {VIEW} is dropped by the robust "
        f"triangulation ({off:.1f} px from its 3D)"
    )
    entry.click()
    wait_for(
        driver, IDLE + f" && window.flylib.state.frame === {FRAME} && window.flylib.allDrawn()"
    )
    assert not box.is_displayed()
    assert not (session.outdir / "corrections.h5").exists()
