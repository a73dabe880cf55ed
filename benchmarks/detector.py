"""2D detector throughput and memory: decode, forward and end-to-end, CPU or CUDA.

Generates its own synthetic 960x480 H.264 clip (moving blobs on a textured
background, like the rig's footage) and measures, on the default plan's shape
(7 sources, 8 pathways, the flip preprocessor, one 19-channel stacked hourglass
at 256x512):

* decode frames/s: one source alone, and 7 sources on flylib's background decode
  threads (what detection uses);
* forward images/s per precision and batch size (random weights), with GFLOP per
  image, the TFLOP/s reached and its fraction of the H100's dense bf16 peak
  (989 TFLOP/s, SXM);
* heatmap decoding per sub-pixel method (``pose2d.models[].subpixel``) on the
  device, against ``parabola`` (flylib's earlier default) as the baseline;
* end-to-end images/s (7 sources decoded -> 8 pathways -> points in the raw
  frame), i.e. ``flylib.pose2d.run_detection``, per precision and batch size; and
  whether decoding or the network is the bottleneck, with where the detection loop's
  thread spent the run (waiting for decoded blocks, launching the work, waiting for
  the GPU's results, scattering points on the host);
* peak memory (RSS, sampled every 10 ms) of streaming a 5,000-frame clip against a
  500-frame clip (target: within 2x); on the CPU the network is replaced by the
  torch preprocessing so this stays quick (``--memory-mode full`` forces it).

Targets (H100): end-to-end >= 1,500 images/s in bf16, decode never the bottleneck.

The network is DeepFly2D's sh8 (the released checkpoint's layout): 25,606,168
parameters, 112.6 GFLOP (56.3 G multiply-adds of its convolutions) per 256x512 image.

Measured on one H100 80GB HBM3 (16 CPU cores, torch 2.11, 2026-11-22), sh8, bf16,
with flylib's earlier stem (layer2 64 planes: 25,445,656 parameters, 110.0
GFLOP/image, 2.4% less work than the corrected network; not re-measured since):
decode 2,270 frames/s over 7 sources with GPU-side YUV->RGB (= 2,590 pathway
images/s; 390-680 when converting to RGB on the CPU); forward 110 GFLOP/image,
~500 images/s eager, 1,265 (batch 64) / 1,323 (batch 128) compiled, 1,292 with CUDA
graphs (14% of the bf16 peak); end-to-end 846-902 images/s (network-bound; below the
1,500 target). Memory, decode + preprocessing: peak RSS 7,645 MiB for 5,000 frames vs
7,267 MiB for 500 (1.05x).

Compiled runs use flylib's compiled detector (``--compile-mode aot``: an AOTInductor
package of the BatchNorm-folded network, cached on disk, replayed as one CUDA graph
per batch), or torch.compile's JIT in another mode for comparison.

``--cold-start`` measures instead what each Snakemake pose2d job pays: one recording
(default 900 frames on CUDA) in a fresh process per mode -- ``compile: false``,
``compile: auto`` and ``compile: true`` with an empty compiled-detector cache, then
``compile: true`` and ``auto`` with the cache the cold run filled -- the wall time of
the whole process (imports, model load or compilation, decode, detection), its
images/s and its ratio to ``compile: false`` measured in the same run, with the
compile status and peak GPU memory. On an H100 (not measured yet: no GPU on the
development machines)::

    python benchmarks/detector.py --cold-start --device cuda --frames 900 \
        --stacks 8 --precision bfloat16 --batch-sizes 16

On a CPU (shows it works; about ten minutes on a busy 2-core box, mostly the cold
AOTInductor build): ``python benchmarks/detector.py --cold-start --device cpu
--frames 8 --stacks 1``.

Run: ``python benchmarks/detector.py [--device cuda] [--precision bfloat16,float16]
[--batch-sizes 32,64,128] [--stacks 8] [--frames 1000] [--compile auto|on|off|both]
[--compile-mode aot|reduce-overhead|max-autotune] [--freezing] [--cold-start]``.
Imports only torch, numpy, av, cv2 and flylib (from ``src/``), no network.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from flylib import io  # noqa: E402
from flylib.config.params import Pose2dParams  # noqa: E402
from flylib.pose2d import decode, stream  # noqa: E402
from flylib.pose2d.inference import LoadedModel, load_models, select_device  # noqa: E402
from flylib.pose2d.model import HourglassNet  # noqa: E402
from flylib.pose2d.plan import DetectionPlan  # noqa: E402

H100_BF16_PEAK_TFLOPS = 989.0
FRAME_H, FRAME_W = 480, 960
N_SOURCES = 7


# --- synthetic footage and plan ---------------------------------------------------


def make_clip(path: Path, n_frames: int, seed: int = 0) -> Path:
    """A 960x480 clip of drifting Gaussian blobs on static texture, H.264 (x264 'fast')."""
    rng = np.random.default_rng(seed)
    background = (rng.normal(70, 12, size=(FRAME_H, FRAME_W)).clip(0, 255)).astype(np.float32)
    yy, xx = np.mgrid[0:FRAME_H, 0:FRAME_W].astype(np.float32)
    centres = rng.uniform([100, 80], [860, 400], size=(12, 2)).astype(np.float32)
    speeds = rng.normal(0, 3, size=(12, 2)).astype(np.float32)
    with io.VideoWriter(path, fps=100, crf=20, preset="fast") as writer:
        for t in range(n_frames):
            frame = background.copy()
            for (cx, cy), (vx, vy) in zip(centres, speeds):
                x0 = (cx + vx * t) % FRAME_W
                y0 = (cy + vy * t) % FRAME_H
                sl = (
                    slice(max(0, int(y0) - 30), int(y0) + 30),
                    slice(max(0, int(x0) - 30), int(x0) + 30),
                )
                frame[sl] += 150 * np.exp(-((xx[sl] - x0) ** 2 + (yy[sl] - y0) ** 2) / 200.0)
            gray = frame.clip(0, 255).astype(np.uint8)
            writer.write_frame(np.repeat(gray[..., None], 3, axis=-1))
    return path


def plan_data(checkpoint: Path, batch_size: int, precision: str, device: str) -> dict:
    """The default fly plan's shape: 7 sources, 8 pathways (4 mirrored), 19 channels."""
    points = [f"l{i}" for i in range(19)] + [f"r{i}" for i in range(19)]
    views = [f"cam{i}" for i in range(N_SOURCES)]
    pathways = [{"name": f"p{i}", "source": f"vid{i}", "model": "hg"} for i in range(4)]
    pathways += [
        {"name": f"p{i}_flip", "source": f"vid{i}", "preprocessor": "flip", "model": "hg"}
        for i in range(3, 7)
    ]
    output_points = {v: {} for v in views}
    for p in pathways:
        view = f"cam{p['source'][3:]}"
        side = "l" if "flip" in p["name"] else "r"
        output_points[view].update(
            {f"{side}{c}": {"pathway": p["name"], "out_channel": c} for c in range(19)}
        )
    return {
        "sources": [{"name": f"vid{i}", "filename": f"camera_{i}.mp4"} for i in range(N_SOURCES)],
        "skeleton": {"point_names": points},
        "cameras": {v: {} for v in views},
        "pose2d": {
            "precision": precision,
            "batch_size": batch_size,
            "decode_buffer": 4,
            "device": device,
            "preprocessors": [{"name": "flip", "ops": [{"op": "fliplr"}]}],
            "models": [
                {
                    "name": "hg",
                    "class": "hourglass",
                    "weights": str(checkpoint),
                    "input_size": [256, 512],
                    "mean": 0.22,
                    "n_out_channels": 19,
                }
            ],
            "pathways": pathways,
            "output_points": output_points,
        },
    }


