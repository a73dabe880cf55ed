"""Threads reach the work: a job's thread count sizes every pool (flylib.resources)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from flylib.config import Config
from flylib.pipeline.inputs import stage_inputs
from flylib.resources import thread_budget, thread_map, usable_cpus
from tests.workflow_run import load_script

REPO = Path(__file__).resolve().parents[1]


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


def test_thread_map_runs_at_most_workers_items_ahead_of_the_consumer():
    ran: list[int] = []

    def work(x):
        ran.append(x)
        return x

    with thread_budget(2):
        results = thread_map(work, list(range(50)), 2)
        assert next(results) == 0
        time.sleep(0.1)  # a pool that queued everything would have run all 50 by now
        assert len(ran) <= 3
        assert list(results) == list(range(1, 50))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A tiny demo recording with its pose2d artifact, and a config rendering one short video."""
    from flylib.pipeline.demo import demo_import_spec, make_demo
    from flylib.pipeline.pose2d import run_pose2d

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
        stage_inputs(config, "pose2d"),
        root / "rec",
        out / "stages" / "pose2d.h5",
        import_spec=demo_import_spec(config),
    )
    return root, config_path, out


@pytest.mark.slow
def test_a_one_thread_job_starts_no_thread(recording, started):
    root, config, out = recording
    common = ["--config", str(config), "--threads", "1"]
    stages = out / "stages"
    assert (
        load_script("triangulation").main(
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
        load_script("refinement").main(
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
        load_script("assemble").main(
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
        load_script("kinematics").main(
            [*common, "--results", str(out / "results.h5"), "--outdir", str(out)]
        )
        == 0
    )
    assert (
        load_script("visualization").main(
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


def test_a_one_thread_budget_decodes_in_the_calling_thread(tmp_path, started):
    import cv2
    import torch

    from flylib import io
    from flylib.pose2d import stream

    files = []
    for i in range(7):
        files.append(tmp_path / f"f{i}.png")
        cv2.imwrite(str(files[-1]), np.full((8, 8, 3), i, np.uint8))

    def blocks(**kwargs):
        prefetcher = stream.BlockPrefetcher("s", files, block_size=3, depth=2, **kwargs)
        prefetcher.start()
        out = []
        while (block := prefetcher.get()) is not stream.END_OF_STREAM:
            out.append(block)
        prefetcher.stop()
        return [len(b) for b in out], torch.cat(out)[:, 0, 0, 0].tolist()

    with thread_budget(1):
        inline = blocks(workers=4)  # more image workers than the budget: capped
        # (a reader opens its file only to decode)
        assert io.VideoReader(REPO / "pyproject.toml").decoder_threads() == 1
        assert io.ImageSequenceReader(files, workers=4).workers == 1
    assert started == []
    assert inline == ([3, 3, 1], list(range(7))) == blocks(workers=2, threaded=True)
    assert "flylib-decode-s" in started
    with thread_budget(2):
        assert io.VideoReader(REPO / "pyproject.toml", threads=8).decoder_threads() == 2
        assert io.VideoReader(REPO / "pyproject.toml").decoder_threads() == 0  # FFmpeg picks


@pytest.fixture
def torch_threads():
    """``load_models`` sizes torch's (process-wide) CPU pool from the budget: restore it."""
    import torch

    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.mark.slow
def test_a_one_thread_pose2d_job_starts_no_thread(recording, started, torch_threads):
    """The 2D stage under ``--threads 1``: the demo's DeepLabCut import, then the detector
    (a tiny random-weight network, on the demo's seven videos) decoding every source in
    the calling thread; with two threads the sources decode on their own threads again."""
    import json

    from flylib.pipeline.demo import demo_import_spec
    from flylib.pose2d.model import HourglassNet
    from flylib.pose2d.weights import save_checkpoint
    from flylib.results import Pose2dData

    root, config_path, out = recording
    pose2d = load_script("pose2d")
    recording_args = ["--recording", str(root / "rec")]
    spec = demo_import_spec(Config.from_file(config_path))
    imported = root / "threads1" / "stages" / "pose2d.h5"
    assert (
        pose2d.main(
            [
                *("--config", str(config_path), "--threads", "1"),
                *recording_args,
                *("--import-spec", json.dumps(spec), "--out", str(imported)),
            ]
        )
        == 0
    )
    import torch

    torch.manual_seed(0)
    checkpoint = save_checkpoint(
        HourglassNet(num_stacks=1, num_feats=8, inplanes=8), root / "sh1_random.tar"
    )
    import yaml

    data = yaml.safe_load(config_path.read_text())
    data["pose2d"]["models"][0].update(weights=str(checkpoint), input_size=[64, 128])
    data["pose2d"].update(batch_size=3, decode_buffer=2, device="cpu")
    detector_config = root / "detector.yaml"
    detector_config.write_text(yaml.safe_dump(data))
    detected = root / "detect1" / "stages" / "pose2d.h5"
    assert (
        pose2d.main(
            [
                *("--config", str(detector_config), "--threads", "1"),
                *recording_args,
                *("--out", str(detected)),
            ]
        )
        == 0
    )
    assert started == []
    assert Pose2dData.load(imported).pts2d.shape == Pose2dData.load(detected).pts2d.shape
    threaded = root / "detect2" / "stages" / "pose2d.h5"
    assert (
        pose2d.main(
            [
                *("--config", str(detector_config), "--threads", "2"),
                *recording_args,
                *("--out", str(threaded)),
            ]
        )
        == 0
    )
    assert sum(name.startswith("flylib-decode-") for name in started) == 7
    # the same points either way (up to torch's float summation order)
    one, two = Pose2dData.load(detected), Pose2dData.load(threaded)
    np.testing.assert_allclose(one.pts2d, two.pts2d, atol=0.05)
    np.testing.assert_allclose(one.conf, two.conf, atol=1e-5)
