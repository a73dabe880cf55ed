"""Detector checkpoints: locate (cache or download), verify, load strictly, save.

A checkpoint is what DeepFly3D publishes: a torch ``.tar`` holding ``{"state_dict": {...}}``
whose keys may carry ``module.`` (DataParallel) or ``model.`` (Lightning) prefixes. The network's
shape (number of stacks, output channels, widths) is read from the checkpoint itself, so an
``sh8`` and an ``sh2`` both load, and any key or shape mismatch is a
:class:`~flylib.errors.WeightsError` rather than a silently half-initialised network.

Integrity. Where a SHA-256 is known (a model's ``sha256`` in the config, or one pinned in
:data:`PUBLISHED_WEIGHTS`) every download and every use is checked against it. No SHA-256 of the
published DeepFly2D checkpoint is published by its authors, and none could be established here,
so none is pinned: instead the first download's hash is recorded beside the file
(``<file>.sha256``, trust on first use) and every later use is checked against that record, so a
cached file that changes afterwards (corruption, a swapped file) is refused with one line naming
it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
import re
import struct
import tempfile
import urllib.error
import urllib.request
from pathlib import Path

import torch

from ..errors import WeightsError
from .model import HourglassNet
from .published import PUBLISHED_WEIGHTS, cached_checkpoint, download_url

log = logging.getLogger(__name__)

_PREFIXES = ("module.", "model.")
_STACK_KEY = re.compile(r"^hg\.(\d+)\.")
_RES_KEY = re.compile(r"^res\.0\.(\d+)\.")


def sha256sum(path: str | Path) -> str:
    """Hex SHA-256 of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _verify(path: Path, sha256: str | None, what: str) -> None:
    if sha256 and sha256sum(path).lower() != sha256.lower():
        raise WeightsError(
            f"{path}: checksum mismatch for {what} (expected sha256 {sha256}); delete the file "
            "and let it download again, or fix the model's sha256"
        )


def recorded_sha256_path(path: str | Path) -> Path:
    """Where the hash of a downloaded checkpoint is recorded: ``<file>.sha256`` beside it."""
    path = Path(path)
    return path.with_name(path.name + ".sha256")


def _recorded_sha256(path: Path) -> str | None:
    """The hash recorded beside ``path`` at its first download, or ``None`` if none is."""
    record = recorded_sha256_path(path)
    if not record.is_file():
        return None
    fields = record.read_text(errors="replace").split()
    if not fields or not re.fullmatch(r"[0-9a-fA-F]{64}", fields[0]):
        raise WeightsError(
            f"{record}: not a SHA-256 record of {path.name}; delete {path} and {record} "
            "to download the weights again"
        )
    return fields[0].lower()


def _trust_on_first_use(path: Path, digest: str, what: str) -> None:
    """Record ``digest`` beside ``path`` in ``sha256sum`` format (atomically)."""
    record = recorded_sha256_path(path)
    tmp = record.with_name(f"{record.name}.{os.getpid()}.tmp")
    tmp.write_text(f"{digest}  {path.name}\n")
    os.replace(tmp, record)
    log.warning(
        "%s: no pinned SHA-256 for %s; recorded its hash %s in %s (trust on first use: later "
        "runs refuse the file if it changes)",
        path,
        what,
        digest,
        record,
    )


def _check_trusted_on_first_use(path: Path, what: str) -> None:
    """Check an unpinned cached checkpoint against the hash recorded at its first download; record
    one if there is none (a file put there by hand)."""
    digest = sha256sum(path)
    recorded = _recorded_sha256(path)
    if recorded is None:
        _trust_on_first_use(path, digest, what)
    elif digest != recorded:
        raise WeightsError(
            f"{path}: the {what} checkpoint changed since it was downloaded (sha256 {digest}, "
            f"recorded {recorded} in {recorded_sha256_path(path)}); delete both files to "
            "download it again"
        )


def download(url: str, dest: Path, *, sha256: str | None = None, timeout: float = 60.0) -> Path:
    """Download ``url`` to ``dest`` atomically (temporary sibling, verified, renamed); a failed
    download or a checksum mismatch is a :class:`WeightsError` saying where to put the file by hand.
    """
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=dest.name + ".", suffix=".part", dir=dest.parent)
    tmp = Path(tmp_name)
    try:
        log.info("downloading detector weights %s -> %s", url, dest)
        with os.fdopen(fd, "wb") as out, urllib.request.urlopen(url, timeout=timeout) as response:
            while chunk := response.read(1 << 20):
                out.write(chunk)
        _verify(tmp, sha256, url)
        os.replace(tmp, dest)
    except (urllib.error.URLError, OSError, TimeoutError) as exc:
        raise WeightsError(
            f"could not download the detector weights from {url} ({exc}); on a machine without "
            f"network, download that file elsewhere and put it at {dest} (or set "
            "pose2d.weights: {<model>: <path>} in the config, or FLYLIB_CACHE to the folder holding it)"
        ) from None
    finally:
        tmp.unlink(missing_ok=True)
    return dest


