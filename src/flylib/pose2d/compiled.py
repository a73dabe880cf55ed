"""The detector compiled ahead of time, cached on disk once per machine, and the
``pose2d.compile`` policy that decides whether a recording uses it.

A compiled detector is an AOTInductor package (``torch.export`` then
``torch._inductor.aoti_compile_and_package``) of the network with its BatchNorms folded into the
convolutions, returning the last stack's heatmaps in float32. It lives under
``<flylib cache>/detector/`` (:func:`flylib.paths.cache_dir`), named by the digest of a
:class:`CompileKey`: the weights' SHA-256, the torch version, the device (GPU name and compute
capability, or the CPU's architecture and vector ISA), the precision, the batch size and the
input shape. Any change of one of them is another file, so a stale package is never loaded.
Packages are written under a temporary name and renamed (atomic); a package that fails to load,
or lacks its key file, is rebuilt with a warning, never a crash. The first job on a machine pays
the compilation (a *cold start*, said so in its log); every later job loads it in seconds.
"""

from __future__ import annotations

import hashlib
import json
import logging
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn

from ..paths import atomic_path, cache_dir
from .model import Bottleneck, HourglassNet

log = logging.getLogger(__name__)

#: Bumped when the package's contents change meaning (its inputs/outputs or folding).
FORMAT = 1

# The policy's cost model, from one H100 80GB with DeepFly2D's sh8 in bf16 at batch 16, one fresh
# process per 900-frame, 8-pathway recording: eager 185 pathway images/s, compiled 863 images/s;
# compiling cost ~165 s of a cold start; loading a cached package a few seconds.
EAGER_IMAGES_PER_S = 185.0
COMPILED_IMAGES_PER_S = 863.0
COLD_COMPILE_S = 165.0
CACHED_LOAD_S = 5.0
#: Below this batch size ``compile: auto`` stays eager (launch-bound either way).
COMPILE_MIN_BATCH = 8


