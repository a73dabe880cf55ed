"""Panel compositor (one video's panels onto a reused canvas from plain NumPy inputs) and the
streaming renderer (footage decoded once per frame a few frames ahead, every video's canvas drawn
and encoded: nothing but the result arrays scales with the recording)."""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import FootageError
from ..paths import atomic_path
from ..resources import usable_cpus
from .draw import (
    color_tuples,
    draw_label,
    draw_rings,
    draw_skeleton_2d,
    draw_skeleton_3d,
    skeleton_colors,
    to_panel_coords,
)
from .specs import PLAUSIBLE_FPS, PanelSpec, VideoSpec, read_video_specs, resolve_output_fps

log = logging.getLogger(__name__)

#: Frames decoded ahead of the drawing loop (bounded: memory stays flat).
PREFETCH_FRAMES = 8
#: Frames reprojected per call to the camera model for ``skeleton_3d`` panels.
PROJECT_CHUNK = 256
#: Converted canvases waiting for each encoder thread.
ENCODE_QUEUE = 4
#: libx264 settings: a fast preset keeps encoding from dominating the render.
X264_SETTINGS = {"preset": "superfast", "crf": 20}


class _Panel:
    """A panel resolved against the frame size: its canvas rectangle and colours."""

    def __init__(
        self,
        spec: PanelSpec,
        image_hw: tuple[int, int],
        skeleton,
        video_background: tuple[int, int, int],
    ):
        self.spec = spec
        self.image_hw = image_hw
        self.width, self.height = spec.size(image_hw)
        self.slices = (slice(spec.y0, spec.y0 + self.height), slice(spec.x0, spec.x0 + self.width))
        # solid fills are prebuilt: copying an array is ~50x faster than broadcasting a colour
        self.fill = None if spec.background is None else self._solid(spec.background)
        self.empty_fill = self._solid(spec.background or video_background)  # imshow, no footage
        if spec.plot != "imshow":
            point_colors, bone_colors = skeleton_colors(skeleton, spec.palette)
            self.point_colors = color_tuples(point_colors)
            self.bone_colors = color_tuples(bone_colors)
            self.bones = np.asarray(skeleton.bones, dtype=int).reshape(-1, 2)

    def _solid(self, color) -> np.ndarray:
        return np.full((self.height, self.width, 3), color, np.uint8)


class Compositor:
    """Draws the panels of one :class:`VideoSpec` onto a reused canvas; ``image_sizes``
    (``view -> (height, width)`` of raw frames) sizes the panels."""

    def __init__(self, spec: VideoSpec, skeleton, image_sizes: Mapping[str, tuple[int, int]]):
        self.spec = spec
        self.width, self.height = spec.canvas_size(image_sizes)
        self._blank = np.full((self.height, self.width, 3), spec.background, np.uint8)
        self.canvas = self._blank.copy()
        self.panels = [
            _Panel(p, tuple(image_sizes[p.view]), skeleton, spec.background) for p in spec.panels
        ]
        # one view name per panel area, written last so that nothing covers it
        self.labelled = list(
            {(p.slices[0].start, p.slices[1].start): p for p in self.panels}.values()
        )

    def compose(
        self,
        frames: Mapping[str, np.ndarray | None],
        points2d: Mapping[str, np.ndarray],
        points3d: Mapping[str, tuple[np.ndarray, np.ndarray]],
        resized: dict | None = None,
        corrected: np.ndarray | None = None,
        stamp: str | None = None,
    ) -> np.ndarray:
        """Draw one output frame; the canvas ``(height, width, 3)`` uint8 (reused: copy to keep).

        ``frames``: ``view -> (H, W, 3)`` uint8 RGB (any size) or ``None``; ``points2d``:
        ``view -> (P, 2)`` raw-frame pixels, NaN = missing; ``points3d``: ``view -> (xy (P, 2),
        depth (P,))``, reprojected with camera-frame depths; ``resized``: a cache keyed ``(view,
        width, height)``, shared by compositors drawing the same frame; ``corrected``: ``(P,)``
        bool, ringed; ``stamp``: written lower-left when ``labels`` is on."""
        canvas = self.canvas
        np.copyto(canvas, self._blank)
        if resized is None:
            resized = {}
        for panel in self.panels:
            spec = panel.spec
            region = canvas[panel.slices]
            if spec.plot == "imshow":
                frame = frames.get(spec.view)
                if frame is None:
                    np.copyto(region, panel.empty_fill)
                    continue
                key = (spec.view, panel.width, panel.height)
                if key not in resized:
                    resized[key] = _fit(frame, panel.width, panel.height)
                np.copyto(region, resized[key])
                continue
            if panel.fill is not None:
                np.copyto(region, panel.fill)
            if spec.plot == "skeleton_2d":
                xy, depth = points2d.get(spec.view), None
            else:
                xy, depth = points3d.get(spec.view, (None, None))
            if xy is None:
                continue
            xy = to_panel_coords(xy, panel.image_hw, (panel.width, panel.height))
            colors = (panel.bones, panel.point_colors, panel.bone_colors)
            style = {"radius": spec.point_radius, "thickness": spec.line_thickness}
            if depth is None:
                draw_skeleton_2d(region, xy, *colors, **style)
            else:
                draw_skeleton_3d(region, xy, depth, *colors, **style)
            if corrected is not None and corrected.any():
                draw_rings(region, xy, corrected, spec.point_radius)
        if self.spec.labels:
            for panel in self.labelled:
                draw_label(canvas[panel.slices], panel.spec.view)
            if stamp:
                draw_label(canvas, stamp, "bottom-left")
        return canvas


