"""Streaming 2D detection over a recording's sources.

Each source is decoded once, on its own background thread (:class:`BlockPrefetcher`), into a
bounded queue of ``batch_size``-frame blocks (``decode_buffer`` blocks deep), so decoding runs in
parallel with the forward passes and frame memory is bounded by
``sources x (decode_buffer + 2) x batch_size`` frames whatever the recording length. Every pathway
reading a source is fed from the same block (moved to the device once). Results are copied back
one block late, so the GPU is never idle waiting for the host.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from .. import io
from ..config.params import IoParams, PictorialParams, Pose2dParams
from ..errors import FootageError
from ..resources import usable_cpus
from .inference import LoadedModel, load_models, yuv420p_to_rgb
from .plan import DetectionPlan, Pathway

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..pictorial import Candidates

log = logging.getLogger(__name__)

END_OF_STREAM = object()


class _Failure:
    def __init__(self, exc: BaseException):
        self.exc = exc


class BlockPrefetcher:
    """Decode one source into a bounded queue of uint8 torch blocks of up to ``block_size`` frames.

    Blocks are ``(T, H, W, 3)`` RGB, or, with ``raw_yuv`` on a ``yuv420p`` video, the decoder's
    planes ``(T, 3H/2, W)`` (:attr:`yuv` tells which; convert with
    :func:`~flylib.pose2d.inference.yuv420p_to_rgb` and :attr:`color`), which skips the CPU colour
    conversion, the slowest part of decoding.

    The source decodes on its own thread (``flylib-decode-<name>``), ``depth`` (at least 1) blocks
    ahead of :meth:`get`; under a one-thread budget (:func:`~flylib.resources.usable_cpus` is 1) it
    decodes in the calling thread instead, one block per :meth:`get`, so a one-thread job starts no
    thread and holds one block. ``files`` is what :func:`flylib.io.open_reader` reads; ``pin``
    allocates blocks in page-locked memory (fast, asynchronous GPU copies); ``on_corrupt`` is
    ``io.on_corrupt_frame`` for image sequences; ``threaded`` defaults to ``usable_cpus() > 1``.
    """

    def __init__(
        self,
        name: str,
        files,
        *,
        block_size: int,
        depth: int,
        workers: int | None = None,
        pin: bool = False,
        raw_yuv: bool = False,
        on_corrupt: str = "error",
        threaded: bool | None = None,
    ):
        self.name = f"flylib-decode-{name}"
        self.source = name
        self.reader = io.open_reader(files, workers=workers, on_corrupt=on_corrupt)
        #: Frames decoded (set once the source ended).
        self.decoded = 0
        self.block_size = block_size
        self.pin = pin
        self.yuv = False
        self.color = ("bt601", "limited")
        if (
            raw_yuv
            and isinstance(self.reader, io.VideoReader)
            and self.reader.pixel_format() == "yuv420p"
        ):
            h, w = self.reader.frame_size()
            self.yuv = h % 2 == 0 and w % 2 == 0
            self.color = self.reader.color_tags()
        self.threaded = usable_cpus() > 1 if threaded is None else bool(threaded)
        self.blocks: queue.Queue = queue.Queue(maxsize=max(1, depth))
        self._stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self._inline: Iterator | None = None  # the block generator, when not threaded

    def _frames(self):
        if self.yuv:
            return self.reader.stream_frames(format="yuv420p")
        return self.reader.stream_frames()

    def _produce(self) -> Iterator:
        """The source's blocks, then the end marker; a decode error as a :class:`_Failure`."""
        try:
            block, filled, shape, index = None, 0, None, 0
            for index, frame in enumerate(self._frames()):
                if shape is None:
                    shape = frame.shape
                elif frame.shape != shape:
                    raise FootageError(
                        f"{self.reader.name}: frame {index} is {frame.shape[1]}x{frame.shape[0]} but "
                        f"earlier frames are {shape[1]}x{shape[0]}; a source's frames must share one size"
                    )
                if block is None:
                    block = torch.empty(
                        (self.block_size, *shape), dtype=torch.uint8, pin_memory=self.pin
                    )
                    view = block.numpy()
                view[filled] = frame
                filled += 1
                if filled == self.block_size:
                    yield block
                    block, filled = None, 0
            if filled:
                yield block[:filled]
            self.decoded = index + 1 if shape is not None else 0
            self._check_complete()
            yield END_OF_STREAM
        except GeneratorExit:
            raise
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            yield _Failure(exc)
        finally:
            self.reader.close()

    def start(self) -> None:
        """Start decoding (on the background thread when :attr:`threaded`)."""
        if not self.threaded:
            self._inline = self._produce()
            return
        self._thread = threading.Thread(target=self.run, name=self.name, daemon=True)
        self._thread.start()

    def run(self) -> None:
        """The decode thread: queue every block (blocking while the queue is full)."""
        produced = self._produce()
        try:
            for item in produced:
                if not self._put(item):
                    return
        finally:
            produced.close()

    def is_alive(self) -> bool:
        """Whether the decode thread runs (never, inline)."""
        return self._thread is not None and self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        """Wait for the decode thread to finish (nothing to wait for inline)."""
        if self._thread is not None:
            self._thread.join(timeout)

    def _check_complete(self) -> None:
        """A video whose header promises more frames than decode is truncated."""
        if not isinstance(self.reader, io.VideoReader):
            return
        promised = self.reader.count()
        if promised is not None and self.decoded < promised:
            raise FootageError(
                f"{self.reader.name}: its header says {promised} frames but only {self.decoded} "
                "decode; the file is truncated: re-copy or re-export it"
            )

    def corrupt_frames(self) -> set[int]:
        """Frames an image sequence marked missing (``io.on_corrupt_frame: missing``)."""
        return set(getattr(self.reader, "corrupt_frames", ()) or ())

    def _put(self, item) -> bool:
        while not self._stop_event.is_set():
            try:
                self.blocks.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def get(self):
        """The next block, or the end marker; re-raises a decode error here."""
        if self._inline is not None:
            item = next(self._inline, END_OF_STREAM)
        else:
            item = self.blocks.get()
        if isinstance(item, _Failure):
            raise item.exc
        return item

    def stop(self) -> None:
        """Ask the decoding to finish and drop what it queued."""
        if self._inline is not None:
            self._inline.close()  # closes the reader
            return
        self._stop_event.set()
        while True:
            try:
                self.blocks.get_nowait()
            except queue.Empty:
                break
        self.join(timeout=10)


