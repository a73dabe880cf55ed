"""``flylib gui`` in a real browser: headless Chromium through Selenium on the demo's
workflow outputs. Open the page, wait for every canvas to draw, jump to the first
suspect, drag a point with real mouse events, save, then check ``corrections.h5`` and
that ``snakemake -n`` plans exactly triangulation, assemble and visualization.

Needs Debian's ``chromium`` and ``chromium-driver`` (``/usr/bin/chromium``,
``/usr/bin/chromedriver``) and the ``selenium`` package; skips with the reason otherwise.
Set ``FLYLIB_GUI_SCREENSHOT=path.png`` to keep a screenshot of the page.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time

import numpy as np
import pytest

from tests.workflow.test_workflow import base_config, jobs, planned, snakemake

pytestmark = pytest.mark.slow

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


def browser(size=(1500, 950)):
    if not CHROMIUM or not CHROMEDRIVER:
        pytest.skip(
            "headless Chromium is not installed: run `bash install.sh --test-system-packages` "
            "as root, or apt-get install chromium chromium-driver"
        )
    webdriver = pytest.importorskip("selenium.webdriver", reason="pip install selenium")
    from selenium.common.exceptions import WebDriverException

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--disable-gpu",
        f"--window-size={size[0]},{size[1]}",
        "--force-device-scale-factor=1",
    ):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    try:
        driver = webdriver.Chrome(options=options, service=webdriver.ChromeService(CHROMEDRIVER))
    except WebDriverException as exc:  # a driver that cannot start in this environment
        pytest.skip(f"Chromium did not start: {str(exc).splitlines()[0]}")
    # the page's viewport exactly `size` (a headless window's chrome varies)
    driver.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": size[0], "height": size[1], "deviceScaleFactor": 1, "mobile": False},
    )
    return driver


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("gui_browser")
    config = base_config()
    config["recordings"] = [{"path": str(root / "demo"), "demo": True}]
    config["demo"] = {**(config.get("demo") or {}), "frames": 16}
    config["bundle_adjustment"]["max_nfev"] = 20
    snakemake(root, config=config)
    return root, config, root / "demo" / "flylib_outputs"


@pytest.fixture
def server(demo_run):
    from flylib.gui import ReviewSession

    from gui_fixtures import serving

    _, _, out = demo_run
    session = ReviewSession(out)
    with serving(session) as url:
        yield url, session
    session.close()


@contextlib.contextmanager
def opened(session, size=(1500, 950), query: str | None = ""):
    """``(driver, url)``: Chromium at ``size`` on ``session`` served, the page at ``url + query``
    loaded and drawn (``query=None``: not loaded); the window and the session closed after."""
    from gui_fixtures import serving

    driver = browser(size)
    try:
        with serving(session) as url:
            if query is not None:
                driver.get(url + query)
                wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
            yield driver, url
    finally:
        driver.quit()
        session.close()


def wait_for(driver, script, timeout=60.0):
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    page_status = driver.execute_script("return document.querySelector('#status').textContent")
    raise AssertionError(f"timed out waiting for: {script}\nstatus: {page_status}")


def drag(driver, canvas, pos, dx, dy):
    """Press on the page position ``pos`` (``window.flylib.screenPosition``) inside
    ``canvas`` and drag by ``(dx, dy)`` CSS pixels in three real mouse moves."""
    from selenium.webdriver.common.action_chains import ActionChains

    actions = ActionChains(driver)
    actions.move_to_element_with_offset(
        canvas, round(pos["x"] - pos["width"] / 2), round(pos["y"] - pos["height"] / 2)
    )
    actions.click_and_hold()
    for _ in range(3):
        actions.move_by_offset(dx // 3, dy // 3)
    actions.release()
    actions.perform()


def test_review_drag_save_and_rerun_plan(demo_run, server):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    from flylib.corrections import Corrections

    root, config, out = demo_run
    url, session = server
    driver = browser()
    try:
        driver.get(url)
        wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
        canvases = driver.find_elements(By.CSS_SELECTOR, ".view canvas[data-view]")
        assert len(canvases) == session.n_views
        # the canvases really hold the footage: not a uniform fill
        spread = driver.execute_script("""
            const c = document.querySelector('.view canvas');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let lo = 255, hi = 0;
            for (let i = 0; i < d.length; i += 4 * 97) { lo = Math.min(lo, d[i + 1]); hi = Math.max(hi, d[i + 1]); }
            return hi - lo;""")
        assert spread > 20
        shot = os.environ.get("FLYLIB_GUI_SCREENSHOT")

        # n: the top suspect item (the list is best first), at its worst frame
        suspects = session.suspects()
        assert len(suspects) > 0
        body = driver.find_element(By.TAG_NAME, "body")
        body.send_keys("n")
        first = int(suspects.items()[0]["peak_frame"])
        wait_for(
            driver, f"return window.flylib.state.frame === {first} && window.flylib.allDrawn()"
        )
        selected = driver.execute_script("return window.flylib.state.selected")
        assert selected is not None

        # pick a used point of the selected view (the suspect itself when it is drawn)
        view, point = selected["view"], selected["point"]
        data = driver.execute_script("return window.flylib.state.data")
        v = [x["name"] for x in data["views"]].index(view)
        if data["views"][v]["points2d"][point] is None:
            point = next(i for i, xy in enumerate(data["views"][v]["points2d"]) if xy is not None)
        before_xy = data["views"][v]["points2d"][point]
        before_3d = data["points3d"][point]
        pos = driver.execute_script(f"return window.flylib.screenPosition({view!r}, {point})")
        canvas = next(c for c in canvases if c.get_attribute("data-view") == view)

        body.send_keys("e")  # Edit 2D on
        assert driver.execute_script("return window.flylib.state.editMode")
        dx, dy = 18, 12
        drag(driver, canvas, pos, dx, dy)
        wait_for(
            driver,
            f"return window.flylib.state.data.views[{v}].edited[{point}] && !window.flylib.busy()",
        )
        after = driver.execute_script("return window.flylib.state.data")
        after_xy = after["views"][v]["points2d"][point]
        scale = driver.execute_script(
            f"const v = window.flylib.state.views[{v}]; return v.transform.scale * "
            "v.canvas.getBoundingClientRect().width / v.canvas.width"
        )
        np.testing.assert_allclose(
            np.subtract(after_xy, before_xy), np.array([dx, dy]) / scale, atol=1.5 / scale
        )
        assert after["points3d"][point] != before_3d
        # a corrected point is a person's call: it leaves the suspect list and timeline
        listed = driver.execute_script(
            "return window.flylib.state.suspects.map(s => [s.frame, s.point, s.reasons.join()])"
        )
        score = driver.execute_script(f"return window.flylib.state.frameScore[{first}]")
        assert [first, point] not in [x[:2] for x in listed], (listed, score, first, point)

        driver.find_element(By.ID, "save").click()
        saved = wait_for(driver, "return window.flylib.saved")
        assert saved["saved"] == str(out / "corrections.h5")
        if shot:
            driver.save_screenshot(shot)

        # ? lists the shortcuts; n left the selected point's view large, g: the grid, g
        # again: that view large with thumbnails; wheel zooms; p goes back
        body.send_keys("?")
        assert driver.find_element(By.ID, "help").is_displayed()
        body.send_keys(Keys.ESCAPE)
        assert not driver.find_element(By.ID, "help").is_displayed()
        assert driver.execute_script("return window.flylib.state.layout") == "focus"
        body.send_keys("g")
        wait_for(driver, "return document.querySelector('#views').classList.contains('grid')")
        body.send_keys("g")
        wait_for(
            driver,
            "return document.querySelector('#views').classList.contains('focus') && "
            "document.querySelectorAll('.view.large').length === 1",
        )
        large = driver.find_element(By.CSS_SELECTOR, ".view.large canvas")
        thumbnail = driver.find_element(By.CSS_SELECTOR, ".view:not(.large) canvas")
        assert large.size["width"] > 2 * thumbnail.size["width"]
        ScrollOrigin = pytest.importorskip(
            "selenium.webdriver.common.actions.wheel_input"
        ).ScrollOrigin
        ActionChains(driver).scroll_from_origin(ScrollOrigin.from_element(large), 0, -300).perform()
        zoom = wait_for(
            driver,
            "const v = document.querySelector('.view.large canvas').dataset.view; "
            "const z = window.flylib.state.zoom[v]; return z.scale > 1 && z.scale",
        )
        assert zoom > 1
        body.send_keys("p")
        wait_for(
            driver,
            f"return window.flylib.state.frame < {first} || window.flylib.state.frame > {first}",
        )
    finally:
        driver.quit()

    corr = Corrections.load(
        out / "corrections.h5", (session.n_views, session.n_frames, session.n_points)
    )
    assert corr.edited[v, first, point] and corr.edited.sum() == 1
    np.testing.assert_allclose(corr.points[v, first, point], after_xy, atol=0.01)
    assert planned(root, config) == jobs(
        ("triangulation", "refinement", "assemble", "visualization", "kinematics"), ("demo",)
    )