def frame_stamp(t: int, n_frames: int, fps: float | None) -> str:
    """``"frame 12 / 59   0.120 s"`` (from 0, as in results.h5; the time when ``fps`` is known)."""
    text = f"frame {t} / {n_frames - 1}"
    return f"{text}   {t / fps:.3f} s" if fps else text


def _fit(frame: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize an RGB frame to ``width x height`` (area averaging when shrinking)."""
    frame = np.asarray(frame)
    if frame.ndim == 2:
        frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)
    if frame.shape[0] == height and frame.shape[1] == width:
        return frame
    shrink = width < frame.shape[1] and height < frame.shape[0]
    return cv2.resize(
        frame, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    )


class _Footage:
    """One view's footage: its frame size and rate, streamed forward once."""

    def __init__(self, view: str, files: Sequence[Path], on_corrupt: str = "error"):
        from ..io import open_reader

        self.view = view
        self.reader = open_reader([Path(f) for f in files], on_corrupt=on_corrupt)
        self.image_hw = tuple(self.reader.frame_size())
        self.fps = self.reader.fps()

    def __iter__(self) -> Iterator[np.ndarray]:
        return iter(self.reader.stream_frames())

    def close(self) -> None:
        self.reader.close()


def _frame_bundles(sources: Mapping[str, Any], n_frames: int) -> Iterator[dict]:
    """``{view: frame}`` for each frame; footage shorter or longer is a :class:`FootageError`."""
    iters = {view: iter(src) for view, src in sources.items()}

    def mismatch(view: str, count: str) -> FootageError:
        return FootageError(
            f"{sources[view].reader.name}: footage of view {view!r} has {count} frames but the "
            f"result has {n_frames}; the footage is truncated or not this recording's: re-copy "
            "it, or re-run the workflow from pose2d with the right footage"
        )

    for t in range(n_frames):
        bundle = {}
        for view, frames in iters.items():
            frame = next(frames, None)
            if frame is None:
                raise mismatch(view, str(t))
            bundle[view] = frame
        yield bundle
    for view, frames in iters.items():
        if next(frames, None) is not None:
            raise mismatch(view, "more")


@contextlib.contextmanager
def _prefetched(items: Iterable, depth: int = PREFETCH_FRAMES):
    """Iterate ``items`` in a background thread (if CPUs allow), at most ``depth`` ahead."""
    if usable_cpus() == 1:
        yield iter(items)
        return
    buffer: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def produce():
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        buffer.put(("item", item), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            buffer.put(("end", done))
        except BaseException as exc:  # forwarded to the consumer
            buffer.put(("error", exc))

    worker = threading.Thread(target=produce, name="flylib-decode", daemon=True)
    worker.start()

    def consume():
        while True:
            kind, item = buffer.get()
            if kind == "end":
                return
            if kind == "error":
                raise item
            yield item

    try:
        yield consume()
    finally:
        stop.set()
        worker.join(timeout=5)


class _Reprojector:
    """``pts3d`` projected into views, in chunks: raw-frame pixels and camera-frame depths (z)."""

    def __init__(
        self, cameras, pts3d: np.ndarray, views: Sequence[str], chunk: int = PROJECT_CHUNK
    ):
        self._views = list(views)
        self._rig = cameras.subset(self._views)
        rmats = np.asarray(self._rig.rmats, float)
        self._axis = rmats[:, 2, :]  # (V, 3) optical axes
        self._offset = np.asarray(self._rig.tvecs, float)[:, 2]
        self._pts3d = pts3d
        self._chunk = chunk
        self._start = -1
        self._xy = self._depth = None

    def at(self, t: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        start = (t // self._chunk) * self._chunk
        if start != self._start:
            block = self._pts3d[start : start + self._chunk]  # (Tc, P, 3)
            self._xy = np.asarray(self._rig.project(block), float)  # (V, Tc, P, 2)
            self._depth = np.einsum("vk,tpk->vtp", self._axis, block) + self._offset[:, None, None]
            self._start = start
        k = t - start
        return {v: (self._xy[i, k], self._depth[i, k]) for i, v in enumerate(self._views)}


class CanvasEncoder:
    """Streams RGB canvases into an H.264 MP4, like :class:`flylib.io.VideoWriter` but faster:
    RGB -> YUV 4:2:0 in OpenCV (BT.601 limited range like FFmpeg's) instead of swscale, and
    encoding in a worker thread (PyAV releases the GIL in x264) beside decoding and drawing."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        import av

        self._av = av
        self.width, self.height = width & ~1, height & ~1  # 4:2:0 needs even sizes
        if self.width == 0 or self.height == 0:
            raise ValueError(f"{path}: a {width}x{height} canvas is too small to encode")
        self._container = av.open(str(path), mode="w", format="mp4")
        rate = Fraction(fps).limit_denominator(1_000_000)
        self._threads = usable_cpus()
        options = {**{k: str(v) for k, v in X264_SETTINGS.items()}, "threads": str(self._threads)}
        self._stream = self._container.add_stream("libx264", rate=rate, options=options)
        self._stream.width, self._stream.height = self.width, self.height
        self._stream.pix_fmt = "yuv420p"
        self._queue: queue.Queue = queue.Queue(maxsize=ENCODE_QUEUE)
        self._error: BaseException | None = None
        self._worker = None
        if self._threads > 1:  # encode beside the drawing; inline under a one-thread budget
            self._worker = threading.Thread(
                target=self._encode_loop, name="flylib-encode", daemon=True
            )
            self._worker.start()

    def _encode_loop(self) -> None:
        while True:
            yuv = self._queue.get()
            if yuv is None:
                return
            if self._error is not None:
                continue  # drain after a failure so the producer never blocks
            self._encode(yuv)

    def _encode(self, yuv: np.ndarray) -> None:
        try:
            frame = self._av.VideoFrame.from_ndarray(yuv, format="yuv420p")
            self._container.mux(self._stream.encode(frame))
        except BaseException as exc:  # re-raised in the caller's thread
            self._error = exc

    def write_frame(self, canvas: np.ndarray) -> None:
        """Queue one ``(H, W, 3)`` RGB canvas (converted now, so it may be reused)."""
        if self._error is not None:
            raise self._error
        rgb = canvas[: self.height, : self.width]
        if not rgb.flags.c_contiguous:
            rgb = np.ascontiguousarray(rgb)
        yuv = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420)
        if self._worker is None:
            self._encode(yuv)
        else:
            self._queue.put(yuv)

    def close(self) -> None:
        """Finish the queued frames, flush the encoder and close the file."""
        if self._worker is not None:
            self._queue.put(None)
            self._worker.join()
        try:
            if self._error is not None:
                raise self._error
            self._container.mux(self._stream.encode(None))
        finally:
            self._container.close()


def _image_sizes(result, sources: Mapping[str, Any], views: Iterable[str]) -> dict:
    """``view -> (height, width)``: from footage, stored sizes, or the principal point."""
    meta_sizes = {
        **((getattr(result, "meta", None) or {}).get("image_sizes") or {}),
        **(getattr(result, "image_sizes", None) or {}),
    }
    names = list(result.cameras.names)
    sizes = {}
    for view in views:
        if view in sources:
            sizes[view] = sources[view].image_hw
        elif view in meta_sizes:
            sizes[view] = tuple(int(s) for s in meta_sizes[view])
        else:
            # principal point at the image centre: cx = (W - 1) / 2
            _, _, cx, cy = np.asarray(result.cameras.intrs, float)[names.index(view)][:4]
            sizes[view] = (max(2, int(round(2 * cy + 1))), max(2, int(round(2 * cx + 1))))
            log.info(
                "view %s: no footage or stored image size; assuming %dx%d from its principal point",
                view,
                sizes[view][1],
                sizes[view][0],
            )
    return sizes


def _panel_views(specs: Sequence[VideoSpec], plot: str | None = None) -> list[str]:
    """The views the panels use (those with a ``plot`` panel), in first-use order."""
    used = list(dict.fromkeys(v for s in specs for v in s.views))
    if plot is None:
        return used
    return [v for v in used if any(p.plot == plot and p.view == v for s in specs for p in s.panels)]


def _open_footage(
    stack: contextlib.ExitStack,
    views: Sequence[str],
    footage: Mapping[str, Sequence[Path]] | None,
    on_corrupt: str,
) -> dict[str, _Footage]:
    sources = {}
    for view in views:
        files = footage.get(view) if footage else None
        if isinstance(files, (str, Path)):
            files = [files]
        if files:
            source = _Footage(view, files, on_corrupt=on_corrupt)
            stack.callback(source.close)
            sources[view] = source
    lacking = [v for v in views if v not in sources]
    if lacking:
        warnings.warn(
            f"no footage for view{'s' * (len(lacking) > 1)} "
            f"{', '.join(map(repr, lacking))}: imshow panels show the "
            "background",
            stacklevel=3,
        )
    return sources


def _open_writers(
    stack: contextlib.ExitStack,
    specs: Sequence[VideoSpec],
    compositors: Sequence[Compositor],
    paths: Sequence[Path],
    rates: tuple[Mapping, float | None, float | None],
    n_frames: int,
) -> list[CanvasEncoder]:
    """One encoder per video, into a temporary file renamed when ``stack`` closes cleanly."""
    writers = []
    for spec, comp, path in zip(specs, compositors, paths):
        fps = resolve_output_fps(spec, *rates)
        tmp = stack.enter_context(atomic_path(path))
        writer = CanvasEncoder(tmp, fps, comp.width, comp.height)
        stack.callback(writer.close)
        writers.append(writer)
        log.info(
            "rendering %s: %dx%d, %d frames at %g fps",
            path.name,
            comp.width,
            comp.height,
            n_frames,
            fps,
        )
    return writers


def render_videos(
    table: Mapping[str, Any] | None,
    result,
    footage: Mapping[str, Sequence[Path]],
    outdir,
    *,
    progress: bool = True,
    corrected: np.ndarray | None = None,
    speed: float | None = None,
    on_corrupt: str = "error",
) -> list[Path]:
    """Render every ``[[visualization.videos]]`` spec of ``table`` for one recording, in one
    pass over the footage; the written ``<outdir>/<video_name>.mp4`` in spec order.

    ``footage``: ``view -> files`` (one video, or an ordered image sequence), a view without any
    drawing the background (with a warning); ``corrected``: ``(T, P)`` bool, ringed; ``speed``:
    multiple of the recording's rate when the config sets none; ``on_corrupt``:
    ``io.on_corrupt_frame``. A bad spec is a ConfigError, unreadable footage a FootageError."""
    from tqdm import tqdm

    table = {} if table is None else table
    names = list(result.cameras.names)
    specs = read_video_specs(table, view_names=names)
    if not specs:
        return []
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    used_views = _panel_views(specs)
    views_3d = _panel_views(specs, "skeleton_3d")
    pts3d = getattr(result, "pts3d", None)
    if views_3d and pts3d is None:
        warnings.warn(
            "the result has no 3D points; skeleton_3d panels stay empty (run triangulation)",
            stacklevel=2,
        )
        views_3d = []
    index = {v: names.index(v) for v in used_views}
    n_frames = int(result.pts2d.shape[1])
    paths = [outdir / f"{spec.name}.mp4" for spec in specs]

    with contextlib.ExitStack() as stack:
        sources = _open_footage(stack, _panel_views(specs, "imshow"), footage, on_corrupt)
        image_sizes = _image_sizes(result, sources, used_views)
        input_fps = next((s.fps for s in sources.values() if s.fps), None)
        if input_fps is None:
            input_fps = (getattr(result, "meta", None) or {}).get("fps")
        compositors = [Compositor(spec, result.skeleton, image_sizes) for spec in specs]
        # the stamp's time: the footage's own rate when plausible (not a container's 0.2 fps)
        recording_fps = (
            input_fps if input_fps and PLAUSIBLE_FPS[0] <= input_fps <= PLAUSIBLE_FPS[1] else None
        )
        writers = _open_writers(
            stack, specs, compositors, paths, (table, input_fps, speed), n_frames
        )
        reprojector = (
            _Reprojector(result.cameras, np.asarray(pts3d, float), views_3d) if views_3d else None
        )
        pts2d = result.pts2d
        bundles = stack.enter_context(_prefetched(_frame_bundles(sources, n_frames)))
        # no bar at all without progress: tqdm starts its monitor thread even disabled
        bar = (
            stack.enter_context(
                tqdm(
                    total=n_frames, unit="frame", desc="render " + ", ".join(s.name for s in specs)
                )
            )
            if progress
            else None
        )
        for t, frames in enumerate(bundles):
            points2d = {v: pts2d[i, t] for v, i in index.items()}
            points3d = reprojector.at(t) if reprojector else {}
            resized: dict = {}
            stamp = frame_stamp(t, n_frames, recording_fps)
            for comp, writer in zip(compositors, writers):
                writer.write_frame(
                    comp.compose(
                        frames,
                        points2d,
                        points3d,
                        resized,
                        None if corrected is None else corrected[t],
                        stamp,
                    )
                )
            if bar is not None:
                bar.update(1)
    return paths
