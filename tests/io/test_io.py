"""Frame I/O: video and image-sequence readers, the MP4 writer, bad footage."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flylib import io
from flylib.errors import FootageError

H, W = 48, 64


def _index_frames(n: int) -> np.ndarray:
    """Frames whose brightness encodes their index (4 grey levels per frame)."""
    frames = np.zeros((n, H, W, 3), dtype=np.uint8)
    for i in range(n):
        frames[i] = 10 + 4 * i
        frames[i, : H // 2, : W // 2, 0] = 200  # some structure, same every frame
    return frames


def _frame_index(frame: np.ndarray) -> int:
    return int(round((np.median(frame[H // 2 :, W // 2 :]) - 10) / 4))


@pytest.fixture(scope="module")
def indexed_video(tmp_path_factory) -> Path:
    """A 50-frame H.264 MP4 with B-frames and a keyframe every 10 frames."""
    path = tmp_path_factory.mktemp("video") / "indexed.mp4"
    with io.VideoWriter(path, fps=100, crf=10, options={"g": 10, "bf": 2}) as writer:
        writer.write_frames(_index_frames(50))
    return path


def test_video_roundtrip_and_frame_accurate_access(indexed_video):
    reader = io.open_reader(indexed_video)
    assert isinstance(reader, io.VideoReader)
    assert reader.count() == 50 and reader.fps() == pytest.approx(100)
    assert reader.frame_size() == (H, W)
    frames = reader[:]
    assert frames.shape == (50, H, W, 3) and frames.dtype == np.uint8
    assert [_frame_index(f) for f in frames] == list(range(50))
    picked = reader[[37, 3, 21, 3, 49, 0]]
    assert [_frame_index(f) for f in picked] == [37, 3, 21, 3, 49, 0]
    np.testing.assert_array_equal(picked, frames[[37, 3, 21, 3, 49, 0]])
    np.testing.assert_array_equal(reader[26], frames[26])
    np.testing.assert_array_equal(reader[-1], frames[49])
    np.testing.assert_array_equal(reader[12:40:7], frames[12:40:7])
    blocks = list(reader.stream_blocks(start=23, block_size=8))
    assert [len(b) for b in blocks] == [8, 8, 8, 3]
    np.testing.assert_array_equal(np.concatenate(blocks), frames[23:])
    with pytest.raises(IndexError, match="frame 50"):
        reader[[2, 50]]


def test_writer_accepts_torch_float_gray_and_crops_to_even(tmp_path):
    path = tmp_path / "odd.mp4"
    frame = np.full((21, 33, 3), 128, np.uint8)
    with io.VideoWriter(path, fps=25, crf=0) as writer:
        writer.write_frame(torch.from_numpy(frame))
        writer.write_frame(np.full((21, 33), 300.0))  # gray float, clipped to 255
        writer.write_frames(torch.from_numpy(np.stack([frame, frame])))
    assert writer.frames_written == 4
    out = io.VideoReader(path)[:]
    assert out.shape == (4, 20, 32, 3)
    assert abs(int(np.median(out[0])) - 128) <= 2 and int(np.median(out[1])) >= 250
    with io.VideoWriter(tmp_path / "small.mp4") as writer:
        writer.write_frame(frame)
        with pytest.raises(ValueError, match="smaller"):
            writer.write_frame(frame[:10])


def test_wrong_frame_rate_and_missing_count_still_decode_every_frame(tmp_path):
    # 1/5 fps, like the DeepFly3D sample's container, and an MKV without a frame count
    slow = tmp_path / "slow.mp4"
    with io.VideoWriter(slow, fps=0.2, options={"g": 5}) as writer:
        writer.write_frames(_index_frames(12))
    reader = io.VideoReader(slow)
    assert reader.fps() == pytest.approx(0.2)
    assert [_frame_index(f) for f in reader[:]] == list(range(12))
    assert [_frame_index(f) for f in reader[[11, 4]]] == [11, 4]
    mkv = tmp_path / "nocount.mkv"
    with io.VideoWriter(mkv, fps=30) as writer:
        writer.write_frames(_index_frames(9))
    reader = io.VideoReader(mkv)
    assert reader.count() is None
    assert [_frame_index(f) for f in reader[:]] == list(range(9))
    assert [_frame_index(f) for f in reader[[7, 2]]] == [7, 2]


def test_corrupt_and_truncated_videos_raise_footage_error(indexed_video, tmp_path):
    data = indexed_video.read_bytes()
    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(b"not a video at all" * 64)
    truncated = tmp_path / "truncated.mp4"
    truncated.write_bytes(data[: len(data) // 2])
    for bad in (garbage, truncated):
        with pytest.raises(FootageError, match=bad.name):
            io.open_reader(bad)[:]
    with pytest.raises(FootageError, match="not found"):
        io.VideoReader(tmp_path / "missing.mp4")


def test_video_corrupted_mid_stream_names_the_frame(tmp_path):
    path = tmp_path / "noisy.mp4"
    rng = np.random.default_rng(0)
    with io.VideoWriter(path, fps=30, options={"g": 100}) as writer:
        writer.write_frames(rng.integers(0, 255, size=(30, H, W, 3), dtype=np.uint8))
    data = bytearray(path.read_bytes())
    start = len(data) // 3
    data[start : start + len(data) // 4] = bytes([0x55]) * (len(data) // 4)
    path.write_bytes(bytes(data))
    with pytest.raises(FootageError, match=r"noisy\.mp4: decoding failed at frame \d+"):
        io.VideoReader(path)[:]


# --- image sequences --------------------------------------------------------


def test_image_sequence_natural_order_gray_alpha_and_workers(tmp_path):
    frames = _index_frames(12)
    for i, frame in enumerate(frames):
        if i == 3:  # a grayscale file
            cv2.imwrite(str(tmp_path / f"img_{i}.png"), frame[..., 0])
        elif i == 5:  # an RGBA file
            bgra = np.concatenate([frame[..., ::-1], np.full((H, W, 1), 7, np.uint8)], axis=-1)
            cv2.imwrite(str(tmp_path / f"img_{i}.png"), bgra)
        else:
            cv2.imwrite(str(tmp_path / f"img_{i}.png"), frame[..., ::-1])
    (tmp_path / "notes.txt").write_text("not an image")
    files = io.list_image_files(tmp_path)
    assert [f.name for f in files] == [f"img_{i}.png" for i in range(12)]  # 2 before 10
    for source in (tmp_path, str(tmp_path / "img_*.png"), files):
        reader = io.open_reader(source, workers=3)
        assert isinstance(reader, io.ImageSequenceReader) and reader.count() == 12
        out = reader[:]
        assert out.shape == (12, H, W, 3)
        np.testing.assert_array_equal(np.delete(out, [3], axis=0), np.delete(frames, [3], axis=0))
        np.testing.assert_array_equal(out[3], np.repeat(frames[3][..., :1], 3, axis=-1))
    serial = io.ImageSequenceReader(files, workers=1)
    np.testing.assert_array_equal(serial[[11, 0, 10]], out[[11, 0, 10]])
    np.testing.assert_array_equal(np.concatenate(list(serial.stream_blocks(block_size=5))), out)
    assert serial.fps() is None


def test_corrupt_image_names_file_and_frame(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.zeros((8, 8, 3), np.uint8))
    (tmp_path / "f1.png").write_bytes(b"\x89PNG broken")
    reader = io.open_reader(tmp_path)
    with pytest.raises(FootageError, match=r"f1\.png: cannot decode frame 1"):
        reader[:]
    with pytest.raises(IndexError, match="out of range"):
        reader[[5]]


def test_open_reader_dispatch_errors(tmp_path, indexed_video):
    assert isinstance(io.open_reader([indexed_video]), io.VideoReader)
    assert isinstance(io.open_reader(str(indexed_video.parent / "*.mp4")), io.VideoReader)
    with pytest.raises(FootageError, match="matches nothing"):
        io.open_reader(tmp_path / "nothing_*.mp4")
    with pytest.raises(FootageError, match="empty file list"):
        io.open_reader([])
    with pytest.raises(FootageError, match="one video or an image sequence"):
        io.open_reader([indexed_video, indexed_video])


def test_to_numpy_and_to_torch_share_memory():
    a = np.arange(6, dtype=np.uint8).reshape(2, 3)
    t = io.to_torch(a)
    t[0, 0] = 42
    assert a[0, 0] == 42
    assert io.to_numpy(a) is a
    np.testing.assert_array_equal(io.to_numpy(t), a)


# --- the real recording -------------------------------------------------------


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_deepfly3d_sample_video_and_images_give_the_same_frames(df3d_sample_dir):
    video = io.open_reader(df3d_sample_dir / "camera_2.mp4")
    assert video.fps() == pytest.approx(0.2)  # the container's quirk
    images = io.open_reader(df3d_sample_dir / "camera_2_img_*.jpg")
    assert images.count() == 15
    v, im = video[:], images[:]
    assert v.shape == im.shape == (15, 480, 960, 3)
    diff = np.abs(v.astype(np.int16)[:, None] - im.astype(np.int16)[None]).mean(axis=(2, 3, 4))
    assert diff.diagonal().max() < 3.0  # lossy codecs, same content
    assert (diff.argmin(axis=1) == np.arange(15)).all()  # and in the same order
    np.testing.assert_array_equal(video[[14, 0, 7]], v[[14, 0, 7]])


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this OS")
def test_worker_counts_follow_the_cpu_affinity_not_the_machine(tmp_path):
    # a cluster job bound to one core of a big node must not start a thread per node core
    code = (
        "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
        "from flylib.resources import usable_cpus; from flylib.io.images import _default_workers; "
        "print(usable_cpus(), _default_workers())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "1"]
