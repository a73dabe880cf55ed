"""The frame-reader interface and the small helpers every reader shares."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FootageError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import UInt8

log = logging.getLogger(__name__)

VIDEO_EXTS = frozenset({".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".ts"})
IMAGE_EXTS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"})


class FrameReader(ABC):
    """Reads ``(T, H, W, 3)`` uint8 RGB frames from one footage source.

    Index with ``reader[key]``: ``reader[5]`` gives one ``(H, W, 3)`` frame, ``reader[[0, 3, 5]]``
    the listed frames in that order, ``reader[2:8:2]`` and ``reader[:]`` a sequential range, each as
    ``(T, H, W, 3)``. Use :meth:`stream_frames` / :meth:`stream_blocks` to walk a long source
    forward without holding it in memory. Readers are context managers.
    """

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:  # noqa: B027 (a no-op unless a reader holds something)
        """Release any resources held by the reader (no-op by default)."""

    @property
    @abstractmethod
    def name(self) -> str:
        """What the reader reads, for error messages (a path or a pattern)."""

    @abstractmethod
    def stream_frames(
        self, *, start: int = 0, stop: int | None = None, step: int = 1
    ) -> Iterator[UInt8[np.ndarray, "H W 3"]]:
        """Yield ``(H, W, 3)`` uint8 RGB frames of ``range(start, stop, step)`` in one pass."""

    @abstractmethod
    def _read_indices(self, indices: list[int]) -> np.ndarray:
        """Decode the listed frames (any order, repeats allowed) to ``(T, H, W, 3)``."""

    @abstractmethod
    def count(self) -> int | None:
        """Best-effort frame count (a progress-bar hint), or ``None`` when unknown."""

    def fps(self) -> float | None:
        """Frame rate in frames/s, or ``None`` when the source carries none."""
        return None

    def frame_size(self) -> tuple[int, int]:
        """``(height, width)`` of the frames, from the first frame."""
        first = next(iter(self.stream_frames(stop=1)), None)
        if first is None:
            raise FootageError(f"{self.name}: no frames could be decoded; check the footage")
        return int(first.shape[0]), int(first.shape[1])

    def stream_blocks(
        self,
        *,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        block_size: int = 64,
    ) -> Iterator[UInt8[np.ndarray, "T H W 3"]]:
        """Yield ``(T, H, W, 3)`` uint8 RGB blocks, ``T <= block_size``, of the frames of
        ``range(start, stop, step)`` in one forward pass."""
        if block_size < 1:
            raise ValueError(f"block_size must be >= 1, got {block_size}")
        buf: list[np.ndarray] = []
        for frame in self.stream_frames(start=start, stop=stop, step=step):
            buf.append(frame)
            if len(buf) == block_size:
                yield np.stack(buf)
                buf = []
        if buf:
            yield np.stack(buf)

    def __getitem__(
        self, key: int | list[int] | slice | np.ndarray
    ) -> UInt8[np.ndarray, "H W 3"] | UInt8[np.ndarray, "T H W 3"]:
        if isinstance(key, (int, np.integer)):
            index = int(key)
            if index < 0:
                index += self._length_for_negative_index()
            if index < 0:
                raise IndexError(f"{self.name}: frame index {key} is out of range")
            return self._read_indices([index])[0]
        if isinstance(key, slice):
            if key.step is not None and key.step <= 0:
                raise ValueError(f"{self.name}: only positive slice steps are supported")
            if (key.start or 0) < 0 or (key.stop is not None and key.stop < 0):
                start, stop, step = key.indices(self._length_for_negative_index())
            else:
                start, stop, step = key.start or 0, key.stop, key.step or 1
            frames = list(self.stream_frames(start=start, stop=stop, step=step))
            if not frames:
                raise IndexError(f"{self.name}: the slice {key} selects no frames")
            return np.stack(frames)
        if isinstance(key, (list, tuple, np.ndarray)):
            indices = [int(i) for i in np.asarray(key).ravel()]
            if not indices:
                raise IndexError(f"{self.name}: the index list is empty")
            if min(indices) < 0:
                n = self._length_for_negative_index()
                indices = [i + n if i < 0 else i for i in indices]
            return self._read_indices(indices)
        raise TypeError(f"frame index must be an int, list or slice, not {type(key).__name__}")

    def _length_for_negative_index(self) -> int:
        n = self.count()
        return n if n is not None else sum(1 for _ in self.stream_frames())


def is_video_file(path: str | Path) -> bool:
    """Whether ``path`` names an existing video file (by extension)."""
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_EXTS


def to_numpy(frames) -> np.ndarray:
    """Frames (NumPy array, torch tensor or any array-like) as a host NumPy array."""
    if isinstance(frames, np.ndarray):
        return frames
    if hasattr(frames, "detach"):  # torch.Tensor, possibly on a GPU
        return frames.detach().cpu().numpy()
    return np.asarray(frames)


def to_torch(frames):
    """Frames as a torch tensor, zero-copy where possible (NumPy and DLPack arrays)."""
    import torch

    if isinstance(frames, torch.Tensor):
        return frames
    if isinstance(frames, np.ndarray):
        return torch.from_numpy(frames)
    if hasattr(frames, "__dlpack__"):
        return torch.from_dlpack(frames)
    return torch.from_numpy(np.asarray(frames))


def as_rgb_uint8(image: np.ndarray) -> np.ndarray:
    """Coerce one decoded image to ``(H, W, 3)`` uint8 RGB (gray broadcast, alpha dropped)."""
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    elif image.shape[-1] > 3:
        image = image[..., :3]
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(image)