def resolve_weights(
    weights: str | Path | None,
    *,
    model_name: str = "deepfly2d",
    model_class: str = "hourglass",
    url: str | None = None,
    sha256: str | None = None,
    allow_download: bool = True,
) -> Path:
    """The existing checkpoint file a model uses, downloading the published one on first use.

    ``weights`` is a local checkpoint path, or empty/``None`` for the per-user cache;
    ``model_name`` is for messages; ``model_class`` selects the published checkpoint; ``url`` and
    ``sha256`` override the download address and expected checksum; ``allow_download`` says whether
    an empty cache may be filled from the network. Raises :class:`WeightsError` if a given path
    does not exist, or the cache is empty and cannot be filled.
    """
    if weights:
        path = Path(weights).expanduser()
        if not path.is_file():
            raise WeightsError(
                f"pose2d.weights.{model_name}: {path} does not exist; point it at the "
                "checkpoint file, or leave it empty to use the downloaded published weights"
            )
        _verify(path, sha256, f"model {model_name!r}")
        return path
    path = cached_checkpoint(model_name, model_class, url)
    url = download_url(model_class, url)
    sha256 = sha256 or PUBLISHED_WEIGHTS.get(model_class, {}).get("sha256")
    what = f"model {model_name!r}"
    if path.is_file():
        if sha256:
            _verify(path, sha256, what)
        else:
            _check_trusted_on_first_use(path, what)
        return path
    if not url:
        raise WeightsError(
            f"pose2d.models[{model_name}]: no weights given and no published checkpoint for class "
            f"{model_class!r}; set pose2d.weights.{model_name} to a checkpoint file"
        )
    if not allow_download:
        raise WeightsError(
            f"pose2d.models[{model_name}]: the weights cache {path} is empty and downloading is off; "
            f"download {url} and put it there"
        )
    download(url, path, sha256=sha256)
    if not sha256:  # a fresh download is the first use: its hash is the record from now on
        _trust_on_first_use(path, sha256sum(path), what)
    return path


def strip_prefixes(state_dict: dict) -> dict:
    """Drop ``module.`` / ``model.`` key prefixes (any nesting, as DataParallel/Lightning add)."""
    out = {}
    for key, value in state_dict.items():
        while key.startswith(_PREFIXES):
            key = key.split(".", 1)[1]
        out[key] = value
    return out


#: What ``torch.load(weights_only=True)`` raises on a damaged or foreign file (seen by fuzzing both
#: the zip and the legacy format): the restricted unpickler's UnpicklingError (also for a refused
#: global), the zip reader's RuntimeError, and the parse errors of the pickle stream and records.
_CHECKPOINT_PARSE_ERRORS = (
    pickle.UnpicklingError,
    RuntimeError,
    EOFError,
    OSError,
    ValueError,
    TypeError,
    KeyError,
    IndexError,
    AttributeError,
    AssertionError,
    OverflowError,
    MemoryError,
    struct.error,
)


def _load_failure(exc: BaseException) -> str:
    """What ``torch.load(weights_only=True)`` objected to, in a few words: never torch's advice to
    load with ``weights_only=False``, which would run code from the file."""
    text = " ".join(str(exc).split())
    refused = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
    if refused:
        return (
            f"it holds an object of class {refused.group(1)}, not only tensors and plain containers"
        )
    text = text.split("WeightsUnpickler error:")[-1].strip()
    sentences = [s for s in re.split(r"(?<=\.) ", text) if "weights_only" not in s]
    detail = (sentences[0] if sentences else "")[:200].rstrip(".")
    return f"{type(exc).__name__}: {detail}" if detail else type(exc).__name__


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """The network parameters of a checkpoint file (``{"state_dict": ...}``, the published format,
    or a bare state dict), prefixes stripped."""
    path = Path(path)
    try:
        # weights_only: torch's own restricted unpickler (tensors and plain containers); a
        # checkpoint that names any other global is refused, never run.
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except _CHECKPOINT_PARSE_ERRORS as exc:
        raise WeightsError(
            f"{path}: cannot read the checkpoint ({_load_failure(exc)}); it must be a torch "
            "file holding {'state_dict': ...} of tensors (flylib reads weights only, never "
            "code from the file)"
        ) from None
    state = payload.get("state_dict", payload) if isinstance(payload, dict) else None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise WeightsError(
            f"{path}: not a network checkpoint (expected a dict with a 'state_dict' of tensors)"
        )
    return strip_prefixes(state)


