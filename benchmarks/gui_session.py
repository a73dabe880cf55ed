#!/usr/bin/env python
"""The review GUI as a lab member uses it (issue 47), in headless Chromium, before and after.

Per GUI (this checkout, and ``--baseline CHECKOUT`` served from that checkout's ``src`` in a
process of its own, the two interleaved ``--repeats`` times in one run):

- the 10-item keyboard session of tests/gui/test_browser_keys.py (a 40-frame demo with ten
  displaced points; ``u``, then per item ``c`` ``a`` ``k``) typed at 60 ms between keys and
  at idle pace (each key once the page is idle): edits landed on the items' points (of 20),
  items marked reviewed (of 10), stray edits (outside the items), seconds per item;
- frame step (-> until every view shows the frame) and playback's drawn frames per second at
  10 and 30 fps asked, on the DeepFly3D sample (``../shared/data/deepfly3d-sample``, run
  through the workflow once) and on a 900-frame demo recording just opened;
- the footage fraction at 1280x720 in the focus view of the sample's first item (``u``): the
  large view's frame less what the thumbnails cover, of the window; with ``--screenshots DIR``
  the focus view at 1280x720 and 1600x1000 as JPEG.

    python benchmarks/gui_session.py --baseline ../base [--repeats 2] [--screenshots docs/images]

``--playback``: frame step and playback only (a few minutes less a run); ``--data DIR`` keeps the
recordings made for the next run.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO.parent / "shared" / "data" / "deepfly3d-sample"
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

SIZE = (1280, 720)
STEP_JS = """
const [n, done] = [arguments[0], arguments[arguments.length - 1]];
const f = window.flylib, ms = [], sleep = (t) => new Promise((r) => setTimeout(r, t));
(async () => {
  for (let i = 0; i < n; i++) {  // a step every 100 ms or so, as a user tapping -> (wrapping)
    const t = performance.now();
    f.goto((f.state.frame + 1) % f.state.meta.frames);
    while (!f.allDrawn()) await sleep(2);
    ms.push(performance.now() - t);
    await sleep(100);
  }
  done(ms);
})();
"""
FOCUS_FILL_JS = """
const s = window.flylib.state, view = s.views[s.focus];
if (s.layout !== "focus" || !view) return 0;
const r = view.canvas.getBoundingClientRect(), fit = Math.min(r.width / view.width, r.height / view.height);
const w = view.width * fit, h = view.height * fit, left = r.left + (r.width - w) / 2, top = r.top + (r.height - h) / 2;
let covered = 0;
for (const tile of [...s.views.map((v) => v.div), s.tile3d]) {
  if (!tile || tile === view.div) continue;
  const t = tile.getBoundingClientRect();
  covered += Math.max(0, Math.min(t.right, left + w) - Math.max(t.left, left)) *
    Math.max(0, Math.min(t.bottom, top + h) - Math.max(t.top, top));
}
return (w * h - covered) / (window.innerWidth * window.innerHeight);
"""
PLAY_JS = """
const [fps, seconds, done] = [arguments[0], arguments[1], arguments[arguments.length - 1]];
const f = window.flylib, drawn = new Set(), started = performance.now();
const canvas = f.state.views[f.state.views.length - 1].canvas;  // drawn last of a frame
new MutationObserver(() => drawn.add(canvas.dataset.drawnFrame)).observe(canvas, { attributes: true });
const fpsField = document.querySelector("#fps");
fpsField.value = String(fps);
fpsField.dispatchEvent(new Event("change"));
const key = () => document.body.dispatchEvent(new KeyboardEvent("keydown", { key: " ", bubbles: true }));
key();
const check = setInterval(() => {  // played `seconds`, or stopped at the last frame
  const elapsed = (performance.now() - started) / 1000;
  if (f.state.playing && elapsed < seconds) return;
  if (f.state.playing) key();
  clearInterval(check);
  done([drawn.size / elapsed, elapsed]);
}, 20);
"""
KEYS = ["u"] + ["c", "a", "k"] * 10


# -- one GUI, in a process of its own (``--one``: flylib imported from that checkout) --------


def serving(session):
    """The GUI's app on a free localhost port in a thread (yields the URL)."""
    import socket

    import uvicorn

    from flylib.gui import create_app

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(create_app(session), host="127.0.0.1", port=port, log_level="warning")
    )
    server.thread = threading.Thread(target=server.run, daemon=True)
    server.thread.start()
    while not server.started:
        time.sleep(0.05)
    return server, f"http://127.0.0.1:{port}/"


def wait(driver, script, timeout=120.0):
    deadline = time.time() + timeout
    while not driver.execute_script(script):
        if time.time() > deadline:
            raise TimeoutError(script)
        time.sleep(0.05)


