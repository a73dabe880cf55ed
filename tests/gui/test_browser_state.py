"""What the review page says describes the state now (issue 47): the replayed journal's
"press Save" goes once saved (and stays gone on reload), Save counts the edits since the
last save, a results.h5 rewritten by a re-run is offered for reload; the help fits
1280x720, hidden points are said in the header, bad fps and frame values are answered.

Headless Chromium at 1280x720 on a 12-frame demo recording; needs Debian's ``chromium``
and ``chromium-driver`` and ``selenium`` (skips with the apt command).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.gui.test_browser import opened, wait_for

from gui_fixtures import make_demo_outputs

pytestmark = pytest.mark.slow


def text(driver, selector):
    return driver.execute_script(
        f"const e = document.querySelector('{selector}'); return e && !e.hidden ? e.textContent : null"
    )


def test_notices_and_counts_follow_saves_and_a_rerun(tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    from flylib.gui import ReviewSession
    from flylib.results import PoseResult

    outdir = make_demo_outputs(tmp_path / "rec")
    first = ReviewSession(outdir)  # stopped before saving: its edit is journaled
    view = first.view_names[0]
    p = int(np.flatnonzero(np.isfinite(first.base2d[0, 1]).all(-1))[0])
    first.edit("move", 1, p, view, (first.base2d[0, 1, p] + 3).tolist())
    first.close()
    session = ReviewSession(outdir)
    with opened(session, (1280, 720)) as (driver, url):
        assert "press Save" in driver.execute_script("return window.flylib.alert()")
        assert driver.find_element(By.ID, "save").text == "Save (1)"
        driver.find_element(By.ID, "save").click()
        wait_for(driver, "return window.flylib.saved")
        assert driver.execute_script("return window.flylib.alert()") == ""
        driver.refresh()
        wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
        assert driver.execute_script("return window.flylib.alert()") == ""
        assert driver.find_element(By.ID, "save").text == "Save"
        # one more edit: Save counts it, not the one already saved
        ActionChains(driver).send_keys("n").pause(0.5).send_keys("i").perform()
        wait_for(driver, "return window.flylib.state.data.dirty && !window.flylib.busy()")
        assert session.corrections.count() == 2
        assert driver.find_element(By.ID, "save").text == "Save (1)"
        # a re-run rewrites results.h5: the page offers to read it again
        result = PoseResult.load(outdir / "results.h5")
        result.pts3d[0] += 0.01
        result.save(outdir / "results.h5")
        banner = wait_for(
            driver,
            "return document.querySelector('#results-banner').hidden ? null : document.querySelector('#results-banner').textContent",
            timeout=20,
        )
        assert "results.h5 was rewritten on disk" in banner and "replayed" in banner
        driver.execute_script("window.beforeReload = true")
        driver.find_element(By.ID, "reload-results").click()
        wait_for(driver, "return !window.beforeReload && window.flylib && window.flylib.allDrawn()")
        assert text(driver, "#results-banner") is None
        assert np.allclose(session.pts3d[0], result.pts3d[0], equal_nan=True)
        assert driver.find_element(By.ID, "save").text == "Save (1)"


def test_help_fits_hidden_points_are_said_and_bad_values_answered(tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    from flylib.gui import ReviewSession

    session = ReviewSession(make_demo_outputs(tmp_path / "rec"))
    with opened(session, (1280, 720)) as (driver, url):
        body = driver.find_element(By.TAG_NAME, "body")
        body.send_keys("?")
        # every line of the help reachable inside the window
        bottom = driver.execute_script(
            "const h = document.querySelector('#help'); h.scrollTop = h.scrollHeight;"
            "const rows = h.querySelectorAll('tr'); return [h.getBoundingClientRect().bottom,"
            "rows[rows.length - 1].getBoundingClientRect().bottom];"
        )
        assert max(bottom) <= 720, bottom
        body.send_keys("\ue00c")  # Escape
        if driver.execute_script("return !document.body.classList.contains('panel-closed')"):
            body.send_keys("b")
        assert text(driver, "#display-state") is None
        ActionChains(driver).send_keys("o").send_keys("]").perform()
        said = text(driver, "#display-state")
        assert said and "overlay off" in said and "only " in said, said
        assert driver.find_element(By.ID, "display-state").is_displayed()
        for field, typed, answer, kept in [
            (
                "fps",
                "500",
                'fps "500" is not a whole number from 1 to 120; playing at 120',
                "120",
            ),
            ("frame-input", "999", "frame 999 is past the last frame; showing frame 11", "11"),
        ]:
            element = driver.find_element(By.ID, field)
            driver.execute_script("arguments[0].value = ''; arguments[0].focus()", element)
            element.send_keys(typed, "\ue007")  # Enter
            driver.execute_script("arguments[0].blur()", element)
            wait_for(driver, f"return document.querySelector('#{field}').value === '{kept}'", 10)
            assert driver.find_element(By.ID, "status").text == answer