def infer_hourglass_config(
    state_dict: dict[str, torch.Tensor], *, source: str = "checkpoint"
) -> dict:
    """Read the hourglass's shape (stacks, classes, widths, blocks) from its parameters."""
    try:
        stacks = 1 + max(int(m.group(1)) for k in state_dict if (m := _STACK_KEY.match(k)))
        blocks = 1 + max(int(m.group(1)) for k in state_dict if (m := _RES_KEY.match(k)))
        return dict(
            num_stacks=stacks,
            num_blocks=blocks,
            num_classes=int(state_dict["score.0.weight"].shape[0]),
            inplanes=int(state_dict["conv1.weight"].shape[0]),
            num_feats=int(state_dict["layer3.0.conv1.weight"].shape[0]),
        )
    except (ValueError, KeyError) as exc:
        raise WeightsError(
            f"{source}: not a stacked-hourglass checkpoint (missing {exc}); expected DeepFly2D "
            "'hg' parameter names (conv1, layer1..3, hg.N..., score.N...)"
        ) from None


def load_hourglass(
    path: str | Path,
    *,
    num_classes: int | None = None,
    num_stacks: int | None = None,
    device: str | torch.device = "cpu",
) -> HourglassNet:
    """Build the hourglass a checkpoint describes and load it strictly, in eval mode, checking
    ``num_classes`` (the model's ``n_out_channels``) and ``num_stacks`` when given; a
    :class:`WeightsError` if the file is unreadable, is not an hourglass, or any key/shape differs.
    """
    state = read_state_dict(path)
    arch = infer_hourglass_config(state, source=str(path))
    if num_classes is not None and arch["num_classes"] != num_classes:
        raise WeightsError(
            f"{path}: the checkpoint outputs {arch['num_classes']} channels but the model's "
            f"n_out_channels is {num_classes}; fix n_out_channels or use the matching weights"
        )
    if num_stacks is not None and arch["num_stacks"] != num_stacks:
        raise WeightsError(
            f"{path}: the checkpoint has {arch['num_stacks']} stacks, expected {num_stacks}"
        )
    net = HourglassNet(**arch)
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = next((ln.strip() for ln in str(exc).splitlines()[1:] if ln.strip()), str(exc))
        layer2 = state.get("layer2.0.conv1.weight")
        if layer2 is not None and layer2.shape[0] == arch["inplanes"]:
            first += (
                "; its layer2 has the stem width, the layout of flylib's earlier, non-DeepFly2D "
                "network, which no DeepFly2D weights fit"
            )
        raise WeightsError(
            f"{path}: the checkpoint does not fit a {arch['num_stacks']}-stack hourglass ({first}); "
            "use a DeepFly2D hourglass checkpoint"
        ) from None
    log.info(
        "loaded %d-stack hourglass (%d outputs) from %s",
        arch["num_stacks"],
        arch["num_classes"],
        path,
    )
    return net.to(device).eval()


def save_checkpoint(net: HourglassNet, path: str | Path, *, prefix: str = "module.") -> Path:
    """Save a network in the published checkpoint format (``.tar`` by convention), atomically;
    ``prefix`` is the key prefix (``"module."`` as DataParallel checkpoints carry; ``""``: none)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {prefix + k: v.detach().cpu() for k, v in net.state_dict().items()}
    tmp = path.with_name(path.name + ".part")
    torch.save({"state_dict": state}, tmp)
    os.replace(tmp, path)
    return path


def load_detector(
    checkpoint: str | Path | None = None, *, device=None, num_classes: int | None = None
):
    """Load the hourglass detector from a checkpoint, in eval mode (strictly; shape read from the
    file), on ``device`` (default CPU).

    ``checkpoint`` is a DeepFly2D checkpoint (``{"state_dict": ...}``, ``module.``/``model.``
    prefixes allowed), or ``None`` for a freshly initialised, **untrained** 8-stack network
    (logged as a warning; for training or tests only). ``num_classes``, the expected output
    channels, is checked against the checkpoint. Raises :class:`WeightsError` if the file is
    unreadable or does not fit the network.
    """
    if checkpoint is None:
        log.warning("load_detector(None): returning an UNTRAINED hourglass network")
        return HourglassNet(num_classes=num_classes or 19).to(device or "cpu").eval()
    return load_hourglass(checkpoint, num_classes=num_classes, device=device or "cpu")
