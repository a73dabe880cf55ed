"""2D keypoint detection: the DeepFly2D stacked hourglass and the detection plan.

Torch loads only when a torch-backed name is used, so the plan
(:class:`DetectionPlan`, :meth:`DetectionPlan.view_sources`) is cheap to read.
"""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

from .plan import DetectionPlan, ModelSpec, Pathway, parse_op

log = logging.getLogger(__name__)

_LAZY = {
    "HourglassNet": "model",
    "LoadedModel": "inference",
    "load_models": "inference",
    "select_device": "inference",
    "detect_2d": "stream",
    "detect_recording": "stream",
    "run_detection": "stream",
    "save_checkpoint": "weights",
    "load_hourglass": "weights",
    "resolve_weights": "weights",
    "cache_dir": "weights",
}

__all__ = ["DetectionPlan", "ModelSpec", "Pathway", "parse_op", "load_detector", *_LAZY]


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'flylib.pose2d' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def load_detector(
    checkpoint: str | Path | None = None, *, device=None, num_classes: int | None = None
):
    """Load the hourglass detector from a checkpoint (strictly; shape read from the file).

    Parameters
    ----------
    checkpoint
        A DeepFly2D checkpoint (``{"state_dict": ...}``, ``module.``/``model.``
        prefixes allowed), or ``None`` for a freshly initialised, **untrained**
        8-stack network (logged as a warning; for training or tests only).
    device
        Where to put it (default CPU).
    num_classes
        Expected output channels, checked against the checkpoint.

    Returns
    -------
    HourglassNet
        The network in eval mode.

    Raises
    ------
    WeightsError
        If the file is unreadable or does not fit the network.
    """
    from .model import HourglassNet
    from .weights import load_hourglass

    if checkpoint is None:
        log.warning("load_detector(None): returning an UNTRAINED hourglass network")
        return HourglassNet(num_classes=num_classes or 19).to(device or "cpu").eval()
    return load_hourglass(checkpoint, num_classes=num_classes, device=device or "cpu")
