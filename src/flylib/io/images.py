"""Image sequences through OpenCV: naturally sorted files, decoded on a thread pool."""

from __future__ import annotations

import glob
import logging
import re
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FootageError
from ..resources import usable_cpus
from .base import IMAGE_EXTS, FrameReader, as_rgb_uint8

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import UInt8

_DIGITS = re.compile(r"(\d+)")
#: The frame number in an image's name: the last number of its stem (``img_007`` -> 7).
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")

log = logging.getLogger(__name__)

#: What an image sequence reader does with a corrupt or truncated image: ``error`` fails naming the
#: file; ``missing`` warns and yields a black frame, its index in ``corrupt_frames``.
ON_CORRUPT = ("error", "missing")


def image_damage(data: bytes) -> str | None:
    """Why an encoded JPEG or PNG is incomplete, or ``None`` when it looks whole.

    OpenCV decodes a truncated JPEG without an error (libjpeg fills the missing rows with grey and
    only prints "Premature end of JPEG file"), so the encoded bytes are checked: a JPEG must end its
    last scan with the EOI marker (``FFD9``; it cannot occur inside entropy-coded data), a PNG must
    hold its ``IEND`` chunk.
    """
    if data[:2] == b"\xff\xd8" and data.rfind(b"\xff\xd9") < data.rfind(b"\xff\xda"):
        return "truncated JPEG: no end-of-image marker after its last scan"
    if data[:8] == b"\x89PNG\r\n\x1a\n" and b"IEND" not in data[-64:]:
        return "truncated PNG: no IEND chunk"
    return None


def natural_key(path: str | Path) -> tuple:
    """Sort key that orders embedded numbers by value (``img_2`` before ``img_10``)."""
    parts = _DIGITS.split(str(path))
    return tuple((0, int(p), p) if p.isdigit() else (1, 0, p.lower()) for p in parts)


def _missing_name(template: Path, number: int) -> str:
    """``template``'s name with its frame number replaced by ``number`` (same zero padding)."""
    found = _LAST_NUMBER.search(template.stem)
    digits = found.group(1)
    text = (
        str(number).zfill(len(digits))
        if digits.startswith("0") and len(digits) > 1
        else str(number)
    )
    return f"{template.stem[: found.start()]}{text}{template.stem[found.end() :]}{template.suffix}"


def sequence_gap(files: list[Path]) -> str | None:
    """Why the frame numbers in an image sequence's file names do not run one by one, or ``None``
    when they do (or some name holds no number: then the order is the frame). The number in each
    image's name is its frame (the last number of its stem), so a missing image is a missing
    frame, never a shift of every later frame by one."""
    files = [Path(f) for f in files]
    found = [_LAST_NUMBER.search(f.stem) for f in files]
    if len(files) < 2 or any(m is None for m in found):
        return None
    by_number: dict[int, Path] = {}
    for path, match in zip(files, found):
        number = int(match.group(1))
        if number in by_number:
            return (
                f"{path.parent}: images {by_number[number].name} and {path.name} both number "
                f"frame {number}; keep one image per frame"
            )
        by_number[number] = path
    numbers = sorted(by_number)
    missing = sorted(set(range(numbers[0], numbers[-1] + 1)) - set(numbers))
    if not missing:
        return None
    names = [_missing_name(by_number[max(n for n in numbers if n < m)], m) for m in missing[:5]]
    more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
    return (
        f"{files[0].parent}: the image sequence {by_number[numbers[0]].name} .. "
        f"{by_number[numbers[-1]].name} lacks {len(missing)} frame(s): {', '.join(names)}{more} "
        "(the number in each image's name is its frame); restore the missing images, or "
        "make the source's filename pattern select the frames before the gap"
    )


def list_image_files(pattern: str | Path) -> list[Path]:
    """Image files of a directory or glob pattern (``"cam0/*.png"``), in natural order (``2``
    before ``10``); :class:`~flylib.errors.FootageError` if nothing matches."""
    p = Path(pattern)
    if p.is_dir():
        files = [f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_EXTS]
    else:
        files = [Path(f) for f in glob.glob(str(pattern)) if Path(f).is_file()]
    if not files:
        raise FootageError(f"{pattern}: no image files found; check the directory or glob pattern")
    return sorted(files, key=natural_key)


def _default_workers() -> int:
    return min(8, usable_cpus())


