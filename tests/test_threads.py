"""Threads reach the work: a job's thread count sizes every pool (flylib.resources)."""

from __future__ import annotations

import importlib.util
import sys
import threading
from pathlib import Path

import pytest

from flylib.config import Config
from flylib.resources import thread_budget, thread_map, usable_cpus

REPO = Path(__file__).resolve().parents[1]


def _script(name: str):
    """Import ``scripts/<name>.py`` as a module (its ``_cli`` import resolved)."""
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        spec = importlib.util.spec_from_file_location(
            f"flylib_script_{name}", REPO / "scripts" / f"{name}.py"
        )
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(REPO / "scripts"))
    return module


@pytest.fixture
def started(monkeypatch):
    """The names of the threads started while the test runs."""
    names: list[str] = []
    original = threading.Thread.start

    def start(self):
        names.append(self.name)
        return original(self)

    monkeypatch.setattr(threading.Thread, "start", start)
    return names


def test_a_budget_sizes_the_pools_and_ends_with_its_block():
    outside = usable_cpus()
    with thread_budget(1) as budget:
        assert budget == 1 and usable_cpus() == 1
        with thread_budget(3):
            assert usable_cpus() == 3
        assert usable_cpus() == 1
    assert usable_cpus() == outside


def test_thread_map_keeps_order_and_runs_inline_under_one_thread(started):
    with thread_budget(1):
        assert list(thread_map(lambda x: x * x, list(range(20)), 8)) == [x * x for x in range(20)]
    assert started == []
    with thread_budget(2):
        assert list(thread_map(lambda x: x * x, list(range(20)), 8)) == [x * x for x in range(20)]
    assert len(started) == 2


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A tiny demo recording with its pose2d artifact, and a config rendering one short video."""
    from flylib.demo import demo_import_spec, make_demo
    from flylib.pipeline.stages import run_pose2d

    root = tmp_path_factory.mktemp("threads")
    data = Config.default().data
    data["pipeline"]["do_bundle_adjustment"] = False
    config_path = root / "config.yaml"
    import yaml

    config_path.write_text(yaml.safe_dump(data))
    config = Config.from_file(config_path)
    make_demo(config, root / "rec", frames=4, seed=0)
    out = root / "out"
    run_pose2d(
        config, root / "rec", out / "stages" / "pose2d.h5", import_spec=demo_import_spec(config)
    )
    return root, config_path, out


@pytest.mark.slow
def test_a_one_thread_job_starts_no_thread(recording, started):
    root, config, out = recording
    common = ["--config", str(config), "--threads", "1"]
    stages = out / "stages"
    assert (
        _script("triangulation").main(
            [
                *common,
                "--pose2d",
                str(stages / "pose2d.h5"),
                "--recording",
                str(root / "rec"),
                "--out",
                str(stages / "triangulation.h5"),
            ]
        )
        == 0
    )
    assert (
        _script("refinement").main(
            [
                *common,
                "--pose2d",
                str(stages / "pose2d.h5"),
                "--triangulation",
                str(stages / "triangulation.h5"),
                "--recording",
                str(root / "rec"),
                "--out",
                str(stages / "refinement.h5"),
            ]
        )
        == 0
    )
    assert (
        _script("assemble").main(
            [
                *common,
                "--pose2d",
                str(stages / "pose2d.h5"),
                "--triangulation",
                str(stages / "triangulation.h5"),
                "--refinement",
                str(stages / "refinement.h5"),
                "--recording",
                str(root / "rec"),
                "--outdir",
                str(out),
            ]
        )
        == 0
    )
    assert (
        _script("kinematics").main(
            [*common, "--results", str(out / "results.h5"), "--outdir", str(out)]
        )
        == 0
    )
    assert (
        _script("visualization").main(
            [
                *common,
                "--results",
                str(out / "results.h5"),
                "--recording",
                str(root / "rec"),
                "--outdir",
                str(out),
            ]
        )
        == 0
    )
    assert list(out.glob("*.mp4")), "no video rendered"
    assert started == []
