"""Video files through PyAV: a frame-accurate reader and an incremental H.264 writer."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import FootageError
from ..resources import usable_cpus
from .base import FrameReader, as_rgb_uint8, to_numpy

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import UInt8

log = logging.getLogger(__name__)

# Decoding keeps walking forward instead of seeking when the next wanted frame is at most this
# many frames ahead: cheaper than a seek back to a keyframe.
_SEEK_GAP = 48


def _av():
    import av

    return av


class VideoReader(FrameReader):
    """Frame-accurate decode of one video file through PyAV (in-process FFmpeg).

    Frames are numbered in presentation order from 0. Random access seeks to the keyframe before
    the wanted frame and decodes forward, identifying frames by their presentation timestamps (read
    once from the packet index, without decoding), so neither a wrong frame rate nor a wrong frame
    count in the container header affects which frame is returned. ``count`` and ``fps`` are
    header values, used only as hints. ``threads``: decoder threads (frame + slice threading);
    ``0`` or ``None`` lets FFmpeg choose from the CPUs; never more than
    :func:`~flylib.resources.usable_cpus` (under a one-thread budget FFmpeg decodes in the calling
    thread).
    """

    def __init__(self, path: str | Path, *, threads: int | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FootageError(
                f"{self.path}: video file not found; check the path or the [[sources]] pattern"
            )
        self.threads = threads or 0
        self._pts_index: list[int] | None = None
        self._pts_index_read = False
        self._header_values: dict | None = None

    @property
    def name(self) -> str:
        return str(self.path)

    def _open(self):
        av = _av()
        try:
            container = av.open(str(self.path))
        except (av.FFmpegError, OSError, UnicodeDecodeError) as exc:
            raise FootageError(
                f"{self.path}: cannot open the video ({exc}); the file is corrupt, truncated "
                "or not a video: re-copy or re-export it"
            ) from None
        if not container.streams.video:
            container.close()
            raise FootageError(f"{self.path}: the file holds no video stream")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        stream.thread_count = self.decoder_threads()
        return container, stream

    def decoder_threads(self) -> int:
        """FFmpeg's ``thread_count`` for the next open (``0``: FFmpeg's choice), read when the
        video is opened, so the :func:`~flylib.resources.thread_budget` in force then applies.

        FFmpeg's choice is kept with more than one CPU: the thread count changes how a truncated
        last packet surfaces (a decode error with one or two threads, a short stream with more;
        both end in a :class:`~flylib.errors.FootageError`).
        """
        cpus = usable_cpus()
        if cpus == 1:
            return 1
        return min(self.threads, cpus) if self.threads else 0

    def _decode_error(self, frame_index: int, exc: Exception) -> FootageError:
        return FootageError(
            f"{self.path}: decoding failed at frame {frame_index} ({exc}); the file is corrupt "
            "or truncated: re-copy or re-export it"
        )

    def pts_index(self) -> list[int] | None:
        """Presentation timestamps of every frame in order, read from the packets; ``None`` when
        they carry none (raw streams): readers then fall back to counting decoded frames."""
        if not self._pts_index_read:
            av = _av()
            container, stream = self._open()
            pts: list[int] = []
            try:
                with container:
                    for packet in container.demux(stream):
                        if packet.size == 0:
                            continue  # the demuxer's flush packet
                        if packet.pts is None:
                            pts = []
                            break
                        pts.append(int(packet.pts))
            except av.FFmpegError as exc:
                raise self._decode_error(len(pts), exc) from None
            self._pts_index = sorted(pts) or None
            self._pts_index_read = True
        return self._pts_index

    def stream_frames(
        self, *, start: int = 0, stop: int | None = None, step: int = 1, format: str = "rgb24"
    ) -> Iterator[UInt8[np.ndarray, "*frame"]]:
        """Yield frames of ``range(start, stop, step)`` in one forward pass.

        ``format="rgb24"``: ``(H, W, 3)`` uint8 RGB. ``"yuv420p"``: the decoder's planes as one
        ``(3 H / 2, W)`` uint8 array (Y, then U, then V), skipping the colour conversion so it can
        run on the GPU (see :meth:`color_tags`).
        """
        if step < 1:
            raise ValueError(f"step must be >= 1, got {step}")
        if stop is not None and stop <= start:
            return
        av = _av()
        container, stream = self._open()
        index_of: dict[int, int] | None = None
        if start > 0:
            pts = self.pts_index()
            if pts is not None:
                if start >= len(pts):
                    container.close()
                    return
                index_of = {p: i for i, p in enumerate(pts)}
                container.seek(pts[start], stream=stream, backward=True, any_frame=False)
        position = 0
        with container:
            decoded = container.decode(stream)
            while True:
                try:
                    frame = next(decoded)
                except StopIteration:
                    return
                except av.FFmpegError as exc:
                    raise self._decode_error(position, exc) from None
                if index_of is not None:
                    i = index_of.get(frame.pts)
                    if i is None:  # a frame the packet index does not know: count on
                        i = position
                else:
                    i = position
                position = i + 1
                if i < start:
                    continue
                if stop is not None and i >= stop:
                    return
                if (i - start) % step == 0:
                    yield frame.to_ndarray(format=format)

    def _read_indices(self, indices: list[int]) -> np.ndarray:
        wanted = sorted(set(indices))
        pts = self.pts_index()
        if pts is None:  # no timestamps: one sequential pass picks them out
            picked = {}
            for i, frame in enumerate(self.stream_frames(stop=wanted[-1] + 1)):
                if i in wanted:
                    picked[i] = frame
        else:
            picked = self._seek_and_pick(wanted, pts)
        missing = [i for i in wanted if i not in picked]
        if missing:
            raise IndexError(
                f"{self.path}: frame {missing[0]} is beyond the last decodable frame "
                f"({len(pts) if pts is not None else len(picked)} frames)"
            )
        return np.stack([picked[i] for i in indices])

    def _seek_and_pick(self, wanted: list[int], pts: list[int]) -> dict[int, np.ndarray]:
        av = _av()
        index_of = {p: i for i, p in enumerate(pts)}
        picked: dict[int, np.ndarray] = {}
        todo = [i for i in wanted if i < len(pts)]
        container, stream = self._open()
        with container:
            k = 0
            while k < len(todo):
                container.seek(pts[todo[k]], stream=stream, backward=True, any_frame=False)
                progressed = False
                try:
                    for frame in container.decode(stream):
                        i = index_of.get(frame.pts)
                        if i is None or i < todo[k]:
                            continue
                        if i > todo[k]:
                            break  # the wanted frame was not produced here
                        picked[i] = frame.to_ndarray(format="rgb24")
                        progressed = True
                        k += 1
                        if k == len(todo) or todo[k] - i > _SEEK_GAP:
                            break  # the next one is far ahead: seek instead
                except av.FFmpegError as exc:
                    raise self._decode_error(todo[k], exc) from None
                if not progressed:
                    break  # the decoder could not reach todo[k]
        return picked

    def _header(self) -> dict:
        """The stream header's values, read in one open of the container (then cached)."""
        if self._header_values is None:
            container, stream = self._open()
            with container:
                cc = stream.codec_context
                rate = stream.average_rate or stream.guessed_rate
                self._header_values = {
                    "frames": int(stream.frames or 0),
                    "fps": float(rate) if rate else None,
                    "pix_fmt": str(cc.pix_fmt) if cc.pix_fmt else None,
                    "colorspace": int(getattr(cc, "colorspace", 2) or 2),
                    "color_range": int(getattr(cc, "color_range", 0) or 0),
                    "size": (int(cc.height or 0), int(cc.width or 0)),
                }
        return self._header_values

    def count(self) -> int | None:
        """Frame count from the container header, or ``None`` when it is absent."""
        try:
            n = self._header()["frames"]
        except FootageError:
            return None
        return n if n > 0 else None

    def fps(self) -> float | None:
        """Average frame rate from the container header, or ``None`` when absent."""
        try:
            return self._header()["fps"]
        except FootageError:
            return None

    def pixel_format(self) -> str | None:
        """The decoder's pixel format (e.g. ``"yuv420p"``), or ``None`` when unknown."""
        return self._header()["pix_fmt"]

    def color_tags(self) -> tuple[str, str]:
        """``(matrix, range)`` of the YUV data: ``"bt709"``/``"bt601"``, ``"full"``/``"limited"``;
        untagged streams are BT.601 limited range, as FFmpeg assumes."""
        header = self._header()
        matrix = "bt709" if header["colorspace"] == 1 else "bt601"
        return matrix, ("full" if header["color_range"] == 2 else "limited")

    def frame_size(self) -> tuple[int, int]:
        """``(height, width)`` from the stream header."""
        h, w = self._header()["size"]
        if not h or not w:
            return super().frame_size()
        return h, w


