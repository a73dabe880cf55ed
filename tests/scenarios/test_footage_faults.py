"""Damaged footage: a truncated JPEG in an image sequence, a truncated MP4
that still has its header, and frame-count mismatches between footage and results."""

from __future__ import annotations

import copy
import logging
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest

from flylib import io
from flylib.config import Config
from flylib.errors import FootageError, ImportFormatError
from flylib.io.images import image_damage
from flylib.pipeline.inputs import stage_inputs, stage_params
from flylib.pipeline.planning import config_rig
from flylib.pipeline.pose2d import import_target


def _inputs(data: dict):
    """The pose2d stage's inputs under the raw config ``data``."""
    return stage_inputs(Config.from_dict(data), "pose2d")


def _jpegs(directory: Path, n: int = 6, size=(48, 64), seed: int = 0) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    files = []
    for i in range(n):
        path = directory / f"img_{i}.jpg"
        cv2.imwrite(str(path), rng.integers(0, 255, (*size, 3), dtype=np.uint8))
        files.append(path)
    return files


def _truncate(path: Path, keep: float = 0.6) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def test_image_damage_finds_truncated_jpeg_and_png(tmp_path):
    jpg = _jpegs(tmp_path, 1)[0].read_bytes()
    assert image_damage(jpg) is None
    assert "truncated JPEG" in image_damage(jpg[: len(jpg) // 2])
    assert image_damage(jpg + b"\x00" * 16) is None  # padding after the end marker is fine
    _, png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))
    png = png.tobytes()
    assert image_damage(png) is None and "truncated PNG" in image_damage(png[:-20])


def test_truncated_jpeg_fails_naming_the_file(tmp_path):
    files = _jpegs(tmp_path)
    _truncate(files[3])
    # OpenCV alone decodes it without an error (grey rows, a libjpeg warning)
    assert cv2.imread(str(files[3])) is not None
    reader = io.open_reader(tmp_path / "img_*.jpg")
    with pytest.raises(
        FootageError,
        match=rf"^{files[3]}: cannot decode frame 3 \(truncated JPEG: no "
        r"end-of-image marker.*io\.on_corrupt_frame: missing",
    ):
        reader[:]


def test_truncated_jpeg_is_marked_missing_when_asked(tmp_path, caplog):
    files = _jpegs(tmp_path)
    whole = io.open_reader(tmp_path / "img_*.jpg")[:]
    _truncate(files[3])
    reader = io.open_reader(tmp_path / "img_*.jpg", on_corrupt="missing", workers=2)
    with caplog.at_level(logging.WARNING):
        frames = np.stack(list(reader.stream_frames()))
    assert frames.shape == whole.shape and not frames[3].any()
    np.testing.assert_array_equal(np.delete(frames, 3, axis=0), np.delete(whole, 3, axis=0))
    assert reader.corrupt_frames == {3}
    assert f"{files[3]}: frame 3 is corrupt" in caplog.text


# -- the detector: the job fails naming the file, or the frame goes missing ------------------


@pytest.fixture(scope="module")
def detector(tmp_path_factory):
    import torch

    from flylib.config import Config
    from flylib.pose2d import HourglassNet, weights

    torch.manual_seed(0)
    net = HourglassNet(num_stacks=1, num_feats=8, inplanes=8).eval()
    checkpoint = weights.save_checkpoint(net, tmp_path_factory.mktemp("w") / "tiny.tar")
    data = copy.deepcopy(dict(Config.default().data))
    data["pose2d"]["models"][0].update(weights=str(checkpoint), input_size=[64, 128])
    data["pose2d"].update(batch_size=4, decode_buffer=2, device="cpu")
    return data


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_detector_fails_on_a_truncated_jpeg_or_marks_its_frame_missing(tmp_path, detector):
    import torch

    from flylib.pose2d import detect_2d, load_models

    torch.set_num_threads(1)
    plan = _inputs(detector).detection_plan()
    sources = {s: _jpegs(tmp_path / s, n=6, seed=i) for i, s in enumerate(plan.sources)}
    broken = sources["vid_rh"][2]
    _truncate(broken)
    models = load_models(plan, _inputs(detector).detector_params())
    with pytest.raises(FootageError, match=rf"^{broken}: cannot decode frame 2 \(truncated JPEG"):
        detect_2d(
            _inputs(detector).detector_params(),
            plan,
            models,
            sources=sources,
            io=_inputs(detector).io(),
        )

    data = copy.deepcopy(detector)
    data["io"]["on_corrupt_frame"] = "missing"
    pts, conf, _ = detect_2d(
        _inputs(data).detector_params(), plan, models, sources=sources, io=_inputs(data).io()
    )
    rh = plan.view_names.index("rh")
    assert np.isnan(pts[rh, 2]).all() and np.isnan(conf[rh, 2]).all()
    assert np.isfinite(pts[rh, [0, 1, 3, 4, 5]]).any()  # the other frames are detected
    others = [v for v in range(len(plan.view_names)) if v != rh]
    assert np.isfinite(pts[others, 2]).any()  # the other cameras' frame 2 is kept


