"""Footage frames for the GUI, as JPEG: one open decoder per view, a small LRU cache and a
background decoder that fills a second cache ahead of the user.

A video keeps one PyAV container open: the next frame costs one decode; any other is reached by
decoding on or by a seek to the keyframe before it, whichever decodes fewer frames (keyframes and
timestamps are indexed once). A cold random jump thus costs up to one keyframe interval (GOP): the
whole video on footage with a single keyframe. So from a view's first request on, a background
thread decodes the video in order into the fill cache (each frame also at half size, for playback):
all of it when its JPEGs fit ``fill_bytes``, else a window around the last requested frame. It
pauses while a request decodes, and a request for a frame the fill decoder is nearer to waits for
it instead of decoding the same frames twice. Image sequences are read by index (:class:`flylib.io.ImageSequenceReader`)."""

from __future__ import annotations

import logging
import os
import sys
import threading
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import FootageError

log = logging.getLogger(__name__)

#: Always decode forward (rather than seek) when the wanted frame is at most this far ahead.
FORWARD_GAP = 24
JPEG_QUALITY = 85
#: JPEG bytes one view may hold in its fill cache (7 views: about 450 MB at most).
FILL_BYTES = 64 * 2**20
#: Longest a request waits for the fill decoder when that one is nearer its frame.
FILL_WAIT_S = 10.0
#: Frames kept behind the last requested one when only a window fits (for stepping back).
_WINDOW_BEHIND = 0.25


def half_size(image: np.ndarray) -> np.ndarray:
    """``image`` at half its width and height (area-averaged: playback's copy)."""
    import cv2

    return cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)