class VideoWriter:
    """Incremental H.264 (libx264) MP4 encoder backed by PyAV; a context manager.

    The file is opened lazily on the first frame, whose size sets the encode size (rounded down to
    even, as ``yuv420p`` needs); later frames must be at least that large and are cropped to it.
    Frames may be NumPy or torch, ``(H, W, 3)`` RGB or ``(H, W)`` gray; non-uint8 values are
    clipped to ``[0, 255]``. ``codec`` is the FFmpeg encoder; ``crf`` the x264 constant rate factor
    (lower is better, 0 lossless in ``yuv444p``); ``preset`` the x264 speed preset
    (``"ultrafast"`` ... ``"veryslow"``); ``options`` further encoder options, passed as strings.
    """

    def __init__(
        self,
        path: str | Path,
        fps: float = 30.0,
        *,
        codec: str = "libx264",
        pix_fmt: str = "yuv420p",
        crf: int | None = None,
        preset: str | None = None,
        options: dict[str, Any] | None = None,
    ) -> None:
        if not fps or fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.path = Path(path)
        self.fps = float(fps)
        self.codec = codec
        self.pix_fmt = pix_fmt
        self.options = {str(k): str(v) for k, v in (options or {}).items()}
        if crf is not None:
            self.options["crf"] = str(crf)
        if preset is not None:
            self.options["preset"] = preset
        self.frames_written = 0
        self._container: Any = None
        self._stream: Any = None
        self._size: tuple[int, int] | None = None  # (height, width), even

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _open(self, height: int, width: int) -> None:
        av = _av()
        h, w = height & ~1, width & ~1
        if h == 0 or w == 0:
            raise ValueError(f"{self.path}: frames of {height}x{width} are too small to encode")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._container = av.open(str(self.path), mode="w")
        rate = Fraction(self.fps).limit_denominator(1_000_000)
        stream = self._container.add_stream(self.codec, rate=rate, options=self.options)
        stream.width, stream.height, stream.pix_fmt = w, h, self.pix_fmt
        self._stream = stream
        self._size = (h, w)
        log.debug("writing %s: %dx%d at %g fps", self.path, w, h, self.fps)

    def write_frame(self, frame) -> None:
        """Append one ``(H, W, 3)`` (or ``(H, W)``) frame."""
        av = _av()
        image = as_rgb_uint8(to_numpy(frame))
        if self._stream is None:
            self._open(image.shape[0], image.shape[1])
        h, w = self._size
        if image.shape[0] < h or image.shape[1] < w:
            raise ValueError(
                f"{self.path}: frame {self.frames_written} is {image.shape[0]}x{image.shape[1]}, "
                f"smaller than the video's {h}x{w}"
            )
        vframe = av.VideoFrame.from_ndarray(np.ascontiguousarray(image[:h, :w]), format="rgb24")
        for packet in self._stream.encode(vframe):
            self._container.mux(packet)
        self.frames_written += 1

    def write_frames(self, frames: Iterable | np.ndarray) -> None:
        """Append a ``(T, H, W, 3)`` batch or any iterable of frames or batches."""
        if hasattr(frames, "detach") or isinstance(frames, np.ndarray):
            array = to_numpy(frames)
            if array.ndim == 4 or (array.ndim == 3 and array.shape[-1] not in (1, 3, 4)):
                for frame in array:
                    self.write_frame(frame)
            else:
                self.write_frame(array)
            return
        for item in frames:
            self.write_frames(item)

    def close(self) -> None:
        """Flush the encoder and close the file (idempotent)."""
        if self._container is None:
            return
        try:
            for packet in self._stream.encode():
                self._container.mux(packet)
        finally:
            self._container.close()
            self._container = None
            self._stream = None