@dataclass
class DetectionOutput:
    """What a detection run produces (the arrays plus the raw frame sizes)."""

    pts2d: np.ndarray  # (V, T, P, 2)
    conf: np.ndarray  # (V, T, P)
    candidates_xy: np.ndarray | None  # (V, T, P, K, 2)
    candidates_score: np.ndarray | None  # (V, T, P, K)
    frame_sizes: dict[str, tuple[int, int]]  # source -> (height, width)


@dataclass
class _Pending:
    start: int
    n: int
    results: list  # (pathway, source, xy, conf, candidates), host copies in flight on CUDA
    ready: object = None  # a CUDA event recorded after the copies


def _start_download(results: list, device: torch.device):
    """Queue device->host copies of a block's results; return them and an event to wait on
    (not the whole stream, so the next block's forwards run while this one is scattered)."""
    if device.type != "cuda":
        return results, None
    host = []
    for pathway, source, xy, cf, cand in results:
        cand = None if cand is None else tuple(c.to("cpu", non_blocking=True) for c in cand)
        host.append(
            (
                pathway,
                source,
                xy.to("cpu", non_blocking=True),
                cf.to("cpu", non_blocking=True),
                cand,
            )
        )
    event = torch.cuda.Event()
    event.record()
    return host, event


def _make_progress(progress, total: int | None):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc="detect 2D", unit="frame", dynamic_ncols=True)


def _to_raw(pathway: Pathway, xy: np.ndarray, raw_size, model: LoadedModel) -> np.ndarray:
    return pathway.heatmap_to_raw(xy, raw_size, model.spec, model.heatmap_size)


def _host(tensor: torch.Tensor, pathway: Pathway) -> np.ndarray:
    """A result tensor on the host in float64, the pathway's channels (axis 1) selected."""
    return tensor.to("cpu", torch.float64).numpy()[:, pathway.channels]