def plan_of(data: dict) -> DetectionPlan:
    """The detection plan of :func:`plan_data`'s tables."""
    return DetectionPlan.from_tables(
        data["sources"], data["pose2d"], list(data["cameras"]), data["skeleton"]["point_names"]
    )


def settings_of(data: dict) -> Pose2dParams:
    """The detector settings :func:`plan_data` (or a ``--cold-start`` spec) sets."""
    keys = ("precision", "batch_size", "decode_buffer", "device", "compile")
    return Pose2dParams(**{k: data["pose2d"][k] for k in keys if k in data["pose2d"]})


# --- measurements -------------------------------------------------------------------


class RssSampler(threading.Thread):
    """Peak resident memory of this process, sampled every ``interval`` s (Linux /proc)."""

    def __init__(self, interval: float = 0.01):
        super().__init__(daemon=True)
        self.interval, self.peak, self._halt = interval, 0, threading.Event()
        self.page = os.sysconf("SC_PAGE_SIZE")

    def rss(self) -> int:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * self.page

    def run(self):
        while not self._halt.is_set():
            self.peak = max(self.peak, self.rss())
            time.sleep(self.interval)

    def stop(self) -> int:
        self._halt.set()
        self.join()
        self.peak = max(self.peak, self.rss())
        return self.peak


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def bench_decode(clip: Path, frames: int, block: int, gpu: bool) -> tuple[float, float, float]:
    """Frames/s of one RGB reader alone, and aggregate frames/s of 7 prefetch threads
    as detection runs them (YUV planes into pinned memory on a GPU), and the latter in RGB."""
    reader = io.open_reader(clip)
    t = time.perf_counter()
    n = sum(len(b) for b in reader.stream_blocks(block_size=block))
    single = n / (time.perf_counter() - t)
    rates = []
    for yuv in (gpu, False):
        rates.append(_bench_prefetch(clip, block, pin=gpu, raw_yuv=yuv))
        assert rates[-1][1] == frames * N_SOURCES, rates[-1]
    assert n == frames
    return single, rates[0][0], rates[1][0]


