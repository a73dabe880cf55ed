"""Working through suspect items in the review page (issue 47): ``n`` / ``p`` go on from
the item last gone to wherever the frame is, the zoom follows the point through an
item's frames in the large view and the thumbnails, thumbnails name the selected point
only, and one line under the frames tells the item's story while the focused footage
fills most of a 1280x720 window.

Headless Chromium at 1280x720 on a 40-frame demo recording whose only suspect items are
three points displaced in one view over five frames each; needs Debian's ``chromium``
and ``chromium-driver`` and ``selenium`` (skips with the apt command).
"""

from __future__ import annotations

import math

import pytest

from tests.gui.test_browser import opened, wait_for

from gui_fixtures import make_demo_outputs

pytestmark = pytest.mark.slow

ITEMS = [
    ("camera_2", "rf_claw", tuple(range(10, 15))),
    ("camera_4", "lf_claw", tuple(range(20, 25))),
    ("camera_1", "rm_tibia_tarsus", tuple(range(30, 35))),
]


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    from flylib.gui import ReviewSession

    outdir = make_demo_outputs(
        tmp_path_factory.mktemp("gui_nav") / "rec",
        frames=40,
        dropout=0.0,
        outliers=0.0,
        displaced=[(camera, point, frames, (45.0, -35.0)) for camera, point, frames in ITEMS],
    )
    session = ReviewSession(outdir)
    with opened(session, (1280, 720), query=None) as (driver, url):
        yield driver, session, url


def open_page(served):
    driver, session, url = served
    driver.get(url)
    wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
    items = session.suspects().items()
    assert sorted(tuple(it["frames"]) for it in items) == sorted(f for *_, f in ITEMS)
    return driver, items


def press(driver, key):
    from selenium.webdriver.common.by import By

    driver.find_element(By.TAG_NAME, "body").send_keys(key)
    wait_for(driver, "return !window.flylib.busy()")


def at_item(driver, item):
    # on the item: its worst frame, its point selected, every view drawn and zoomed to it
    wait_for(
        driver,
        f"return window.flylib.state.frame === {item['peak_frame']} && "
        f"window.flylib.state.selected?.point === {item['point']} && "
        "window.flylib.state.layout === 'focus' && window.flylib.allDrawn()",
    )
    return driver.execute_script("return window.flylib.state.selected.view")


def step_to(driver, frame):
    from selenium.webdriver.common.keys import Keys

    now = driver.execute_script("return window.flylib.state.frame")
    for _ in range(abs(frame - now)):
        press(driver, Keys.ARROW_RIGHT if frame > now else Keys.ARROW_LEFT)
    wait_for(driver, f"return window.flylib.state.frame === {frame} && window.flylib.allDrawn()")


def offsets(driver, point):
    """Per view that places the point: its distance from the view's centre (CSS px)."""
    out = {}
    for view in driver.execute_script("return window.flylib.state.meta.views.map((v) => v.name)"):
        pos = driver.execute_script(f"return window.flylib.screenPosition({view!r}, {point})")
        if pos:
            out[view] = math.hypot(pos["x"] - pos["width"] / 2, pos["y"] - pos["height"] / 2)
    return out


def test_n_and_p_go_on_from_the_item_and_the_zoom_follows_its_point(served):
    driver, items = open_page(served)
    press(driver, "l")  # every point's name on: thumbnails still name the selected point only
    press(driver, "n")
    at_item(driver, items[0])
    press(driver, "n")
    item = items[1]
    large = at_item(driver, item)
    # through the item's frames the point stays at the centre of every zoomed view
    worst = {}
    for frame in item["frames"]:
        step_to(driver, frame)
        for view, off in offsets(driver, item["point"]).items():
            worst[view] = max(worst.get(view, 0.0), off)
    assert worst[large] < 3, f"the point drifts {worst[large]:.0f} px off the large view's centre"
    assert max(worst.values()) < 3, {v: round(o) for v, o in worst.items()}
    labelled = driver.execute_script(
        "return window.flylib.state.views.map((v) => [v.index, v.labelled])"
    )
    focus = driver.execute_script("return window.flylib.state.focus")
    assert all(names in ([], [item["point"]]) for i, names in labelled if i != focus), labelled
    assert len(dict(labelled)[focus]) > 5  # the large view names every point
    # one frame past the item: n goes to the next item, p to the one before
    step_to(driver, item["last_frame"] + 1)
    press(driver, "n")
    at_item(driver, items[2])
    step_to(driver, items[2]["last_frame"] + 1)
    press(driver, "p")
    at_item(driver, items[1])


def test_one_line_under_the_frames_tells_the_item_and_the_footage_fills_the_window(served):
    driver, items = open_page(served)
    press(driver, "n")
    item = items[0]
    large = at_item(driver, item)
    line = driver.execute_script(
        "const e = document.querySelector('#item-line'); if (!e) return null;"
        "const r = e.getBoundingClientRect();"
        "return {text: e.textContent, top: r.top, bottom: r.bottom, height: r.height,"
        " frames: document.querySelector('.view.large').getBoundingClientRect().bottom}"
    )
    fill = driver.execute_script("return window.flylib.focusFill()")
    assert line is not None and fill >= 0.8, f"no item line; the footage fills {fill:.0%}"
    error = served[1].points(item["peak_frame"])["views"]
    v = served[1].view_names.index(large)
    frames = f"{item['first_frame']}\u2013{item['last_frame']}"
    text = line["text"]
    assert f"#1 of {len(items)}" in text and item["point_name"] in text and frames in text, text
    assert item["detail"] in text, text
    assert f"{error[v]['error'][item['point']]:.1f} px" in text, text
    # one line, under the frames, inside the window
    assert line["top"] >= line["frames"] and line["bottom"] <= 720 and line["height"] < 24, line
