"""The GUI's footage access (``flylib.gui.frames``) on single-keyframe H.264, the layout
of the real samples: the background fill decodes the video in order into its cache, so
a random jump is served from memory and is the same frame a fresh decode gives."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flylib.gui.frames import FrameSource, encode_jpeg, half_size

FRAMES = 40


def _frame_image(i: int) -> np.ndarray:
    """``(64, 96, 3)`` BGR frame whose grey level and bar position tell the frame number."""
    image = np.full((64, 96, 3), 30 + 5 * i, np.uint8)
    image[:, 2 * i : 2 * i + 4] = 255
    return image


@pytest.fixture(scope="module")
def one_keyframe_video(tmp_path_factory):
    """An H.264 video with a single keyframe (every later frame needs all before it)."""
    import av

    path = tmp_path_factory.mktemp("frames") / "camera_0.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 96, 64, "yuv420p"
        stream.options = {"g": "1000", "keyint_min": "1000", "sc_threshold": "0", "bf": "0"}
        for i in range(FRAMES):
            frame = av.VideoFrame.from_ndarray(_frame_image(i), format="bgr24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    with av.open(str(path)) as container:
        keys = sum(p.is_keyframe for p in container.demux(video=0) if p.size)
    assert keys == 1, "the fixture must have a single keyframe"
    return path


def _decoded(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).astype(int)


def test_the_fill_holds_every_frame_and_jumps_give_the_right_frame(one_keyframe_video):
    source = FrameSource([one_keyframe_video], (64, 96), cache_frames=2)
    try:
        source.jpeg(0)  # the page opened: the fill starts
        assert source.wait_filled(FRAMES, timeout=60)
        for i in np.random.default_rng(0).permutation(FRAMES):
            image = _decoded(source.jpeg(int(i)))
            assert np.abs(image - _frame_image(int(i))).mean() < 4, f"frame {i}"
            # playback's at half size, made by the fill (frame 0 too, requested before)
            small = _decoded(source.jpeg(int(i), small=True))
            half = cv2.resize(_frame_image(int(i)), (48, 32), interpolation=cv2.INTER_AREA)
            assert small.shape == half.shape and np.abs(small - half).mean() < 4, f"frame {i}"
        assert source._frames._next in (None, 1)  # the request decoder never had to move
    finally:
        source.close()


def test_a_small_budget_fills_a_window_that_follows_the_user(one_keyframe_video):
    image = FrameSource([one_keyframe_video], (64, 96), fill_bytes=0)._spare_read(0)
    one = len(encode_jpeg(image)) + len(encode_jpeg(half_size(image)))
    budget = int(one * 1.25 * 10)  # about ten frames (each at full and half size)
    source = FrameSource([one_keyframe_video], (64, 96), cache_frames=2, fill_bytes=budget)
    try:
        source.jpeg(20)
        assert source.wait_filled(8, timeout=60)
        held = sorted(source._filled)
        assert len(held) <= 12 and all(18 <= i < 32 for i in held), held
        image = _decoded(source.jpeg(25))
        assert np.abs(image - _frame_image(25)).mean() < 4
    finally:
        source.close()


def test_no_fill_when_switched_off(one_keyframe_video):
    source = FrameSource([one_keyframe_video], (64, 96), fill_bytes=0)
    try:
        image = _decoded(source.jpeg(33))
        assert np.abs(image - _frame_image(33)).mean() < 4
        assert source.filled == 0 and source._fill_thread is None
    finally:
        source.close()


def test_a_jump_the_fill_is_nearer_to_waits_for_it(one_keyframe_video, monkeypatch):
    """While the fill decodes forward, a jump ahead of it is served by the fill rather
    than a second decoder working through the same frames (the request decoder stays)."""
    import time

    from flylib.gui import frames as frames_module

    real = frames_module.encode_jpeg

    def slow_encode(image, quality=frames_module.JPEG_QUALITY):
        time.sleep(0.02)  # a real frame's decode + encode, so the fill takes a while
        return real(image, quality)

    monkeypatch.setattr(frames_module, "encode_jpeg", slow_encode)
    source = FrameSource([one_keyframe_video], (64, 96), cache_frames=2)
    try:
        source.jpeg(0)
        assert source.wait_filled(4, timeout=30)
        position = source._frames._next
        assert source.filled < FRAMES - 5  # still filling
        image = _decoded(source.jpeg(FRAMES - 5))
        assert np.abs(image - _frame_image(FRAMES - 5)).mean() < 4
        assert source._frames._next == position  # served by the fill
    finally:
        source.close()


def test_closing_while_requests_decode_does_not_crash(one_keyframe_video):
    # the GUI's session closed (Ctrl+C, a test's teardown) with frame requests still decoding:
    # PyAV crashed the process when the container was closed under a decode
    import random
    import threading
    import time

    for _ in range(20):
        source = FrameSource([one_keyframe_video], (64, 96), 2, fill_bytes=0)
        stop = threading.Event()

        def requests(source=source, stop=stop):
            while not stop.is_set():
                source.jpeg(random.randrange(FRAMES))  # mostly seeks: no cache to help

        threads = [threading.Thread(target=requests) for _ in range(2)]
        for thread in threads:
            thread.start()
        time.sleep(0.1)
        source.close()
        stop.set()
        for thread in threads:
            thread.join()