def _bench_prefetch(clip: Path, block: int, pin: bool, raw_yuv: bool) -> tuple[float, int]:
    prefetchers = [
        stream.BlockPrefetcher(f"s{i}", [clip], block_size=block, depth=4, pin=pin, raw_yuv=raw_yuv)
        for i in range(N_SOURCES)
    ]
    t = time.perf_counter()
    for p in prefetchers:
        p.start()
    total = 0
    for p in prefetchers:
        while (b := p.get()) is not stream.END_OF_STREAM:
            total += len(b)
    return total / (time.perf_counter() - t), total


def flops_per_image(stacks: int) -> float:
    """Forward FLOPs (2 x multiply-adds of the convolutions) of one 256x512 image."""
    from torch.utils.flop_counter import FlopCounterMode

    net = HourglassNet(num_stacks=stacks).eval()
    with FlopCounterMode(display=False) as counter, torch.inference_mode():
        net(torch.zeros(1, 3, 256, 512))
    return float(counter.get_total_flops())


def n_parameters(stacks: int) -> int:
    """Trainable parameters of the network (batch-norm running statistics excluded)."""
    return sum(p.numel() for p in HourglassNet(num_stacks=stacks).parameters())


def bench_decode_methods(
    device: torch.device, batch: int, seconds: float = 1.0
) -> dict[str, float]:
    """Images/s of arg-max + sub-pixel decoding of ``batch`` 19x64x128 heatmaps per method."""
    gen = torch.Generator().manual_seed(0)
    hm = torch.rand(batch, 19, 64, 128, generator=gen).to(device)
    rates = {}
    for method in decode.SUBPIXEL_METHODS:
        decode.decode_argmax(hm, method)
        sync(device)
        n, t = 0, time.perf_counter()
        while time.perf_counter() - t < seconds or n < 3:
            decode.decode_argmax(hm, method)
            n += 1
        sync(device)
        rates[method] = n * batch / (time.perf_counter() - t)
    return rates


