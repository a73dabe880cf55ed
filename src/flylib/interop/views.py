"""Which footage belongs to which configured view, and the raw frame size it has.

Imported 2D keypoints are placed on the configured views (the ``cameras`` table, in config order). A
view's footage is found through the detection plan: the pathways that fill the view
(``pose2d.output_points.<view>``) name a source, whose ``filename`` glob is matched in the recording
directory. Only the container/image header is read, never the pixels of a whole video."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

from ..config.sources import config_data, source_patterns, view_names, view_sources  # noqa: F401  (re-exported)
from ..errors import FootageError, ImportFormatError
from ..io import VIDEO_EXTS, open_reader
from ..io.images import sequence_gap
from ..recordings.footage import footage_matches, natural_sorted, video_frame_count


def footage_files(
    view_globs: Mapping[str, str | None] | Iterable[tuple[str, str | None]], recording_dir: Path
) -> dict[str, list[Path]]:
    """Each view's footage files in ``recording_dir`` (naturally sorted; empty if none), from
    ``view_globs`` (``view -> glob`` of the source feeding it, ``None`` for a source without a
    pattern; a mapping or pairs, in view order).

    Matched like :func:`flylib.recordings.find_recording`: only video and image files count, so a
    DeepLabCut CSV beside ``camera_0.mp4`` is not footage. A match that is no regular file, or an
    image sequence with a gap in its numbering (:func:`flylib.io.images.sequence_gap`), is a
    :class:`FootageError`."""
    found = {
        view: natural_sorted(footage_matches(Path(recording_dir), glob)) if glob is not None else []
        for view, glob in dict(view_globs).items()
    }
    for files in found.values():
        gap = sequence_gap([f for f in files if f.suffix.lower() not in VIDEO_EXTS])
        if gap is not None:
            raise FootageError(gap)
    return found


def read_frame_size(path: Path) -> tuple[int, int]:
    """``(height, width)`` of a video (from its stream header) or an image file."""
    try:
        return open_reader(Path(path)).frame_size()
    except FootageError as exc:
        raise ImportFormatError(str(exc)) from exc


def read_frame_count(files: list[Path]) -> int | None:
    """Frame count of a view's footage: the number of images, or the video's frames, counted from
    its packets (read without decoding) since a truncated file still carries its whole header count;
    the header count is the fallback for a stream without timestamps. ``None`` when neither gives a
    count (it is then not checked)."""
    if not files:
        return None
    if len(files) > 1 or files[0].suffix.lower() not in VIDEO_EXTS:
        return len(files)
    from ..io import VideoReader

    packets = VideoReader(files[0]).pts_index()
    return len(packets) if packets else video_frame_count(files[0])


def image_sizes(
    footage: dict[str, list[Path]],
    recording_dir: Path | None,
    views: list[str],
    fallback=None,
    *,
    origin: str,
    globs: Mapping[str, str | None] | None = None,
) -> dict[str, tuple[int, int]]:
    """Raw frame ``(height, width)`` per view: from its footage (:func:`footage_files`), else
    ``fallback``; a view with neither is an :class:`ImportFormatError` (:func:`missing_footage`)."""
    problem = missing_footage(footage, recording_dir, views, fallback, globs=globs)
    if problem is not None:
        raise ImportFormatError(f"{origin}: {problem}")
    out: dict[str, tuple[int, int]] = {}
    for view in views:
        if footage.get(view):
            out[view] = read_frame_size(footage[view][0])
        else:
            h, w = (int(v) for v in fallback)
            out[view] = (h, w)
    return out


def missing_footage(
    footage: Mapping[str, list[Path]],
    recording_dir: Path | None,
    views: list[str],
    fallback=None,
    *,
    globs: Mapping[str, str | None] | None = None,
) -> str | None:
    """Why imported 2D cannot be given frame sizes, or ``None``: a view with no footage
    (:func:`footage_files`) while ``pose2d.import.image_size`` (``fallback``) is not set. The
    missing file is named (from ``globs``) when other views have footage, else how to set
    ``image_size`` is said."""
    if fallback is not None:
        return None
    missing = [v for v in views if not footage.get(v)]
    if not missing:
        return None
    globs = globs or {}
    where = f" in {recording_dir}" if recording_dir is not None else ""
    if any(footage.get(v) for v in views):  # a camera's file missing among the others
        named = "; ".join(
            f"view {v!r}: no file matches {Path(recording_dir or '.') / globs[v]}"
            if globs.get(v)
            else f"view {v!r}: no footage source feeds it"
            for v in missing
        )
        return (
            f"no footage for {named}; put the camera's file there (or fix its source's "
            "filename in sources), or, to import its 2D without footage, set "
            "pose2d.import.image_size: [height, width]"
        )
    return (
        f"no footage for any view{where} to read the frame size from; imported 2D without "
        "footage needs the frames' size in pixels: set pose2d.import.image_size: [height, width] "
        "(e.g. [480, 960])"
    )