def run_detection(
    plan: DetectionPlan,
    models: dict[str, LoadedModel],
    sources: dict[str, list[Path] | str | Path],
    *,
    batch_size: int = Pose2dParams.batch_size,
    decode_buffer: int = Pose2dParams.decode_buffer,
    workers: int | None = None,
    k: int | None = None,
    progress=False,
    raw_yuv: bool | None = None,
    timings: dict[str, float] | None = None,
    on_corrupt: str = "error",
) -> DetectionOutput:
    """Stream every active source through its pathways and scatter the points.

    ``models``: name -> :class:`LoadedModel` for every model the active pathways use;
    ``sources``: source name -> footage (file list, video, directory or glob); ``batch_size``:
    frames per decoded block and per forward; ``decode_buffer``: blocks queued ahead per source;
    ``k``: top-``k`` candidates per (view, point) when given. ``raw_yuv`` converts YUV video to RGB
    on the device instead of in the decoder (default: on a GPU); results agree to within a grey
    level. ``on_corrupt``: a corrupt image in a sequence fails naming it (``"error"``) or marks
    every point of that frame in the views it feeds missing (NaN, ``"missing"``).

    ``timings``, when given, receives where the calling thread spent its time, in seconds:
    ``wait_decode`` (blocked on the decode threads; decoding, under a one-thread budget),
    ``launch`` (preprocessing and forwards; on a GPU only queueing them), ``wait_device`` (blocked
    on a GPU block's results) and ``scatter`` (points to raw pixels on the host); which one
    dominates says what bounds the throughput.

    Raises :class:`FootageError` if a source is missing or unreadable, or the sources differ in
    length or change frame size.
    """
    active = plan.active_sources()
    missing = [s for s in active if s not in sources or not sources[s]]
    if missing:
        raise FootageError(
            f"no footage for source(s) {missing}: each [[sources]] pattern must match a video or images "
            f"(patterns: {[plan.sources[s] for s in missing]})"
        )
    device = next(iter(models.values())).device if models else torch.device("cpu")
    pin = device.type == "cuda"
    raw_yuv = device.type != "cpu" if raw_yuv is None else raw_yuv
    prefetchers = {
        s: BlockPrefetcher(
            s,
            sources[s],
            block_size=batch_size,
            depth=decode_buffer,
            workers=workers,
            pin=pin,
            raw_yuv=raw_yuv,
            on_corrupt=on_corrupt,
        )
        for s in active
    }
    total = prefetchers[active[0]].reader.count() if active and progress else None
    gather = _Gather(plan, models, k, _make_progress(progress, total))

    for p in prefetchers.values():
        p.start()
    pending: _Pending | None = None
    start = 0
    try:
        while True:
            t0 = time.perf_counter()
            blocks = {s: prefetchers[s].get() for s in active}
            t1 = time.perf_counter()
            gather.clock["wait_decode"] += t1 - t0
            if _ended(blocks, start):
                break
            n, results = _launch(blocks, prefetchers, plan, models, gather.frame_sizes, start, k)
            results, ready = _start_download(results, device)
            gather.clock["launch"] += time.perf_counter() - t1
            if pending is not None:
                gather.finalize(pending)
            pending = _Pending(start, n, results, ready)
            start += n
            del blocks
        if pending is not None:
            gather.finalize(pending)
    finally:
        for p in prefetchers.values():
            p.stop()
        if gather.bar is not None:
            gather.bar.close()
        if timings is not None:
            timings.update(gather.clock)
    out = gather.output(active)
    for source, prefetcher in prefetchers.items():
        frames = sorted(prefetcher.corrupt_frames())
        if frames:
            _mark_missing(
                out,
                sorted({int(v) for p in plan.pathways_on(source) for v in np.atleast_1d(p.views)}),
                frames,
            )
    return out


def _ended(blocks: dict, start: int) -> bool:
    """Whether every source ended; a source ending before the others, or blocks of
    different lengths, is a :class:`FootageError`."""
    ended = [s for s, b in blocks.items() if b is END_OF_STREAM]
    if ended:
        if len(ended) != len(blocks):
            going = [s for s in blocks if s not in ended]
            raise FootageError(
                f"sources differ in length: {ended} end after {start} frames while {going} go on; "
                "every camera must have the same number of frames"
            )
        return True
    lengths = {s: int(b.shape[0]) for s, b in blocks.items()}
    if len(set(lengths.values())) > 1:
        raise FootageError(
            f"sources differ in length around frame {start}: block sizes {lengths}; every camera "
            "must have the same number of frames"
        )
    return False


