"""Running a detector model on frames: device and precision choice, torch preprocessing, the
forward pass and on-device heatmap decoding."""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..config.params import Pose2dParams
from ..errors import ConfigError
from ..resources import usable_cpus
from . import compiled, decode
from .model import HourglassNet
from .plan import DetectionPlan, ModelSpec, Op, Resize
from .weights import load_hourglass, resolve_weights

log = logging.getLogger(__name__)

PRECISIONS = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def select_device(requested: str | torch.device | None = "auto") -> torch.device:
    """The torch device to detect on: ``auto`` picks CUDA, then Apple MPS, then the CPU."""
    if isinstance(requested, torch.device):
        return requested
    if requested in (None, "", "auto"):
        if torch.cuda.is_available():
            return torch.device("cuda")
        mps = getattr(torch.backends, "mps", None)
        if mps is not None and mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        device = torch.device(requested)
    except RuntimeError:
        raise ConfigError(
            f"pose2d.device: {requested!r} is not a torch device (use auto, cpu, cuda, cuda:1, mps)"
        ) from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            "pose2d.device: cuda was asked for but torch sees no CUDA GPU; use auto or cpu"
        )
    return device


# (Y scale, V->R, U->G, V->G, U->B) per colour matrix and range
_YUV_COEFFS = {
    ("bt601", "limited"): (255 / 219, 1.596027, 0.391762, 0.812968, 2.017232),
    ("bt709", "limited"): (255 / 219, 1.792741, 0.213249, 0.532909, 2.112402),
    ("bt601", "full"): (1.0, 1.402, 0.344136, 0.714136, 1.772),
    ("bt709", "full"): (1.0, 1.5748, 0.187324, 0.468124, 1.8556),
}