def encode_jpeg(image_bgr: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """``(H, W, 3)`` uint8 BGR -> JPEG bytes."""
    import cv2

    ok, data = cv2.imencode(".jpg", image_bgr, [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise FootageError("JPEG encoding failed")
    return data.tobytes()


class _VideoFrames:
    """Random access to one video with a persistent decoder."""

    def __init__(self, path: Path, index: tuple | None = None):
        from ..io import VideoReader

        self.reader = VideoReader(path)
        self.pts, self.keyframes = index if index is not None else self._index()
        self._container = None
        self._frames = None  # the decoder's frame iterator
        self._next: int | None = None  # index of the frame the iterator yields next

    def _index(self) -> tuple[list[int] | None, np.ndarray | None]:
        """Timestamps in frame order and the keyframes' frame indices (one demux pass)."""
        import av

        pts, key = [], []
        try:
            with av.open(str(self.reader.path)) as container:
                for packet in container.demux(container.streams.video[0]):
                    if packet.size == 0:
                        continue
                    if packet.pts is None:
                        return None, None
                    pts.append(int(packet.pts))
                    if packet.is_keyframe:
                        key.append(int(packet.pts))
        except (av.FFmpegError, OSError) as exc:
            raise FootageError(
                f"{self.reader.path}: cannot index the video ({exc}); re-copy or re-export it"
            ) from None
        pts.sort()
        index_of = {p: i for i, p in enumerate(pts)}
        return (pts or None), np.array(sorted(index_of[k] for k in key), dtype=int)

    def __len__(self) -> int:
        return len(self.pts) if self.pts is not None else int(self.reader.count() or 0)

    def spawn(self) -> _VideoFrames:
        """A second decoder of the same file (sharing the index)."""
        return _VideoFrames(self.reader.path, (self.pts, self.keyframes))

    def _keyframe_before(self, index: int) -> int:
        if self.keyframes is None or not len(self.keyframes):
            return 0
        k = int(np.searchsorted(self.keyframes, index, side="right")) - 1
        return int(self.keyframes[max(k, 0)])

    def _forward_is_cheaper(self, index: int) -> bool:
        """Decoding on from the current position costs fewer frames than a seek would."""
        if self._frames is None or self._next is None or index < self._next:
            return False
        return index - self._next <= max(FORWARD_GAP, index - self._keyframe_before(index))

    def _restart(self, index: int) -> None:
        import av

        if self._container is None:
            self._container = av.open(str(self.reader.path))
            stream = self._container.streams.video[0]
            stream.thread_type = "SLICE"  # frame threading would delay every single-frame read
        stream = self._container.streams.video[0]
        if self.pts is not None:
            self._container.seek(self.pts[index], stream=stream, backward=True, any_frame=False)
        else:
            self._container.seek(0, stream=stream)
        self._frames = self._container.decode(stream)
        self._next = None  # unknown until a frame's timestamp says

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as ``(H, W, 3)`` uint8 BGR."""
        if not self._forward_is_cheaper(index):
            self._restart(index if self.pts is not None else 0)
            if self.pts is None:
                self._next = 0
        index_of = self._index_of()
        for frame in self._frames:
            i = index_of.get(frame.pts, self._next) if index_of else self._next
            if i is None:
                continue
            self._next = i + 1
            if i == index:
                return frame.to_ndarray(format="bgr24")
            if i > index:
                break
        self._frames = None
        raise FootageError(f"{self.reader.path}: frame {index} could not be decoded")

    def _index_of(self) -> dict[int, int] | None:
        if self.pts is None:
            return None
        if not hasattr(self, "_index_map"):
            self._index_map = {p: i for i, p in enumerate(self.pts)}
        return self._index_map

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
            self._container = None
            self._frames = None


class _ImageFrames:
    def __init__(self, files: Sequence[Path]):
        from ..io import ImageSequenceReader

        self.reader = ImageSequenceReader(list(files), workers=1)

    def __len__(self) -> int:
        return self.reader.count()

    def spawn(self) -> _ImageFrames:
        return _ImageFrames(self.reader.files)

    def read(self, index: int) -> np.ndarray:
        rgb = self.reader[[index]][0]
        return np.ascontiguousarray(rgb[..., ::-1])

    def close(self) -> None:
        self.reader.close()


class FrameSource:
    """JPEG frames of one view (``files``: one video or images in frame order; none: dark frames
    of ``size`` ``(height, width)``), with an LRU cache of ``cache_frames`` and a fill cache of
    ``fill_bytes`` (0: none). One decoder follows the requests, the other fills the caches
    (:meth:`prefetch` and the fill thread) without moving the first away from the user."""

    def __init__(
        self,
        files: Sequence[Path],
        size: tuple[int, int],
        cache_frames: int = 128,
        *,
        fill_bytes: int = FILL_BYTES,
    ):
        files = [Path(f) for f in files]
        self.size = (int(size[0]), int(size[1]))
        self._cache_lock = threading.Lock()
        self._lock = threading.Lock()  # the request decoder
        self._spare_lock = threading.Lock()  # the prefetch / fill decoder
        self._cache: OrderedDict[int, bytes] = OrderedDict()
        self.cache_frames = int(cache_frames)
        self._blank: bytes | None = None
        self._spare = None
        self.fill_bytes = int(fill_bytes)
        self._filled: dict[int, tuple[bytes, bytes]] = {}  # frame -> (JPEG, half-size JPEG)
        self._fill_window: int | None = None  # None: undecided; else frames the fill may hold
        self._anchor = 0  # the last requested frame
        self._requests = 0  # requests decoding now (the fill waits for them)
        self._fill_wake = threading.Condition()
        self._filled_wake = threading.Condition()  # a frame entered the fill cache
        self._fill_thread: threading.Thread | None = None
        self._closed = False
        if not files:
            self._frames = None
        elif len(files) == 1 and files[0].suffix.lower() not in {
            ".png",
            ".jpg",
            ".jpeg",
            ".tif",
            ".tiff",
            ".bmp",
        }:
            self._frames = _VideoFrames(files[0])
        else:
            self._frames = _ImageFrames(files)

    @property
    def has_footage(self) -> bool:
        return self._frames is not None

    def __len__(self) -> int:
        return 0 if self._frames is None else len(self._frames)

    def frame_size(self) -> tuple[int, int] | None:
        """``(height, width)`` of the footage (None without)."""
        return None if self._frames is None else tuple(self._frames.reader.frame_size())

    def _cached(self, index: int, small: bool = False) -> bytes | None:
        with self._cache_lock:
            both = self._filled.get(index)
            if both is not None:
                return both[small]
            data = self._cache.get(index)
            if data is not None:
                self._cache.move_to_end(index)
            return data

    def _store(self, index: int, data: bytes) -> None:
        with self._cache_lock:
            self._cache[index] = data
            self._cache.move_to_end(index)
            while len(self._cache) > self.cache_frames:
                self._cache.popitem(last=False)

    def jpeg(self, index: int, small: bool = False) -> bytes:
        """Frame ``index`` as JPEG bytes (a dark placeholder without footage or past its end);
        ``small``: at half size if the fill made it (for playback: a quarter of the pixels)."""
        self._follow(index)
        cached = self._cached(index, small)
        if cached is not None:
            return cached
        if self._frames is None or index >= len(self._frames):
            if self._blank is None:
                self._blank = encode_jpeg(np.full((*self.size, 3), 24, np.uint8))
            return self._blank
        if self._fill_is_nearer(index):
            data = self._await_fill(index, FILL_WAIT_S, small)
            if data is not None:
                return data
        with self._fill_wake:
            self._requests += 1
        try:
            with self._lock:
                cached = self._cached(index)  # the prefetcher may have just made it
                if cached is not None:
                    return cached
                data = encode_jpeg(self._frames.read(index))
        finally:
            with self._fill_wake:
                self._requests -= 1
                self._fill_wake.notify_all()
        self._store(index, data)
        return data

    def prefetch(self, index: int) -> None:
        """Put frame ``index`` in the cache with the background decoder (no-op if there)."""
        if (
            self._frames is None
            or not 0 <= index < len(self._frames)
            or self._cached(index) is not None
        ):
            return
        image = self._spare_read(index)
        if image is not None:
            self._store(index, encode_jpeg(image))

    def _spare_read(self, index: int) -> np.ndarray | None:
        """Frame ``index`` decoded by the spare decoder (None once closed or filled)."""
        with self._spare_lock:
            if self._closed or index in self._filled:  # (the fill decodes past the cache's frames)
                return None
            if self._spare is None:
                self._spare = self._frames.spawn()
            return self._spare.read(index)

    def _fill_is_nearer(self, index: int) -> bool:
        """The fill decoder (decoding forward) reaches ``index`` in fewer decodes than ours."""
        spare, frames = self._spare, self._frames
        if (
            self._fill_thread is None
            or not self._fill_thread.is_alive()
            or spare is None
            or spare._next is None
            or not isinstance(frames, _VideoFrames)
        ):
            return False
        ahead = index - spare._next
        if ahead < 0 or ahead > FORWARD_GAP + index - spare._keyframe_before(index):
            return False
        own = (
            index - frames._next
            if frames._forward_is_cheaper(index)
            else index - frames._keyframe_before(index)
        )
        return ahead < own

    def _await_fill(self, index: int, timeout: float, small: bool = False) -> bytes | None:
        """Frame ``index`` (at half size with ``small``) once the fill has it, or None after
        ``timeout`` s."""
        import time

        deadline = time.monotonic() + timeout
        with self._filled_wake:
            while True:
                data = self._cached(index, small)
                if data is not None or self._closed or time.monotonic() > deadline:
                    return data
                if self._fill_thread is None or not self._fill_thread.is_alive():
                    return None
                self._filled_wake.wait(0.05)

    def _follow(self, index: int) -> None:
        """A request for ``index``: move the fill window there, start the fill thread."""
        if not isinstance(self._frames, _VideoFrames) or self.fill_bytes <= 0:
            return
        with self._fill_wake:
            self._anchor = int(index)
            if self._fill_thread is None and not self._closed:
                self._fill_thread = threading.Thread(
                    target=self._fill_loop, name="flylib-gui-fill", daemon=True
                )
                self._fill_thread.start()
            self._fill_wake.notify_all()

    @property
    def filled(self) -> int:
        """Frames in the fill cache now."""
        with self._cache_lock:
            return len(self._filled)

    def wait_filled(self, frames: int, timeout: float) -> bool:
        """Wait until the fill cache holds ``frames`` frames (True) or ``timeout`` s pass."""
        import time

        deadline = time.monotonic() + timeout
        while self.filled < frames:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True

    def _wanted(self) -> list[int]:
        """Frames the fill should hold now, nearest first ahead of the user."""
        n = len(self._frames)
        anchor = min(max(self._anchor, 0), n - 1)
        if self._fill_window is None or self._fill_window >= n:
            return [*range(anchor, n), *range(anchor)]
        behind = int(self._fill_window * _WINDOW_BEHIND)
        start = max(0, anchor - behind)
        stop = min(n, start + self._fill_window)
        return [*range(anchor, stop), *range(start, anchor)]

    def _next_to_fill(self) -> int | None:
        wanted = self._wanted()
        with self._cache_lock:
            keep = set(wanted)
            for index in [i for i in self._filled if i not in keep]:
                del self._filled[index]  # outside the window: the user moved on
            return next((i for i in wanted if i not in self._filled), None)

    def _fill_loop(self) -> None:
        if sys.platform == "linux":  # a thread's own nice: the page's requests and browser first
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
        while True:
            with self._fill_wake:
                while not self._closed and (self._requests or self._next_to_fill() is None):
                    self._fill_wake.wait(0.5)
                if self._closed:
                    return
                index = self._next_to_fill()
            if index is None:
                continue
            try:
                image = self._spare_read(index)
            except (FootageError, OSError, ValueError) as exc:  # the request reports it
                log.debug("%s: background decode of frame %d failed: %s", self, index, exc)
                return
            if image is None:
                continue
            made = encode_jpeg(image), encode_jpeg(half_size(image))
            if self._fill_window is None:
                frames = max(1, self.fill_bytes // max(1, int(len(b"".join(made)) * 1.25)))
                self._fill_window = min(frames, len(self._frames))
            with self._cache_lock:
                self._filled[index] = made
            with self._filled_wake:
                self._filled_wake.notify_all()

    def close(self) -> None:
        with self._fill_wake:
            self._closed = True
            self._fill_wake.notify_all()
        if self._fill_thread is not None:
            self._fill_thread.join(timeout=5)
        with self._lock, self._spare_lock:  # a decoder closed under a request crashes PyAV
            for frames in (self._frames, self._spare):
                if frames is not None:
                    frames.close()
