"""Frame I/O: readers for video files and image sequences, and an MP4 writer.

:func:`open_reader` resolves a footage source once to a :class:`VideoReader` (PyAV) or an
:class:`ImageSequenceReader` (OpenCV); both yield ``(T, H, W, 3)`` uint8 RGB frames by index
(``reader[i]``, ``reader[[0, 3]]``, ``reader[2:8]``) or forward streaming (``stream_frames``,
``stream_blocks``). :class:`VideoWriter` encodes frames to H.264 MP4 one frame or block at a time.
"""

from __future__ import annotations

import glob
from pathlib import Path

from ..errors import FootageError
from .base import IMAGE_EXTS, VIDEO_EXTS, FrameReader, is_video_file, to_numpy, to_torch
from .images import ImageSequenceReader, list_image_files, natural_key
from .video import VideoReader, VideoWriter

__all__ = [
    "FrameReader",
    "VideoReader",
    "ImageSequenceReader",
    "VideoWriter",
    "open_reader",
    "is_video_file",
    "list_image_files",
    "natural_key",
    "to_numpy",
    "to_torch",
    "VIDEO_EXTS",
    "IMAGE_EXTS",
]


def open_reader(
    source: str | Path | list | tuple,
    *,
    workers: int | None = None,
    threads: int | None = None,
    on_corrupt: str = "error",
) -> FrameReader:
    """Open the right :class:`FrameReader` (:class:`VideoReader` or :class:`ImageSequenceReader`)
    for a footage source.

    ``source`` is a video file; a directory of images; a glob pattern (matching one video, or
    images); or an explicit list of files (one video, or an image sequence already in frame order,
    read as given). ``workers`` (image sequences) and ``threads`` (videos) are decode threads
    (``0``/``None``: automatic). ``on_corrupt``, for image sequences: ``"error"`` fails on a
    corrupt or truncated image naming it, ``"missing"`` yields a black frame and records it. Raises
    :class:`FootageError` if the source does not exist, matches nothing, or mixes several videos.
    """
    if isinstance(source, (list, tuple)):
        files = [Path(f) for f in source]
        if not files:
            raise FootageError(
                "open_reader got an empty file list; the footage pattern matched nothing"
            )
        videos = [f for f in files if f.suffix.lower() in VIDEO_EXTS]
        if videos:
            if len(files) > 1:
                raise FootageError(
                    f"{files[0].parent}: a source must be one video or an image sequence, got "
                    f"{len(files)} files including {videos[0].name}; narrow the pattern"
                )
            return VideoReader(videos[0], threads=threads)
        return ImageSequenceReader(files, workers=workers, on_corrupt=on_corrupt)
    path = Path(source)
    if path.is_file():
        if path.suffix.lower() in IMAGE_EXTS:
            return ImageSequenceReader([path], workers=workers, on_corrupt=on_corrupt)
        return VideoReader(path, threads=threads)
    if path.is_dir():
        return ImageSequenceReader.from_pattern(path, workers=workers, on_corrupt=on_corrupt)
    matches = sorted(glob.glob(str(source)))
    if not matches:
        raise FootageError(f"{source}: no such file or directory, and the pattern matches nothing")
    if len(matches) == 1 and Path(matches[0]).suffix.lower() in VIDEO_EXTS:
        return VideoReader(matches[0], threads=threads)
    return open_reader(
        [Path(m) for m in list_image_files(source)],
        workers=workers,
        threads=threads,
        on_corrupt=on_corrupt,
    )