def bench_forward(model: LoadedModel, batch: int, seconds: float) -> float:
    """Images/s of the network alone on preprocessed input."""
    x = model.preprocess(
        torch.randint(0, 255, (batch, FRAME_H, FRAME_W, 3), dtype=torch.uint8, device=model.device)
    )
    for _ in range(3):
        model.heatmaps(x)
    sync(model.device)
    n, t = 0, time.perf_counter()
    while time.perf_counter() - t < seconds or n < 3:
        model.heatmaps(x)
        n += 1
    sync(model.device)
    return n * batch / (time.perf_counter() - t)


def bench_end_to_end(plan, model, clip: Path, frames: int, batch: int):
    """End-to-end images/s and frames/s, the points, and where the detection loop's
    thread spent the run (fractions of the wall time, ``run_detection(timings=...)``)."""
    sources = {s: [clip] for s in plan.sources}
    # warm-up on a short prefix is not possible with whole files; the first block
    # carries compile/cudnn autotuning, so time from the second run
    timings: dict[str, float] = {}
    t = time.perf_counter()
    out = stream.run_detection(
        plan, {"hg": model}, sources, batch_size=batch, decode_buffer=4, timings=timings
    )
    sync(model.device)
    dt = time.perf_counter() - t
    n_images = frames * len(plan.active_pathways())
    shares = {k: v / dt for k, v in timings.items()}
    return n_images / dt, frames / dt, out.pts2d, shares


def bench_memory(
    plan, model, clips: dict[int, Path], batch: int, full: bool
) -> dict[int, tuple[int, int]]:
    """Peak RSS (and its rise over the pre-run RSS) streaming each clip length."""
    out = {}
    for n, clip in clips.items():
        sources = {s: [clip] for s in plan.sources}
        sampler = RssSampler()
        base = sampler.rss()
        sampler.start()
        if full:
            stream.run_detection(plan, {"hg": model}, sources, batch_size=batch, decode_buffer=4)
        else:  # decode threads + torch preprocessing of every pathway, no network
            prefetchers = {
                s: stream.BlockPrefetcher(s, sources[s], block_size=batch, depth=4)
                for s in plan.sources
            }
            for p in prefetchers.values():
                p.start()
            while True:
                blocks = {s: p.get() for s, p in prefetchers.items()}
                if any(b is stream.END_OF_STREAM for b in blocks.values()):
                    break
                for s, block in blocks.items():
                    for pathway in plan.pathways_on(s):
                        model.preprocess(block.to(model.device), pathway.ops)
        peak = sampler.stop()
        out[n] = (peak, peak - base)
    return out


# --- cold start: one recording per fresh process, as each Snakemake pose2d job -------

COLD_START_MODES = (
    ("compile: false", False, "empty"),
    ("compile: auto, empty cache", "auto", "empty"),
    ("compile: true, empty cache (cold)", True, "empty"),
    ("compile: true, warm cache", True, "warm"),
    ("compile: auto, warm cache", "auto", "warm"),
)


def one_recording(spec_path: Path) -> None:
    """The child of ``--cold-start``: load the models as a pose2d job does (the policy
    sees the recording's frame count) and detect over the clip; print one JSON line."""
    import json

    spec = json.loads(Path(spec_path).read_text())
    data = spec["config"]
    plan = plan_of(data)
    t = time.perf_counter()
    models = load_models(plan, settings_of(data), frames=spec["frames"])
    loaded = time.perf_counter() - t
    sources = {s: [Path(spec["clip"])] for s in plan.sources}
    stream.run_detection(
        plan, models, sources, batch_size=data["pose2d"]["batch_size"], decode_buffer=4
    )
    model = next(iter(models.values()))
    cuda = model.device.type == "cuda"
    if cuda:
        torch.cuda.synchronize()
    print(
        "RESULT "
        + json.dumps(
            {
                "load_s": loaded,
                "compiled": model.compiled,
                "status": model.compile_status,
                "peak_gib": torch.cuda.max_memory_allocated() / 2**30 if cuda else None,
            }
        )
    )