def _launch(blocks, prefetchers, plan, models, frame_sizes, start: int, k) -> tuple[int, list]:
    """Queue one block's forwards on every pathway -> ``(frames, results)``; the first
    block records each source's frame size, a later one must keep it."""
    device = next(iter(models.values())).device if models else torch.device("cpu")
    results = []
    for source, block in blocks.items():
        frames = block.to(device, non_blocking=True)
        if prefetchers[source].yuv:
            frames = yuv420p_to_rgb(frames, *prefetchers[source].color)
        size = (int(frames.shape[1]), int(frames.shape[2]))
        if frame_sizes.setdefault(source, size) != size:
            raise FootageError(
                f"source {source}: frame {start} is {size[1]}x{size[0]} but earlier frames are "
                f"{frame_sizes[source][1]}x{frame_sizes[source][0]}"
            )
        for pathway in plan.pathways_on(source):
            if start == 0:
                pathway.check_frame(size)
            xy, cf, cand = models[pathway.model].detect(frames, pathway.ops, k=k)
            results.append((pathway, source, xy, cf, cand))
    return next(int(b.shape[0]) for b in blocks.values()), results


class _Gather:
    """A detection run's host side: each finished block's points scattered into the
    ``(V, n, P)`` arrays in raw-frame pixels, and where the time went."""

    def __init__(self, plan: DetectionPlan, models: dict[str, LoadedModel], k, bar) -> None:
        self.models, self.k, self.bar = models, k, bar
        self.n_views, self.n_points = len(plan.view_names), len(plan.point_names)
        self.frame_sizes: dict[str, tuple[int, int]] = {}
        self.parts: dict[str, list[np.ndarray]] = {"pts": [], "conf": [], "cxy": [], "cscore": []}
        self.clock = dict.fromkeys(("wait_decode", "launch", "wait_device", "scatter"), 0.0)

    def finalize(self, pending: _Pending) -> None:
        """Wait for a block's results and scatter them."""
        k, models = self.k, self.models
        t0 = time.perf_counter()
        if pending.ready is not None:
            pending.ready.synchronize()
        t1 = time.perf_counter()
        self.clock["wait_device"] += t1 - t0
        pts = np.full((self.n_views, pending.n, self.n_points, 2), np.nan)
        conf = np.full((self.n_views, pending.n, self.n_points), np.nan)
        cxy = np.full((self.n_views, pending.n, self.n_points, k, 2), np.nan) if k else None
        cscore = np.full((self.n_views, pending.n, self.n_points, k), np.nan) if k else None
        for pathway, source, xy, cf, cand in pending.results:
            model, size = models[pathway.model], self.frame_sizes[source]
            raw = _to_raw(pathway, _host(xy, pathway), size, model)
            pts[pathway.views, :, pathway.points] = raw.transpose(1, 0, 2)
            conf[pathway.views, :, pathway.points] = _host(cf, pathway).T
            if k:
                cand_raw = _to_raw(pathway, _host(cand[0], pathway), size, model)  # NaN stays NaN
                cxy[pathway.views, :, pathway.points] = cand_raw.transpose(1, 0, 2, 3)
                cscore[pathway.views, :, pathway.points] = _host(cand[1], pathway).transpose(
                    1, 0, 2
                )
        self.parts["pts"].append(pts)
        self.parts["conf"].append(conf)
        if k:
            self.parts["cxy"].append(cxy)
            self.parts["cscore"].append(cscore)
        if self.bar is not None:
            self.bar.update(pending.n)
        self.clock["scatter"] += time.perf_counter() - t1

    def output(self, active: list[str]) -> DetectionOutput:
        """The blocks joined along time (no block at all is a :class:`FootageError`)."""
        if not self.parts["pts"]:
            raise FootageError(
                f"the detector received no frames from sources {active}; check the footage"
            )
        k, parts = self.k, self.parts
        return DetectionOutput(
            pts2d=np.concatenate(parts["pts"], axis=1),
            conf=np.concatenate(parts["conf"], axis=1),
            candidates_xy=np.concatenate(parts["cxy"], axis=1) if k else None,
            candidates_score=np.concatenate(parts["cscore"], axis=1) if k else None,
            frame_sizes=self.frame_sizes,
        )


def _mark_missing(out: DetectionOutput, views: list[int], frames: list[int]) -> None:
    """NaN every point of ``frames`` in ``views`` (a corrupt image is no observation)."""
    index = np.ix_(views, frames)
    out.pts2d[index] = np.nan
    out.conf[index] = np.nan
    if out.candidates_xy is not None:
        out.candidates_xy[index] = np.nan
        out.candidates_score[index] = np.nan


