"""Typing ahead in the review page (issue 47): every key acts on the state it was pressed
in. Ten suspect items corrected keyboard-only at 60 ms between keys in headless Chromium
(u, then per item c: onto its 3D, a: over the item's other frame, k: reviewed and on to
the next) land every edit on its item's point, mark every item and lose no undo step.

On a 40-frame demo recording without detector noise beyond 1 px, ten points displaced
each in one view over two frames (the recording's only ten suspect items); needs
Debian's ``chromium`` and ``chromium-driver`` and ``selenium`` (skips with the apt command).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.gui.test_browser import browser, wait_for

from gui_fixtures import make_demo_outputs, serving

pytestmark = pytest.mark.slow

ITEMS = [
    ("camera_2", "rf_femur_tibia", (3, 4)),
    ("camera_1", "rf_tibia_tarsus", (7, 8)),
    ("camera_0", "rf_claw", (11, 12)),
    ("camera_4", "lf_tibia_tarsus", (15, 16)),
    ("camera_5", "lf_femur_tibia", (19, 20)),
    ("camera_6", "lf_claw", (23, 24)),
    ("camera_2", "rm_femur_tibia", (27, 28)),
    ("camera_1", "rm_tibia_tarsus", (31, 32)),
    ("camera_6", "lm_femur_tibia", (35, 36)),
    ("camera_4", "lm_tibia_tarsus", (38, 39)),
]


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    return make_demo_outputs(
        tmp_path_factory.mktemp("gui_keys") / "rec",
        frames=40,
        dropout=0.0,
        outliers=0.0,
        displaced=[(camera, point, frames, (45.0, -35.0)) for camera, point, frames in ITEMS],
    )


def test_ten_items_typed_ahead_at_60_ms_land_every_edit_on_its_point(outdir):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    from flylib.gui import ReviewSession

    session = ReviewSession(outdir)
    items = session.review()["items"]
    assert [(it["point_name"], tuple(it["frames"])) for it in items] == [
        (point, frames) for _, point, frames in ITEMS
    ]
    # where each item's edits belong: the view the page focuses (the point's largest
    # error at the item's worst frame), on the 3D ghost there, copied to the other frame
    expected = []
    for it in items:
        views = session.points(it["peak_frame"])["views"]
        errors = [-1 if v["error"][it["point"]] is None else v["error"][it["point"]] for v in views]
        v = int(np.argmax(errors))
        expected.append((v, it["point"], it["frames"], views[v]["reprojected"][it["point"]]))
    driver = browser((1280, 720))
    try:
        with serving(session) as url:
            driver.get(url)
            wait_for(driver, "return window.flylib && window.flylib.allDrawn()")
            driver.execute_script(
                "window.busySeen = false; const b = document.querySelector('#busy');"
                "new MutationObserver(() => { if (b && !b.hidden) window.busySeen = true; })"
                ".observe(document.body, {attributes: true, subtree: true});"
            )
            keys = ActionChains(driver, duration=0)
            for key in ["u"] + ["c", "a", "k"] * len(ITEMS):
                keys.send_keys(key).pause(0.06)
            keys.perform()
            for _ in range(2):  # idle, and still idle a second later: every key handled
                wait_for(driver, "return !window.flylib.busy()", timeout=120)
                time.sleep(1.0)
            busy_seen = driver.execute_script("return window.busySeen")
            busy_hidden = driver.execute_script("return document.querySelector('#busy')?.hidden")
            history = driver.execute_script("return window.flylib.history()")
            status = driver.find_element(By.ID, "status").text
    finally:
        driver.quit()
        session.close()
    c = session.corrections
    landed = sum(
        c.edited[v, f, p] and np.allclose(c.points[v, f, p], ghost, atol=0.01)
        for v, p, frames, ghost in expected
        for f in frames
    )
    marked = sum(c.reviewed[list(frames), p].all() for _, p, frames, _ in expected)
    stray = c.edited.sum() - sum(c.edited[v, frames, p].sum() for v, p, frames, _ in expected)
    assert (landed, marked, stray) == (2 * len(ITEMS), len(ITEMS), 0), (
        f"{landed} of {2 * len(ITEMS)} edits landed, {marked} of {len(ITEMS)} items marked, "
        f"{stray} stray edit(s); status: {status}"
    )
    assert c.reviewed.sum() == 2 * len(ITEMS)
    # every step undoable (per item the snap, the application, the mark), none refused
    assert history == {"undo": 3 * len(ITEMS), "redo": 0}
    assert "not applied" not in status and "refused" not in status, status
    assert busy_seen and busy_hidden is True  # said while the server re-solved, gone after