def bench_cold_start(args, device: torch.device, work: Path) -> None:
    """Wall time of one recording in a fresh process per compile mode, empty then warm cache."""
    import json
    import shutil
    import subprocess

    cuda = device.type == "cuda"
    frames = args.frames or (900 if cuda else 8)
    stacks = args.stacks or (8 if cuda else 1)
    batch = int((args.batch_sizes or ("16" if cuda else "4")).split(",")[0])
    precision = (args.precision or ("bfloat16" if cuda else "float32")).split(",")[0]
    torch.manual_seed(0)
    checkpoint = work / "random.tar"
    from flylib.pose2d.weights import save_checkpoint

    save_checkpoint(HourglassNet(num_stacks=stacks), checkpoint)
    clip = make_clip(work / f"clip_{frames}.mp4", frames)
    cache = work / "cache"
    shutil.rmtree(cache, ignore_errors=True)
    print(
        f"cold start: one {frames}-frame recording ({N_SOURCES} sources, 8 pathways = "
        f"{frames * 8} images), {stacks}-stack hourglass, {precision}, batch {batch}, "
        f"a fresh process per mode (FLYLIB_CACHE={cache})"
    )
    print("\n mode                                 wall s  images/s  vs compile:false  compiled")
    eager_wall = None
    for label, setting, cache_state in COLD_START_MODES:
        if cache_state == "empty":
            shutil.rmtree(cache, ignore_errors=True)
        data = plan_data(checkpoint, batch, precision, str(device))
        data["pose2d"]["compile"] = setting
        spec = work / "cold_start.json"
        spec.write_text(json.dumps({"config": data, "frames": frames, "clip": str(clip)}))
        env = {**os.environ, "FLYLIB_CACHE": str(cache)}
        t = time.perf_counter()
        done = subprocess.run(
            [sys.executable, __file__, "--one-recording", str(spec)],
            env=env,
            capture_output=True,
            text=True,
        )
        wall = time.perf_counter() - t
        lines = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
        if done.returncode or not lines:
            print(f" {label:36s} failed: {(done.stderr.strip().splitlines() or ['?'])[-1]}")
            continue
        result = json.loads(lines[-1][len("RESULT ") :])
        if setting is False:
            eager_wall = wall
        ratio = f"{wall / eager_wall:15.2f}x" if eager_wall else f"{'-':>16s}"
        state = result["status"] or "no"
        memory = f", peak GPU {result['peak_gib']:.2f} GiB" if result["peak_gib"] else ""
        print(
            f" {label:36s} {wall:6.1f} {frames * 8 / wall:9.1f} {ratio}  {state} "
            f"(models ready in {result['load_s']:.1f} s{memory})"
        )


