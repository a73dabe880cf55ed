"""Canonical forms: a stage's tracked params (JSON, :mod:`flylib.pipeline.inputs`) and the
snapshot of a dict config (YAML)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def canonical(value: Any) -> Any:
    """JSON-ready copy with mapping keys sorted (order-bearing content is passed as lists)."""
    if isinstance(value, Mapping):
        return {str(k): canonical(value[k]) for k in sorted(value, key=str)}
    if isinstance(value, (list, tuple)):
        return [canonical(v) for v in value]
    if hasattr(value, "item") and callable(value.item):  # numpy scalar
        return value.item()
    return value


def plain(value: Any) -> Any:
    """YAML-dumpable copy: tuples become lists, numpy scalars Python numbers; key order kept."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if hasattr(value, "item") and callable(value.item):
        return value.item()
    return value