class Page:
    """A recording opened in ReviewSession, served, and loaded in Chromium at ``size``."""

    def __init__(self, outdir: Path, size=SIZE):
        from flylib.gui import ReviewSession
        from tests.gui.test_browser import browser

        self.session = ReviewSession(outdir)
        self.server, url = serving(self.session)
        self.driver = browser(size)
        self.driver.set_script_timeout(600)
        self.driver.get(url)
        wait(self.driver, "return window.flylib && window.flylib.allDrawn()")

    def idle(self) -> float:
        """When the page went idle (and stayed so half a second later: every key handled)."""
        while True:
            wait(self.driver, "return !window.flylib.busy() && window.flylib.allDrawn()")
            at = time.perf_counter()
            time.sleep(0.5)
            if self.driver.execute_script("return !window.flylib.busy()"):
                return at

    def close(self):
        self.driver.quit()
        self.server.should_exit = True
        self.server.thread.join(10)  # its requests answered before the decoders close
        self.session.close()


def keyboard_session(rec: Path, pace: float | None) -> dict:
    """The 10 items typed at ``pace`` s between keys (None: each key once the page is idle)."""
    from selenium.webdriver.common.action_chains import ActionChains

    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(rec, Path(tmp) / "rec")  # no journal, no edits (footage: where made)
        page = Page(Path(tmp) / "rec" / "flylib_outputs")
        try:
            items = page.session.review()["items"][:10]
            seconds = 0.0
            if pace is None:  # each key once the page is idle: the time from key to idle
                for key in KEYS:
                    started = time.perf_counter()
                    ActionChains(page.driver, duration=0).send_keys(key).perform()
                    time.sleep(0.1)  # (the key's action under way)
                    seconds += page.idle() - started
            else:
                started = time.perf_counter()
                keys = ActionChains(page.driver, duration=0)
                for key in KEYS:
                    keys.send_keys(key).pause(pace)
                keys.perform()
                seconds = page.idle() - started
            c = page.session.corrections
        finally:
            page.close()
    inside = sum(c.edited[:, it["frames"], it["point"]].any(axis=0).sum() for it in items)
    within = sum(c.edited[:, it["frames"], it["point"]].sum() for it in items)
    return {
        "landed": int(inside),
        "marked": int(sum(c.reviewed[it["frames"], it["point"]].all() for it in items)),
        "stray": int(c.edited.sum() - within),
        "s_per_item": seconds / len(items),
    }


def stepping(outdir: Path, steps: int) -> dict:
    page = Page(outdir)
    try:
        ms = page.driver.execute_async_script(STEP_JS, steps)
        figures = {"step_ms": ms}
        for fps in (10, 30):
            page.driver.execute_script("window.flylib.goto(0)")
            page.idle()
            shown, _ = page.driver.execute_async_script(PLAY_JS, fps, 3)
            figures[f"play{fps}"] = shown
    finally:
        page.close()
    return figures


def focus_view(outdir: Path, shots: Path | None, label: str) -> dict:
    figures = {}
    for size in (SIZE, (1600, 1000)):
        page = Page(outdir, size)
        try:
            page.driver.find_element("tag name", "body").send_keys("u")
            page.idle()
            if size == SIZE:
                figures["footage"] = page.driver.execute_script(FOCUS_FILL_JS)
            if shots is not None:  # the header: the results' path from the run's folder
                from PIL import Image

                shown = json.dumps(str(Path(*outdir.resolve().parts[-2:], "results.h5")))
                page.driver.execute_script(
                    f"document.querySelector('#recording').textContent = {shown}"
                )

                png = Image.open(io.BytesIO(page.driver.get_screenshot_as_png())).convert("RGB")
                png.save(shots / f"gui-{label}-{size[0]}x{size[1]}.jpg", quality=70, optimize=True)
        finally:
            page.close()
    return figures


def one(data: Path, label: str, shots: Path | None, playback: bool = False) -> dict:
    figures = {}
    if not playback:
        figures["keys60"] = keyboard_session(data / "keys" / "rec", 0.06)
        figures["keys_idle"] = keyboard_session(data / "keys" / "rec", None)
    figures["sample"] = stepping(data / "sample", 28)
    figures["rec900"] = stepping(data / "rec900" / "flylib_outputs", 30)
    if not playback:
        figures.update(focus_view(data / "sample", shots, label))
    return figures


# -- the parent: data made once, each GUI run in turn -----------------------------------------