def frame_count(plan: DetectionPlan, sources) -> int | None:
    """The recording's frame count from its first active source's header (``None`` if
    unknown: the detection itself then reports any problem with the footage)."""
    active = plan.active_sources()
    if not active or not sources.get(active[0]):
        return None
    try:
        reader = io.open_reader(sources[active[0]])
    except Exception:  # noqa: BLE001 - run_detection names the problem
        return None
    try:
        return reader.count()
    finally:
        reader.close()


def _candidates(xy: np.ndarray, score: np.ndarray):
    from ..pictorial import Candidates

    return Candidates(xy=xy, score=score)


def detect_2d(
    params: Pose2dParams,
    plan: DetectionPlan,
    models: dict[str, LoadedModel],
    *,
    sources: dict[str, list[Path] | str | Path],
    io: IoParams | None = None,
    want_candidates: bool = False,
    k: int | None = None,
    progress=False,
) -> tuple[Float[np.ndarray, "V T P 2"], Float[np.ndarray, "V T P"], Candidates | None]:
    """Stream 2D detection over a recording -> ``(pts2d, conf, candidates)``.

    ``params`` gives ``batch_size`` and ``decode_buffer``; ``plan`` comes from
    :meth:`DetectionPlan.from_tables`, ``models`` from :func:`load_models`; ``sources`` maps source
    name -> footage (the resolved file list of each ``[[sources]]`` entry); ``io`` gives
    ``io.image.workers`` and ``io.on_corrupt_frame`` (default: their defaults). ``want_candidates``
    also returns the top-``k`` heatmap peaks per (view, point) for pictorial structures (``k``
    default: ``pictorial_structures.k``'s default).

    ``pts2d`` is ``(V, T, P, 2)`` raw-frame pixels, NaN where the plan fills nothing; ``conf``
    ``(V, T, P)`` heatmap peak values, NaN likewise; ``candidates`` (``xy (V, T, P, K, 2)``,
    ``score (V, T, P, K)``) is ``None`` unless ``want_candidates``.
    """
    out = _detect(
        params,
        io or IoParams(),
        plan,
        models,
        sources,
        k=(k or PictorialParams.k) if want_candidates else None,
        progress=progress,
    )
    cands = _candidates(out.candidates_xy, out.candidates_score) if want_candidates else None
    return out.pts2d, out.conf, cands


def _detect(
    params: Pose2dParams, io: IoParams, plan, models, sources, *, k: int | None, progress
) -> DetectionOutput:
    """:func:`run_detection` with the settings' knobs (``k``: candidates, or ``None``)."""
    return run_detection(
        plan,
        models,
        sources,
        batch_size=int(params.batch_size),
        decode_buffer=int(params.decode_buffer),
        workers=io.image_workers,
        k=k,
        progress=progress,
        on_corrupt=io.on_corrupt_frame,
    )


def detect_recording(
    plan: DetectionPlan,
    sources: dict[str, list[Path]],
    params: Pose2dParams,
    *,
    io: IoParams | None = None,
    k: int | None = None,
    progress: bool = True,
    models: dict[str, LoadedModel] | None = None,
):
    """The pose2d stage's detection: run the plan over one recording -> a
    :class:`flylib.results.Pose2dData`.

    ``sources`` maps source name -> resolved footage files (:mod:`flylib.recordings`); ``params``
    are the ``pose2d`` settings (precision, device, batch size, decode buffer, compile); ``io``
    gives ``io.image.workers`` and ``io.on_corrupt_frame`` (default: their defaults); ``k`` also
    keeps the top-``k`` peaks per (view, point) (pictorial structures on); ``models`` are
    already-loaded models (default: load the plan's weights, downloading the published checkpoint
    on first use).

    Raises :class:`WeightsError` if the weights cannot be found or downloaded (never runs an
    untrained network), :class:`FootageError` if the footage is missing, corrupt or inconsistent
    across cameras.
    """
    if models is None:
        models = load_models(plan, params, frames=frame_count(plan, sources))
    out = _detect(params, io or IoParams(), plan, models, sources, k=k, progress=progress)
    view_sources = plan.view_sources()
    image_sizes = {v: out.frame_sizes[s] for v, s in view_sources.items() if s in out.frame_sizes}
    from ..results import Pose2dData

    return Pose2dData(
        pts2d=out.pts2d,
        conf=out.conf,
        view_names=list(plan.view_names),
        image_sizes=image_sizes,
        candidates=_candidates(out.candidates_xy, out.candidates_score) if k else None,
    )