def yuv420p_to_rgb(
    planes: torch.Tensor, matrix: str = "bt601", value_range: str = "limited"
) -> torch.Tensor:
    """Planar YUV 4:2:0 ``(N, 3H/2, W)`` uint8 -> ``(N, H, W, 3)`` uint8 RGB, on the tensor's device.

    Chroma is upsampled by pixel repetition, as FFmpeg's default converter does; the result
    matches :meth:`flylib.io.VideoReader` RGB frames to within one grey level.
    """
    n, rows, w = planes.shape
    h = rows * 2 // 3
    y = planes[:, :h].float()
    chroma = planes[:, h:].reshape(n, 2, h // 2, w // 2).float() - 128.0
    chroma = chroma.repeat_interleave(2, dim=-2).repeat_interleave(2, dim=-1)
    u, v = chroma[:, 0], chroma[:, 1]
    ys, vr, ug, vg, ub = _YUV_COEFFS[(matrix, value_range)]
    if value_range == "limited":
        y = (y - 16.0) * ys
    rgb = torch.stack([y + vr * v, y - ug * u - vg * v, y + ub * u], dim=-1)
    return rgb.round_().clamp_(0, 255).to(torch.uint8)


def _autocast(device: torch.device, precision: str):
    dtype = PRECISIONS[precision]
    if dtype == torch.float32 or device.type == "cpu":
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


@dataclass
class LoadedModel:
    """A detector network (``net``, eval mode, on ``device``) ready for inference.

    ``precision`` is the forward precision, float32 on the CPU whatever was asked. With
    ``compiled`` the forward is the ahead-of-time compiled network (:mod:`flylib.pose2d.compiled`)
    from the on-disk cache ``cache_root`` (default ``<cache_dir()>/detector``) or compiled into it
    (``compile_status``: ``"cached"``, ``"cold"`` or ``"rebuilt"``); it has a fixed shape, so
    batches shorter than ``batch_size`` are padded to it.
    """

    spec: ModelSpec
    net: HourglassNet
    device: torch.device
    precision: str = "float32"
    batch_size: int = Pose2dParams.batch_size
    compiled: bool = False
    compile_status: str | None = None
    cache_root: Path | None = None
    _forward: Any = field(default=None, repr=False)
    _key: compiled.CompileKey | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.device.type == "cpu" and self.precision != "float32":
            log.debug("CPU inference runs in float32 (asked for %s)", self.precision)
            self.precision = "float32"
        self.net = self.net.to(self.device).eval()
        if self.device.type == "cuda":
            torch.backends.cudnn.benchmark = True
            self.net = self.net.to(memory_format=torch.channels_last)
        self._forward = self.net.heatmaps
        if self.compiled:
            self.compiled = False
            self.use_compiled()

    def use_compiled(self) -> str:
        """Switch the forward to the compiled network, loaded from the cache or compiled
        into it (a cold start); return :attr:`compile_status`."""
        forward, self.compile_status = compiled.load_or_compile(
            self.net, self.compile_key(), self.device, root=self.cache_root
        )
        if self.device.type == "cuda":
            forward = self._graphed(forward)
        self._forward, self.compiled = forward, True
        return self.compile_status

    def compile_key(self) -> compiled.CompileKey:
        """The compiled-detector cache key of this network, device, precision and batch."""
        if self._key is None:
            self._key = compiled.CompileKey.for_model(
                self.net, self.device, self.precision, self.batch_size, (3, *self.spec.input_size)
            )
        return self._key

    def is_cached(self) -> bool:
        """Whether the compiled network for :meth:`compile_key` is in the cache."""
        return compiled.is_cached(self.compile_key(), self.cache_root)

    def _graphed(self, forward):
        # One CUDA-graph replay per batch: the Python decode threads competing for the GIL cannot
        # starve kernel launches. Capture can fail (driver, memory): then the package runs as is.
        example = torch.zeros((self.batch_size, 3, *self.spec.input_size), device=self.device)
        try:
            with torch.inference_mode():
                return compiled.CudaGraphForward(forward, example)
        except RuntimeError as err:
            log.warning(
                "CUDA graph capture failed (%s); running the compiled detector without", err
            )
            return forward

    @property
    def heatmap_size(self) -> tuple[int, int]:
        """``(height, width)`` of the output heatmaps."""
        stride = self.net.output_stride()
        return self.spec.input_size[0] // stride, self.spec.input_size[1] // stride

    def preprocess(self, frames: torch.Tensor, ops: tuple[Op, ...] = ()) -> torch.Tensor:
        """``(N, H, W, 3)`` uint8 frames (on ``device``) -> normalised ``(N, 3, h, w)`` model input:
        ``ops`` (the pathway's preprocessor), resize, scale to ``[0, 1]``, ``(x - mean) / std``."""
        x = frames.permute(0, 3, 1, 2).float()
        for op in ops:
            x = op.apply(x)
        x = Resize(*self.spec.input_size).apply(x)
        x = x * (1.0 / (255.0 * self.spec.std)) - self.spec.mean / self.spec.std
        if self.device.type == "cuda":
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def heatmaps(self, x: torch.Tensor) -> torch.Tensor:
        """Last-stack heatmaps ``(N, C, h/4, w/4)`` in float32 for a model-input batch."""
        n = x.shape[0]
        outputs = []
        for start in range(0, n, self.batch_size):
            chunk = x[start : start + self.batch_size]
            short = chunk.shape[0]
            if self.compiled:
                if short < self.batch_size:
                    chunk = torch.cat(
                        [chunk, chunk[-1:].expand(self.batch_size - short, *chunk.shape[1:])]
                    )
                # exported for contiguous input; its layout choice (channels-last) is inside it
                with torch.inference_mode():
                    hm = self._forward(chunk.contiguous())
            else:
                with torch.inference_mode(), _autocast(self.device, self.precision):
                    hm = self._forward(chunk)
            # a copy: a CUDA-graph replay reuses its output buffer
            outputs.append(hm[:short].to(torch.float32, copy=True))
        return outputs[0] if len(outputs) == 1 else torch.cat(outputs)

    def detect(
        self, frames: torch.Tensor, ops: tuple[Op, ...] = (), *, k: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
        """Detect on raw frames: heatmap-cell ``xy (N, C, 2)``, ``conf (N, C)`` and, with ``k``, the
        top-``k`` candidates ``(xy (N, C, k, 2), score (N, C, k))``; ``spec.subpixel`` refines."""
        method = self.spec.subpixel
        with torch.inference_mode():
            hm = self.heatmaps(self.preprocess(frames, ops))
            xy, conf = decode.decode_argmax(hm, method)
            candidates = None
            if k:
                from ..pictorial import DEFAULT_PEAK_RADIUS, DEFAULT_PEAK_THRESHOLD

                candidates = decode.topk_peaks(
                    hm,
                    k,
                    radius=DEFAULT_PEAK_RADIUS,
                    threshold=DEFAULT_PEAK_THRESHOLD,
                    method=method,
                )
        return xy, conf, candidates


def load_models(
    plan: DetectionPlan,
    params: Pose2dParams | None = None,
    *,
    frames: int | None = None,
    cache_root: Path | None = None,
    allow_download: bool = True,
) -> dict[str, LoadedModel]:
    """Load every model the plan's active pathways use.

    ``params`` gives ``device``, ``precision``, ``batch_size`` and ``compile`` (default:
    :class:`~flylib.config.params.Pose2dParams`'s); ``frames`` is the recording's frame count, for
    ``compile: auto`` (the work is frames x the model's pathways;
    :func:`~flylib.pose2d.compiled.decide_compile`); ``cache_root`` the compiled-detector cache
    (default ``<cache_dir()>/detector``); ``allow_download`` whether an empty weights cache may be
    filled from the network. Raises :class:`WeightsError` if a model's weights cannot be found,
    downloaded or loaded.
    """
    params = params or Pose2dParams()
    dev = select_device(params.device)
    if dev.type == "cpu":  # torch's intra-op pool, sized like every other (flylib.resources)
        torch.set_num_threads(usable_cpus())
    precision = params.precision
    if precision not in PRECISIONS:
        raise ConfigError(f"pose2d.precision: {precision!r} is not one of {sorted(PRECISIONS)}")
    batch = int(params.batch_size)
    want_compile = params.compile
    models = {}
    pathways = plan.active_pathways()
    for name in dict.fromkeys(p.model for p in pathways):
        spec = plan.models[name]
        path = resolve_weights(
            spec.weights,
            model_name=name,
            model_class=spec.model_class,
            url=spec.url,
            sha256=spec.sha256,
            allow_download=allow_download,
        )
        net = load_hourglass(path, num_classes=spec.n_out_channels)
        model = LoadedModel(
            spec, net, dev, precision=precision, batch_size=batch, cache_root=cache_root
        )
        images = None if frames is None else frames * sum(p.model == name for p in pathways)
        use, reason = compiled.decide_compile(
            want_compile,
            dev,
            batch_size=batch,
            images=images,
            # hashing the weights costs a fraction of a second: only where it can matter
            cached=(want_compile is True or (want_compile == "auto" and dev.type == "cuda"))
            and model.is_cached(),
        )
        log.info("model %s: %s (%s)", name, "compiled detector" if use else "eager", reason)
        if use:
            status = model.use_compiled()
            log.info("model %s: compiled detector %s", name, _STATUS_WORDS[status])
        models[name] = model
        log.info(
            "model %s on %s (%s, batch %d%s)",
            name,
            dev,
            model.precision,
            batch,
            ", compiled" if use else "",
        )
    return models


_STATUS_WORDS = {
    "cached": "loaded from the cache",
    "cold": "compiled (cold start) and cached for later jobs",
    "rebuilt": "rebuilt (the cached one was damaged) and cached",
}