def make_data(data: Path, frames: int) -> None:
    sys.path.insert(0, str(REPO / "src"))
    from tests.gui.test_browser_keys import ITEMS

    from gui_fixtures import make_demo_outputs

    if not (data / "keys").is_dir():
        make_demo_outputs(
            data / "keys" / "rec",
            frames=40,
            dropout=0.0,
            outliers=0.0,
            displaced=[(camera, point, at, (45.0, -35.0)) for camera, point, at in ITEMS],
        )
    if not (data / "rec900").is_dir():
        make_demo_outputs(data / "rec900", frames=frames)
    if not (data / "sample").is_dir():
        work = data / "sample-run"
        work.mkdir(exist_ok=True)
        (work / "sample.yaml").write_text(
            json.dumps(
                {
                    "recordings": [
                        {
                            "path": str(SAMPLE),
                            "import": {"format": "deepfly3d", "files": "df3d_result_2d.pkl"},
                        }
                    ],
                    "outdir": "sample_outputs/{id}",
                }
            )
        )
        snakemake = Path(sys.executable).parent / "snakemake"
        subprocess.run(
            [snakemake, "-s", REPO / "Snakefile", "-d", work, "--configfile", work / "sample.yaml"]
            + ["-c1", "-q"],
            env={**os.environ, "PYTHONPATH": str(REPO / "src")},
            check=True,
        )
        (data / "sample").symlink_to(next(work.glob("sample_outputs/*/results.h5")).parent)


def run_one(checkout: Path, data: Path, label: str, shots: Path | None, playback: bool) -> dict:
    command = [sys.executable, __file__, "--one", label, "--data", str(data)]
    if shots is not None:
        command += ["--screenshots", str(shots)]
    if playback:
        command += ["--playback"]
    env = {**os.environ, "PYTHONPATH": str(checkout / "src")}
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    if done.returncode:
        raise SystemExit(f"{label} ({checkout}) failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def report(runs: dict[str, list[dict]]) -> None:
    labels = list(runs)

    def figure(label, *path):
        values = []
        for run in runs[label]:
            value = run
            for key in path:
                value = value[key]
            values.append(value)
        return values

    def row(name, *path, unit="", ratio=True):
        cells = []
        for label in labels:
            v = np.asarray(figure(label, *path), float)
            cells.append(f"{label} {np.median(v):7.2f}{unit}")
        line = f"{name:38s}" + "   ".join(cells)
        if ratio and len(labels) == 2:
            a, b = (np.median(figure(label, *path)) for label in labels)
            line += f"   after/before {b / a:5.2f}" if a else ""
        print(line)

    print(f"medians over {len(runs[labels[0]])} run(s) each, interleaved:")
    for pace in [p for p in ("keys60", "keys_idle") if p in runs[labels[0]][0]]:
        for key, unit in (
            ("landed", " /20"),
            ("marked", " /10"),
            ("stray", ""),
            ("s_per_item", " s"),
        ):
            row(f"{pace} {key}", pace, key, unit=unit, ratio=key == "s_per_item")
    for rec in ("sample", "rec900"):
        for label in labels:
            steps = np.concatenate([np.asarray(r[rec]["step_ms"]) for r in runs[label]])
            print(
                f"{rec} frame step {label:8s} median {np.median(steps):6.1f} ms, "
                f"p95 {np.percentile(steps, 95):6.1f} ms ({len(steps)} steps)"
            )
        row(f"{rec} playback 10 fps asked, drawn", rec, "play10", unit=" fps")
        row(f"{rec} playback 30 fps asked, drawn", rec, "play30", unit=" fps")
    if "footage" in runs[labels[0]][0]:
        row("footage fraction 1280x720 (focus)", "footage")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, help="a checkout to compare with (its src)")
    parser.add_argument("--repeats", type=int, default=1, help="interleaved runs per GUI")
    parser.add_argument("--frames", type=int, default=900, help="the long demo recording")
    parser.add_argument("--data", type=Path, help="where the recordings are made (kept)")
    parser.add_argument("--screenshots", type=Path, help="focus-view JPEGs of this checkout")
    parser.add_argument("--json", type=Path, help="every run's figures written here")
    parser.add_argument(
        "--playback", action="store_true", help="only frame step and playback (no keys, no focus)"
    )
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        shots = args.screenshots if args.one == "after" else None
        print(json.dumps(one(args.data, args.one, shots, args.playback)))
        return 0
    data = args.data or Path(tempfile.mkdtemp(prefix="gui-session-"))
    data.mkdir(parents=True, exist_ok=True)
    make_data(data, args.frames)
    checkouts = {"before": args.baseline, "after": REPO} if args.baseline else {"after": REPO}
    runs = {label: [] for label in checkouts}
    for i in range(args.repeats):
        for label, checkout in checkouts.items():
            run = run_one(checkout.resolve(), data, label, args.screenshots, args.playback)
            runs[label].append(run)
            said = f"at 60 ms {run['keys60']['landed']}/20 edits landed" if "keys60" in run else ""
            print(f"run {i + 1} {label}: {said or 'done'}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(runs, indent=1))
    report(runs)
    print("(headless Chromium, --disable-gpu; timing on a shared machine is noisy)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