def _fold(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> None:
    """Fold an eval-mode ``bn`` that follows ``conv`` into ``conv``'s weights, in place."""
    scale = bn.weight.double() / torch.sqrt(bn.running_var.double() + bn.eps)
    weight = conv.weight.double() * scale.reshape(-1, 1, 1, 1)
    bias = conv.bias.double() if conv.bias is not None else torch.zeros_like(scale)
    bias = (bias - bn.running_mean.double()) * scale + bn.bias.double()
    conv.weight.data = weight.to(conv.weight.dtype)
    if conv.bias is None:
        conv.bias = nn.Parameter(bias.to(conv.weight.dtype))
    else:
        conv.bias.data = bias.to(conv.bias.dtype)


def fold_batchnorm(net: HourglassNet) -> HourglassNet:
    """An eval-mode copy of ``net`` (left untouched) with every BatchNorm that directly follows a
    convolution folded into it, now :class:`torch.nn.Identity`: the same heatmaps to float
    rounding, with fewer layers (inference only).

    The network is pre-activation: a bottleneck's ``bn2``/``bn3`` follow ``conv1``/``conv2``, the
    stem's ``bn1`` follows ``conv1`` and each ``fc`` is conv, BN, ReLU; those fold. A bottleneck's
    ``bn1`` acts on the sum of two branches and stays.
    """
    import copy

    folded = copy.deepcopy(net).eval()
    with torch.no_grad():
        _fold(folded.conv1, folded.bn1)
        folded.bn1 = nn.Identity()
        for module in folded.modules():
            if isinstance(module, Bottleneck):
                _fold(module.conv1, module.bn2)
                _fold(module.conv2, module.bn3)
                module.bn2, module.bn3 = nn.Identity(), nn.Identity()
        for block in folded.fc:
            _fold(block[0], block[1])
            block[1] = nn.Identity()
    return folded


class LastStack(nn.Module):
    """``net`` in ``dtype`` returning the last stack's heatmaps ``(N, C, h, w)`` in float32: what
    is exported (one output tensor; the precision fixed in the weights, autocast's cast done once).
    """

    def __init__(self, net: HourglassNet, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.net = net.to(dtype)
        self.dtype = dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.to(self.dtype))[-1].float()


def weights_digest(net: nn.Module) -> str:
    """SHA-256 of a network's state (names, dtypes, shapes and values), hex."""
    h = hashlib.sha256()
    for name, tensor in sorted(net.state_dict().items()):
        t = tensor.detach().to("cpu").contiguous().reshape(-1)
        h.update(f"{name}:{t.dtype}:{tuple(tensor.shape)};".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def device_tag(device: torch.device) -> str:
    """What compiled code depends on: GPU name and compute capability, or CPU arch and ISA."""
    if device.type == "cuda":
        major, minor = torch.cuda.get_device_capability(device)
        return f"cuda:{torch.cuda.get_device_name(device)}:sm{major}{minor}"
    return f"{device.type}:{platform.machine()}:{torch.backends.cpu.get_cpu_capability()}"


@dataclass(frozen=True)
class CompileKey:
    """Everything a compiled detector depends on; its :meth:`digest` names the cache entry.
    ``batch_size`` is every forward's fixed batch, ``input_shape`` ``(channels, height, width)``."""

    weights: str
    torch_version: str
    device: str
    precision: str
    batch_size: int
    input_shape: tuple[int, int, int]
    format: int = FORMAT

    @classmethod
    def for_model(
        cls,
        net: nn.Module,
        device: torch.device,
        precision: str,
        batch_size: int,
        input_shape: tuple[int, int, int],
    ) -> CompileKey:
        """The key of ``net`` compiled for this device, precision, batch and input."""
        return cls(
            weights=weights_digest(net),
            torch_version=torch.__version__,
            device=device_tag(device),
            precision=precision,
            batch_size=int(batch_size),
            input_shape=tuple(int(s) for s in input_shape),
        )

    def as_json(self) -> str:
        """The key as sorted JSON (what is stored beside the package)."""
        return json.dumps(asdict(self), sort_keys=True)

    def digest(self) -> str:
        """A 32-hex-digit name for the cache entry."""
        return hashlib.sha256(self.as_json().encode()).hexdigest()[:32]


def cache_root() -> Path:
    """Where compiled detectors live: ``<cache_dir()>/detector``."""
    return cache_dir() / "detector"


def entry_paths(key: CompileKey, root: Path | None = None) -> tuple[Path, Path]:
    """``(package, key file)`` of ``key``'s cache entry."""
    base = Path(root) if root is not None else cache_root()
    name = key.digest()
    return base / f"{name}.pt2", base / f"{name}.json"


def is_cached(key: CompileKey, root: Path | None = None) -> bool:
    """Whether a complete entry for ``key`` exists (package and matching key file)."""
    package, meta = entry_paths(key, root)
    try:
        return package.is_file() and meta.read_text() == key.as_json()
    except (OSError, UnicodeDecodeError):
        return False


def compile_package(net: HourglassNet, key: CompileKey, device: torch.device, package: Path):
    dtype = getattr(torch, key.precision)  # float32 | float16 | bfloat16
    module = LastStack(fold_batchnorm(net), dtype).to(device).eval()
    example = torch.zeros((key.batch_size, *key.input_shape), device=device)
    with torch.no_grad():
        exported = torch.export.export(module, (example,))
    with atomic_path(package) as tmp:
        torch._inductor.aoti_compile_and_package(exported, package_path=str(tmp))


def _load_package(package: Path, device: torch.device):
    index = device.index if device.type == "cuda" and device.index is not None else -1
    return torch._inductor.aoti_load_package(str(package), device_index=index)


def load_or_compile(
    net: HourglassNet, key: CompileKey, device: torch.device, *, root: Path | None = None
) -> tuple[object, str]:
    """``(forward, status)``: the compiled detector for ``key`` (:meth:`CompileKey.for_model` of
    the eval-mode ``net``), loaded from the cache (``root``, default :func:`cache_root`), else
    compiled into it. ``forward`` maps a ``(batch_size, C, H, W)`` float32 contiguous input on
    ``device`` to last-stack heatmaps ``(batch_size, n_out_channels, H/4, W/4)`` float32;
    ``status`` is ``"cached"`` (loaded), ``"cold"`` (compiled now: nothing was cached) or
    ``"rebuilt"`` (the cached entry was damaged and was compiled again)."""
    package, meta = entry_paths(key, root)
    status = "cold"
    if package.exists() or meta.exists():
        if is_cached(key, root):
            try:
                return _load_package(package, device), "cached"
            except Exception as err:  # noqa: BLE001 - any damage means rebuild
                reason = " ".join(str(err).split())[:200] or type(err).__name__
        else:
            reason = "its key file is missing or does not match"
        log.warning("compiled detector %s is unusable (%s); compiling it again", package, reason)
        package.unlink(missing_ok=True)
        meta.unlink(missing_ok=True)
        status = "rebuilt"
    t = time.perf_counter()
    log.info(
        "compiling the detector (cold start: nothing cached for this checkpoint, torch, "
        "device, precision and batch) into %s; later jobs load it in seconds",
        package,
    )
    compile_package(net, key, device, package)
    with atomic_path(meta) as tmp:
        tmp.write_text(key.as_json())
    log.info("compiled the detector in %.1f s", time.perf_counter() - t)
    return _load_package(package, device), status


class CudaGraphForward:
    """Replays one CUDA graph of ``forward`` (fixed shape, that of ``example``) on a static input
    buffer, one launch per batch, so the detection loop's Python threads (decode, scatter) cannot
    starve kernel launches. Outputs live in a buffer the next replay overwrites: copy them."""

    def __init__(self, forward, example: torch.Tensor):
        self.forward = forward
        self.static_input = example.clone()
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(3):  # allocator and library warm-up before capture
                forward(self.static_input)
        torch.cuda.current_stream().wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.static_output = forward(self.static_input)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        self.static_input.copy_(x)
        self.graph.replay()
        return self.static_output


def decide_compile(
    setting: bool | str,
    device: torch.device,
    *,
    batch_size: int,
    images: int | None,
    cached: bool,
) -> tuple[bool, str]:
    """Whether this job compiles the detector, and why (one line for the log).

    ``setting`` is ``pose2d.compile``: ``True`` and ``False`` are obeyed (compiling only on CUDA or
    the CPU, where AOTInductor builds); ``auto`` compiles on CUDA when the estimated time of the
    recording with the compiled network (loading a cached package, or a cold compilation, plus the
    work at the compiled rate) is below its time eager, so it never makes a recording slower than
    eager by its cost model. ``images`` is the recording's pathway images (frames x pathways),
    ``None`` if unknown; ``cached`` whether the package is cached.
    """
    if setting is False:
        return False, "pose2d.compile is false"
    if device.type not in ("cuda", "cpu"):
        return False, f"ahead-of-time compilation does not support {device.type}; eager"
    if setting is True:
        state = "loading the cached package" if cached else "cold start: compiling now"
        return True, f"pose2d.compile is true ({state})"
    if device.type != "cuda":
        return False, f"auto: eager on {device.type} (compiling pays on a CUDA GPU)"
    if batch_size < COMPILE_MIN_BATCH:
        return False, f"auto: batch {batch_size} < {COMPILE_MIN_BATCH}; eager"
    if images is None:
        return bool(cached), "auto: frame count unknown; " + (
            "using the cached package" if cached else "eager (nothing cached)"
        )
    eager = images / EAGER_IMAGES_PER_S
    overhead = CACHED_LOAD_S if cached else COLD_COMPILE_S
    compiled = overhead + images / COMPILED_IMAGES_PER_S
    source = "load the cached package" if cached else "compile (cold cache)"
    if compiled < eager:
        return True, (
            f"auto: {images} images: {source} ~{overhead:.0f} s + ~{images / COMPILED_IMAGES_PER_S:.0f} s "
            f"beats ~{eager:.0f} s eager"
        )
    return False, (
        f"auto: {images} images: {source} ~{overhead:.0f} s + ~{images / COMPILED_IMAGES_PER_S:.0f} s "
        f"would not beat ~{eager:.0f} s eager; eager"
        + ("" if cached else " (set pose2d.compile: true once to fill the cache for later jobs)")
    )
