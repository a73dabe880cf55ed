"""Where a detector model's checkpoint comes from, told without torch: the published checkpoints,
the per-user cache file each lands in, and whether a model's checkpoint is present or can be
downloaded (what validation checks before any job runs). :mod:`flylib.pose2d.weights` loads them."""

from __future__ import annotations

import socket
import tarfile
import threading
import urllib.parse
import urllib.request
import zipfile
from pathlib import Path
from typing import Any

from ..paths import cache_dir

#: The published DeepFly2D ``sh8`` checkpoint (its project's download link); ``sha256`` stays
#: ``None`` until one can be pinned from an authoritative source (:mod:`flylib.pose2d.weights`).
PUBLISHED_WEIGHTS = {
    "hourglass": {
        "url": "https://www.dropbox.com/s/csgon8uojr3gdd9/sh8_front_j8.tar?dl=1",
        "filename": "sh8_deepfly.tar",
        "sha256": None,
    }
}

#: Seconds validation waits for the weights host (name lookup and connection together) before it
#: calls the checkpoint not downloadable.
PROBE_TIMEOUT_S = 3.0


def cached_checkpoint(model_name: str, model_class: str, url: str | None = None) -> Path:
    """The cache file a model without a local ``weights`` path loads (and downloads to): named by
    the published checkpoint of ``model_class``, else by the model's own ``url``, else its name."""
    filename = PUBLISHED_WEIGHTS.get(model_class, {}).get("filename") or (
        Path(url.split("?")[0]).name if url else f"{model_name}.tar"
    )
    return cache_dir() / filename


def download_url(model_class: str, url: str | None = None) -> str | None:
    """The address a model's checkpoint downloads from: its own ``url``, else the published one."""
    return url or PUBLISHED_WEIGHTS.get(model_class, {}).get("url")


def host_reachable(url: str, timeout: float = PROBE_TIMEOUT_S) -> tuple[bool, str]:
    """``(reachable, why)``: whether a TCP connection to ``url``'s host opens within ``timeout``
    seconds (a ``file:`` URL: whether the file exists), and what failed (empty when reachable).

    The name lookup has no timeout of its own, so both run on a daemon thread that is abandoned
    when the time is up: an offline machine answers in ``timeout``.
    """
    parts = urllib.parse.urlsplit(url)
    if parts.scheme == "file":
        path = Path(urllib.request.url2pathname(parts.path))
        return (True, "") if path.is_file() else (False, f"{path} does not exist")
    if not parts.hostname:
        return False, f"{url!r} names no host"
    port = parts.port or (443 if parts.scheme == "https" else 80)
    outcome: list[str] = []

    def probe() -> None:
        try:
            with socket.create_connection((parts.hostname, port), timeout=timeout):
                outcome.append("")
        except OSError as exc:
            outcome.append(" ".join(str(exc).split()) or type(exc).__name__)

    thread = threading.Thread(target=probe, daemon=True, name="flylib-weights-probe")
    thread.start()
    thread.join(timeout)
    if not outcome:
        return False, f"no answer from {parts.hostname} within {timeout:g} s"
    return not outcome[0], outcome[0]


#: The start of a checkpoint in torch's legacy (pre-1.6) format: a pickle stream (``\\x80`` and
#: its protocol) whose first object is torch's magic number as a long.
_LEGACY_MAGIC = b"\x8a\x0a" + (0x1950A86A20F9469CFC6C).to_bytes(10, "little")


def container_problem(path: str | Path) -> str | None:
    """Why ``path`` is no file ``torch.save`` wrote, or ``None``; told from its layout alone, never
    unpickled. Accepted: torch's zip archive (with its ``data.pkl``), the legacy pickle stream (its
    magic number first), and the old tar layout (with its ``pickle`` member)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(16)
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as archive:
                names = archive.namelist()
            if any(name == "data.pkl" or name.endswith("/data.pkl") for name in names):
                return None
            return "a zip archive without torch's data.pkl"
        if head[:1] == b"\x80" and head[2:14] == _LEGACY_MAGIC:
            return None
        if tarfile.is_tarfile(path):
            with tarfile.open(path) as archive:
                if "pickle" in archive.getnames():
                    return None
            return "a tar archive without torch's pickle member"
    except (OSError, zipfile.BadZipFile, tarfile.TarError, EOFError) as exc:
        return f"cannot be read ({type(exc).__name__})"
    return "neither a torch.save zip archive nor torch's legacy format" if head else "empty"


def checkpoint_problem(spec: Any, key: str, timeout: float = PROBE_TIMEOUT_S) -> str | None:
    """Why a model's checkpoint will not be there when the detector starts, as one
    ``"<key>: <what is wrong; where to put the file>"`` line, else ``None``. ``spec`` is the
    model's :class:`flylib.pose2d.plan.ModelSpec`; ``key`` the config key that sets its weights."""
    if spec.weights:
        path = Path(spec.weights).expanduser()
        if path.is_file():
            why = container_problem(path)
            if why is None:
                return None
            return (
                f"{key}: {spec.weights} is not a PyTorch checkpoint ({why}); point it at the "
                "model's checkpoint (a torch.save file holding {'state_dict': ...}, such as "
                "DeepFly2D's sh8 .tar)"
            )
        return (
            f"{key}: {spec.weights} does not exist; point it at the checkpoint file "
            "(or leave it empty for the published weights)"
        )
    cached = cached_checkpoint(spec.name, spec.model_class, spec.url)
    if cached.is_file():
        why = container_problem(cached)
        if why is None:
            return None
        return (
            f"{key}: the cached checkpoint {cached} of model {spec.name!r} is not a PyTorch "
            f"checkpoint ({why}; a download cut short?); delete it to download it again, or "
            f"set pose2d.weights: {{{spec.name}: /path/to/checkpoint.tar}}"
        )
    url = download_url(spec.model_class, spec.url)
    if not url:
        return (
            f"{key}: model {spec.name!r} has no weights and class {spec.model_class!r} no "
            f"published checkpoint; set pose2d.weights: {{{spec.name}: /path/to/checkpoint.tar}}"
        )
    reachable, why = host_reachable(url, timeout)
    if reachable:
        return None
    return (
        f"{key}: model {spec.name!r} needs its checkpoint, which is not in the cache ({cached}) "
        f"and cannot be downloaded now ({why}); download {url} on a machine with network "
        f"and put it at {cached}, or set pose2d.weights: {{{spec.name}: /path/to/the/file}}"
    )