# --- driver ---------------------------------------------------------------------------


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto", help="auto, cpu, cuda, mps")
    ap.add_argument(
        "--precision",
        default=None,
        help="comma list (default: bfloat16,float16,float32 on CUDA; float32 on CPU)",
    )
    ap.add_argument(
        "--batch-sizes", default=None, help="comma list (default: 32,64,128 on CUDA; 4 on CPU)"
    )
    ap.add_argument(
        "--stacks", type=int, default=None, help="hourglass stacks (default 8 on CUDA, 1 on CPU)"
    )
    ap.add_argument(
        "--frames",
        type=int,
        default=None,
        help="clip length for decode/end-to-end (default 1000 CUDA, 16 CPU)",
    )
    ap.add_argument("--compile", default="auto", choices=["auto", "on", "off", "both"])
    ap.add_argument(
        "--compile-mode",
        default="aot",
        choices=["aot", "reduce-overhead", "max-autotune"],
        help="compiled runs: flylib's AOTInductor package + CUDA graph (aot, cached under "
        "the workdir), or torch.compile's JIT in this mode, for comparison",
    )
    ap.add_argument(
        "--freezing",
        action="store_true",
        help="Inductor freezing (constant-folds weights, folds BatchNorm into convolutions)",
    )
    ap.add_argument("--forward-seconds", type=float, default=3.0)
    ap.add_argument(
        "--memory-frames", default="500,5000", help="the two clip lengths compared ('' to skip)"
    )
    ap.add_argument("--memory-mode", default="auto", choices=["auto", "full", "decode"])
    ap.add_argument(
        "--workdir", default=None, help="where to write the synthetic clips (default: a temp dir)"
    )
    ap.add_argument(
        "--cold-start",
        action="store_true",
        help="only the cold-start comparison: one recording per fresh process per compile "
        "mode, empty then warm compiled-detector cache (--frames default 900 on CUDA)",
    )
    ap.add_argument("--one-recording", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.one_recording:
        one_recording(args.one_recording)
        return
    device = select_device(args.device)
    cuda = device.type == "cuda"
    precisions = (args.precision or ("bfloat16,float16,float32" if cuda else "float32")).split(",")
    batches = [int(b) for b in (args.batch_sizes or ("32,64,128" if cuda else "4")).split(",")]
    stacks = args.stacks or (8 if cuda else 1)
    frames = args.frames or (1000 if cuda else 16)
    compile_modes = {"auto": [cuda], "on": [True], "off": [False], "both": [False, True]}[
        args.compile
    ]
    if args.freezing:
        # bound to its own name: a bare `import torch._inductor.config` would make
        # `torch` a local of main() and unbound everywhere else in it
        import torch._inductor.config as inductor_config

        inductor_config.freezing = True
    if cuda:
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
        print(f"device: {torch.cuda.get_device_name()}  torch {torch.__version__}")
    else:
        print(
            f"device: {device} ({torch.get_num_threads()} torch threads, {os.cpu_count()} cpus)  torch {torch.__version__}"
        )
    print(
        f"hourglass: {stacks} stacks, 256x512 input, 19 channels; plan: {N_SOURCES} sources, 8 pathways"
    )
    if cuda:
        print(
            f"compiled runs: mode {args.compile_mode}{', Inductor freezing' if args.freezing else ''}"
        )

    work = Path(args.workdir or tempfile.mkdtemp(prefix="flylib-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    if args.cold_start:
        bench_cold_start(args, device, work)
        return
    t = time.perf_counter()
    clip = make_clip(work / f"clip_{frames}.mp4", frames)
    print(f"synthetic clip: {frames} frames 960x480 in {time.perf_counter() - t:.1f} s")

    single, parallel, parallel_rgb = bench_decode(clip, frames, block=max(batches), gpu=cuda)
    print(
        f"\ndecode: {single:8.0f} frames/s one source (RGB) | {parallel:8.0f} frames/s total over {N_SOURCES} "
        f"parallel sources{' (YUV, converted on the GPU)' if cuda else ''} = {parallel / N_SOURCES:.0f} recording "
        f"frames/s = {parallel / N_SOURCES * 8:.0f} pathway images/s"
    )
    if cuda:
        print(
            f"        {parallel_rgb:8.0f} frames/s total over {N_SOURCES} sources when converting to RGB on the CPU"
        )

    gflop = flops_per_image(stacks) / 1e9
    print(
        f"forward cost: {gflop:.1f} GFLOP per 256x512 image ({gflop / 2:.1f} G multiply-adds), "
        f"{n_parameters(stacks):,} parameters"
    )

    rates = bench_decode_methods(device, max(batches))
    base = rates["parabola"]
    print(
        "decode heatmaps (arg-max + sub-pixel), images/s: "
        + ", ".join(f"{m} {r:,.0f} ({r / base:.2f}x parabola)" for m, r in rates.items())
    )

    torch.manual_seed(0)
    checkpoint = work / "random.tar"
    from flylib.pose2d.weights import save_checkpoint

    save_checkpoint(HourglassNet(num_stacks=stacks), checkpoint)
    from flylib.pose2d.weights import load_hourglass

    print(
        "\n precision  batch compile | forward img/s  TFLOP/s  %bf16peak | end-to-end img/s  frames/s  bound"
    )
    best = (0.0, None)
    points = {}
    for precision in precisions:
        for batch in batches:
            for compiled in compile_modes:
                plan = plan_of(plan_data(checkpoint, batch, precision, str(device)))
                aot = compiled and cuda and args.compile_mode == "aot"
                model = LoadedModel(
                    plan.models["hg"],
                    load_hourglass(checkpoint),
                    device,
                    precision=precision,
                    batch_size=batch,
                    compiled=aot,
                    cache_root=work / "compiled",
                )
                if compiled and cuda and not aot:  # torch.compile (JIT), for comparison
                    model._forward = torch.compile(
                        model.net.heatmaps, dynamic=False, mode=args.compile_mode
                    )
                    model.compiled = True
                if cuda:
                    torch.cuda.reset_peak_memory_stats()
                try:
                    fwd = bench_forward(model, batch, args.forward_seconds)
                    bench_end_to_end(
                        plan, model, clip, frames, batch
                    ) if compiled else None  # warm compile
                    e2e, fps, pts, shares = bench_end_to_end(plan, model, clip, frames, batch)
                except torch.OutOfMemoryError:
                    print(f" {precision:9s} {batch:6d} {str(compiled):7s} | out of memory")
                    torch.cuda.empty_cache()
                    continue
                tflops = fwd * gflop / 1e3
                bound = "decode" if parallel / N_SOURCES * 8 < 1.15 * e2e else "network"
                print(
                    f" {precision:9s} {batch:6d} {str(compiled):7s} | {fwd:13.1f} {tflops:8.2f} {100 * tflops / H100_BF16_PEAK_TFLOPS:9.2f}"
                    f"  | {e2e:16.1f} {fps:9.1f}  {bound}"
                )
                if cuda:
                    print(
                        f"     peak GPU memory {torch.cuda.max_memory_allocated() / 2**30:.2f} GiB"
                        + (f" (compiled detector: {model.compile_status})" if aot else "")
                    )
                print(
                    "     detection loop: "
                    + ", ".join(f"{k} {100 * v:.0f}%" for k, v in shares.items())
                    + f", other {100 * (1 - sum(shares.values())):.0f}% of the wall time"
                )
                points[(precision, batch)] = pts
                if e2e > best[0]:
                    best = (e2e, (precision, batch, compiled))
                del model
                if cuda:
                    torch.cuda.empty_cache()
    print(
        f"\nbest end-to-end: {best[0]:.0f} images/s with {best[1]} (target on H100: >= 1500 bf16)"
    )
    for (precision, batch), pts in points.items():
        ref = points.get(("float32", batch))
        if precision != "float32" and ref is not None:
            moved = np.linalg.norm(pts - ref, axis=-1)
            print(
                f"{precision} vs float32 points (batch {batch}, random weights): median shift "
                f"{np.nanmedian(moved):.2f} px, {np.nanmean(moved < 1.0) * 100:.0f}% within 1 px"
            )

    if args.memory_frames:
        lengths = [int(n) for n in args.memory_frames.split(",")]
        full = args.memory_mode == "full" or (args.memory_mode == "auto" and cuda)
        clips = {}
        for n in lengths:
            t = time.perf_counter()
            clips[n] = make_clip(work / f"mem_{n}.mp4", n, seed=1)
            print(f"memory clip {n} frames written in {time.perf_counter() - t:.1f} s")
        batch = batches[0]
        plan = plan_of(plan_data(checkpoint, batch, precisions[0], str(device)))
        model = LoadedModel(
            plan.models["hg"],
            load_hourglass(checkpoint),
            device,
            precision=precisions[0],
            batch_size=batch,
            compiled=False,
        )
        result = bench_memory(plan, model, clips, batch, full)
        print(
            f"\nmemory ({'full detection' if full else 'decode + preprocessing'}, batch {batch}, buffer 4):"
        )
        for n, (peak, rise) in result.items():
            print(
                f"  {n:6d} frames: peak RSS {peak / 2**20:8.0f} MiB (+{rise / 2**20:6.0f} MiB over the start)"
            )
        small, large = result[lengths[0]][0], result[lengths[-1]][0]
        print(f"  ratio {lengths[-1]}/{lengths[0]} frames: {large / small:.2f}x (target <= 2x)")


if __name__ == "__main__":
    main()