class ImageSequenceReader(FrameReader):
    """An ordered image sequence, one frame per file (``files``, in frame order; use
    :meth:`from_pattern` to list a directory or glob in natural order), decoded by OpenCV.

    The number in each file's name is its frame: a sequence whose numbers skip one (or repeat one)
    is refused (:func:`sequence_gap`), never read shifted. Gray images are broadcast to three
    channels and alpha is dropped, so frames are always ``(H, W, 3)`` uint8 RGB. Image sequences
    carry no frame rate, so :meth:`fps` is ``None``.

    Blocks are decoded on a pool of ``workers`` threads (OpenCV releases the GIL while decoding):
    ``0`` or ``None`` picks ``min(8, usable_cpus())``; never more than
    :func:`~flylib.resources.usable_cpus` (a thread budget caps it); with one, blocks decode in the
    calling thread. ``on_corrupt="error"`` (default): a corrupt or truncated image raises
    :class:`~flylib.errors.FootageError` naming it; ``"missing"``: it is logged as a warning,
    decoded as a black frame and its index added to :attr:`corrupt_frames`, so callers can mark
    the frame missing.
    """

    def __init__(self, files, *, workers: int | None = None, on_corrupt: str = "error") -> None:
        self.files = [Path(f) for f in files]
        if not self.files:
            raise FootageError(
                "ImageSequenceReader got an empty file list; check the footage pattern"
            )
        gap = sequence_gap(self.files)
        if gap is not None:
            raise FootageError(gap)
        if on_corrupt not in ON_CORRUPT:
            raise ValueError(f"on_corrupt must be one of {ON_CORRUPT}, got {on_corrupt!r}")
        self.workers = min(int(workers), usable_cpus()) if workers else _default_workers()
        self.on_corrupt = on_corrupt
        #: Indices of the frames whose image was corrupt (``on_corrupt="missing"``).
        self.corrupt_frames: set[int] = set()
        self._shape: tuple[int, ...] | None = None
        self._pool: ThreadPoolExecutor | None = None

    @classmethod
    def from_pattern(
        cls, pattern: str | Path, *, workers: int | None = None, on_corrupt: str = "error"
    ) -> ImageSequenceReader:
        """A reader over a directory or glob pattern, in natural order."""
        return cls(list_image_files(pattern), workers=workers, on_corrupt=on_corrupt)

    @property
    def name(self) -> str:
        first = self.files[0]
        return (
            str(first)
            if len(self.files) == 1
            else f"{first.parent}/{first.name}...({len(self.files)} images)"
        )

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _decode_one(self, index: int) -> np.ndarray:
        import cv2

        path = self.files[index]
        if not path.is_file():
            raise FootageError(f"{path}: image file of frame {index} not found")
        data = path.read_bytes()
        damage = image_damage(data)
        image = None
        if damage is None:  # gray -> 3 channels, alpha dropped, 8-bit
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            if image is None:
                damage = "OpenCV could not decode it"
        if damage is not None:
            return self._corrupt(index, path, damage)
        frame = as_rgb_uint8(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        self._shape = self._shape or frame.shape
        return frame

    def _corrupt(self, index: int, path: Path, damage: str) -> np.ndarray:
        if self.on_corrupt == "error":
            raise FootageError(
                f"{path}: cannot decode frame {index} ({damage}); the image is corrupt or truncated: "
                "re-copy or re-export it, or set io.on_corrupt_frame: missing to mark such frames missing"
            )
        log.warning(
            "%s: frame %d is corrupt (%s); marking it missing (io.on_corrupt_frame: missing)",
            path,
            index,
            damage,
        )
        self.corrupt_frames.add(index)
        shape = self._shape or self._shape_from_neighbour(index)
        return np.zeros(shape, np.uint8)

    def _shape_from_neighbour(self, index: int) -> tuple[int, ...]:
        import cv2

        for other in (*range(index + 1, len(self.files)), *range(index - 1, -1, -1)):
            data = self.files[other].read_bytes()
            if image_damage(data) is None:
                image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
                if image is not None:
                    self._shape = (image.shape[0], image.shape[1], 3)
                    return self._shape
        raise FootageError(f"{self.name}: every image is corrupt; re-copy or re-export the footage")

    def _decode(self, indices: list[int]) -> np.ndarray:
        if len(indices) == 1 or self.workers == 1:
            return np.stack([self._decode_one(i) for i in indices])
        if self._pool is None:
            self._pool = ThreadPoolExecutor(
                max_workers=self.workers, thread_name_prefix="flylib-imread"
            )
        frames = list(self._pool.map(self._decode_one, indices))
        shapes = {f.shape for f in frames}
        if len(shapes) > 1:
            raise FootageError(
                f"{self.name}: images of different sizes in one sequence: {sorted(shapes)}"
            )
        return np.stack(frames)

    def _read_indices(self, indices: list[int]) -> np.ndarray:
        n = len(self.files)
        bad = [i for i in indices if not 0 <= i < n]
        if bad:
            raise IndexError(
                f"{self.name}: frame {bad[0]} is out of range (the sequence has {n} images)"
            )
        return self._decode(indices)

    def stream_frames(
        self, *, start: int = 0, stop: int | None = None, step: int = 1
    ) -> Iterator[UInt8[np.ndarray, "H W 3"]]:
        for block in self.stream_blocks(start=start, stop=stop, step=step, block_size=self.workers):
            yield from block

    def stream_blocks(
        self, *, start: int = 0, stop: int | None = None, step: int = 1, block_size: int = 64
    ) -> Iterator[UInt8[np.ndarray, "T H W 3"]]:
        if block_size < 1:
            raise ValueError(f"block_size must be >= 1, got {block_size}")
        indices = list(range(len(self.files)))[start:stop:step]
        for pos in range(0, len(indices), block_size):
            yield self._decode(indices[pos : pos + block_size])

    def count(self) -> int:
        return len(self.files)