def test_missing_frames_are_part_of_pose2d_params_only_when_asked():
    from flylib.config import Config

    data = copy.deepcopy(dict(Config.default().data))
    assert "on_corrupt_frame" not in stage_params(Config.from_dict(data), "pose2d")
    data["io"]["on_corrupt_frame"] = "missing"
    assert stage_params(Config.from_dict(data), "pose2d")["on_corrupt_frame"] == "missing"
    data["io"]["on_corrupt_frame"] = "skip"
    from flylib.errors import ConfigError

    with pytest.raises(ConfigError, match="io.on_corrupt_frame: expected 'error' or 'missing'"):
        Config.from_dict(data)


# -- a truncated MP4 that still has its header ---------------------------------------------


def _mp4(path: Path, n: int = 60, truncate: float | None = None) -> Path:
    """An H.264 MP4 with its index (moov) before the frames, as a camera's recorder or
    ``-movflags faststart`` writes it: cut short, it still opens and reports ``n``."""
    import av

    rng = np.random.default_rng(0)
    with av.open(str(path), "w", options={"movflags": "faststart"}) as container:
        stream = container.add_stream("libx264", rate=Fraction(100))
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        for _ in range(n):
            frame = av.VideoFrame.from_ndarray(
                rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), format="rgb24"
            )
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    if truncate:
        _truncate(path, truncate)
    return path


def test_truncated_mp4_keeps_its_header_count(tmp_path):
    from flylib.recordings.frame_counts import video_frame_count

    path = _mp4(tmp_path / "cam.mp4", truncate=0.6)
    assert video_frame_count(path) == 60  # what the header says...
    assert sum(1 for _ in io.VideoReader(path).stream_frames()) < 60  # ...is not what decodes


def test_detector_fails_on_a_truncated_video(tmp_path):
    from flylib.pose2d import stream

    path = _mp4(tmp_path / "cam.mp4", truncate=0.6)
    prefetcher = stream.BlockPrefetcher("s", [path], block_size=8, depth=2, workers=1)
    prefetcher.start()
    with pytest.raises(
        FootageError,
        match=rf"^{path}: its header says 60 frames but only \d+ decode; "
        "the file is truncated",
    ):
        while prefetcher.get() is not stream.END_OF_STREAM:
            pass
    whole = stream.BlockPrefetcher(
        "s", [_mp4(tmp_path / "whole.mp4")], block_size=8, depth=2, workers=1
    )
    whole.start()
    n = 0
    while (block := whole.get()) is not stream.END_OF_STREAM:
        n += len(block)
    assert n == 60


def test_import_against_truncated_footage_names_both_files_and_counts(tmp_path):
    from flylib.config import Config
    from flylib.interop import import_points2d
    from flylib.pipeline.demo import demo_import_spec, make_demo

    config = Config.default()
    make_demo(config, tmp_path, frames=6, seed=0)
    spec = demo_import_spec(config)
    video = tmp_path / "camera_1.mp4"
    assert import_points2d(import_target(config), tmp_path, spec).pts2d.shape[1] == 6
    data = video.read_bytes()
    moov, mdat = data.find(b"moov"), data.find(b"mdat")
    if moov > mdat:  # index at the end: a cut would lose the header; rebuild it first
        _mp4_from(video, tmp_path / "faststart.mp4")
    _truncate(video, 0.5)
    with pytest.raises(
        ImportFormatError,
        match=rf"{spec['files']['rm']}: 6 frames but view 'rm' footage "
        rf"has [0-5] \({video}\); .*re-copy truncated footage",
    ):
        import_points2d(import_target(config), tmp_path, spec)


def _mp4_from(video: Path, tmp: Path) -> None:
    """Rewrite ``video`` with its index first (same frames)."""
    import av

    frames = [f.to_ndarray(format="rgb24") for f in av.open(str(video)).decode(video=0)]
    with av.open(str(tmp), "w", options={"movflags": "faststart"}) as container:
        stream = container.add_stream("libx264", rate=Fraction(100))
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuv420p"
        for image in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    tmp.replace(video)


@pytest.mark.parametrize("n_footage", [4, 8])
def test_visualization_errors_when_footage_and_result_differ_in_length(tmp_path, n_footage):
    from flylib.config import Config
    from flylib.results import PoseResult
    from flylib.visualization import render_videos

    config = Config.default()
    views = config.view_names()
    rig = config_rig(config, {v: (48, 64) for v in views})
    skeleton = config.skeleton()
    result = PoseResult(
        rig, skeleton, np.full((7, 6, 38, 2), np.nan), pts3d=np.full((6, 38, 3), np.nan)
    )
    footage = {}
    for v in views:
        footage[v] = [_mp4(tmp_path / f"{v}.mp4", n=6 if v != "rm" else n_footage)]
    with pytest.raises(
        FootageError,
        match=rf"^{tmp_path / 'rm.mp4'}: footage of view 'rm' has "
        rf"{n_footage if n_footage < 6 else 'more'} frames but the result has 6",
    ):
        render_videos(config.visualization, result, footage, tmp_path / "out", progress=False)
    assert not list((tmp_path / "out").glob("*.mp4"))
