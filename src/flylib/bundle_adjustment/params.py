"""The ``fixed`` / ``shared`` parameter grammar and the free-variable layout.

A camera's parameters form one row ``[rvec(3), tvec(3), intr(4), dist(K)]`` of a ``(V, C)``
table. A reference ``<camera>.<param>`` or ``<camera>.<param>[<index>]`` names some of its
entries: ``<camera>`` is a camera name or ``*`` (every camera), ``<param>`` is ``rvec``,
``tvec``, ``intr`` (``fx, fy, cx, cy``) or ``dist`` (OpenCV order).

``fixed`` references stay at their initial values. Each ``shared`` group is a list of
references that all expand to the same number of entries per camera; the i-th entry of every
expansion is tied to one free variable (so ``["*.intr"]`` gives the whole rig one set of
intrinsics and ``["rm.tvec[2]", "lm.tvec[2]"]`` one shared depth). A tied slot that contains a
fixed entry is fixed as a whole."""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int

log = logging.getLogger(__name__)

PARAM_OFFSETS = {"rvec": (0, 3), "tvec": (3, 6), "intr": (6, 10)}
_REF = re.compile(r"^\s*(?P<cam>\*|[^.\[\]\s]+)\.(?P<param>[A-Za-z_]+)(?:\[(?P<idx>-?\d+)\])?\s*$")


def param_slices(n_dist: int) -> dict[str, tuple[int, int]]:
    """Column range of each parameter in the ``(V, 10 + n_dist)`` camera table."""
    return {**PARAM_OFFSETS, "dist": (10, 10 + n_dist)}


def expand_reference(
    ref: str, camera_names: Sequence[str], n_dist: int, key: str = "bundle_adjustment"
) -> list[list[tuple[int, int]]]:
    """Expand one reference to ``[(view, column), ...]`` entries, one list per camera;
    ConfigError, naming it, for a malformed one or an unknown camera, parameter or index."""
    match = _REF.match(str(ref))
    if match is None:
        raise ConfigError(
            f"{key}: cannot parse parameter reference {ref!r}; write <camera>.<param> or "
            f"<camera>.<param>[<index>], e.g. '*.intr', 'f.rvec', 'rm.tvec[2]'"
        )
    cam, param, idx = match["cam"], match["param"], match["idx"]
    slices = param_slices(n_dist)
    if param not in slices:
        raise ConfigError(
            f"{key}: unknown parameter {param!r} in reference {ref!r}; "
            f"use one of rvec, tvec, intr, dist"
        )
    if cam == "*":
        views = list(range(len(camera_names)))
    elif cam in camera_names:
        views = [list(camera_names).index(cam)]
    else:
        raise ConfigError(
            f"{key}: unknown camera {cam!r} in reference {ref!r}; "
            f"the rig's cameras are {', '.join(camera_names)}"
        )
    lo, hi = slices[param]
    columns = list(range(lo, hi))
    if idx is not None:
        i = int(idx)
        if not 0 <= i < hi - lo:
            raise ConfigError(
                f"{key}: index {i} out of range in reference {ref!r}; {param} has "
                f"{hi - lo} entries here (valid 0..{hi - lo - 1})"
            )
        columns = [lo + i]
    return [[(v, c) for c in columns] for v in views]


@dataclass(frozen=True)
class ParamLayout:
    """How the ``(V, C)`` camera table maps onto the solver's ``n_free`` free variables:
    ``var_index`` ``(V, C)`` is the free variable an entry reads, or ``-1`` when fixed."""

    var_index: Int[np.ndarray, "V C"]
    n_free: int

    def pack(self, table: Float[np.ndarray, "V C"]) -> Float[np.ndarray, " F"]:
        """Free-variable vector from a camera table (tied entries are averaged)."""
        free = self.var_index >= 0
        sums = np.bincount(self.var_index[free], weights=table[free], minlength=self.n_free)
        counts = np.bincount(self.var_index[free], minlength=self.n_free)
        return sums / np.maximum(counts, 1)

    def unpack(
        self, x: Float[np.ndarray, " F"], base: Float[np.ndarray, "V C"]
    ) -> Float[np.ndarray, "V C"]:
        """Camera table: ``base`` with every free entry replaced from ``x``."""
        free = self.var_index >= 0
        table = np.array(base, dtype=float, copy=True)
        table[free] = x[self.var_index[free]]
        return table

    @property
    def extrinsics_free(self) -> bool:
        """True when no rotation or translation entry is fixed (the gauge is open)."""
        return bool((self.var_index[:, :6] >= 0).all())


def build_layout(
    camera_names: Sequence[str],
    n_dist: int,
    fixed: Sequence[str] = (),
    shared: Sequence[Sequence[str]] = (),
) -> ParamLayout:
    """Resolve ``fixed`` / ``shared`` references into a :class:`ParamLayout`; ConfigError for a
    bad reference or a shared group whose references expand to different numbers of entries."""
    if isinstance(fixed, str) or isinstance(shared, str):
        raise ConfigError(
            "bundle_adjustment.fixed must be a list of references and "
            "bundle_adjustment.shared a list of lists of references"
        )
    n_views, n_cols = len(camera_names), 10 + n_dist
    is_fixed = np.zeros((n_views, n_cols), bool)
    for ref in fixed:
        for entries in expand_reference(ref, camera_names, n_dist, "bundle_adjustment.fixed"):
            for v, c in entries:
                is_fixed[v, c] = True

    # Union-find over entries so overlapping groups merge into one tie.
    parent = np.arange(n_views * n_cols)

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for group in shared:
        if isinstance(group, str):
            raise ConfigError(
                f"bundle_adjustment.shared: each group must be a list of references, "
                f"got the string {group!r}; write [[{group!r}, ...]]"
            )
        expansions = [
            e
            for ref in group
            for e in expand_reference(ref, camera_names, n_dist, "bundle_adjustment.shared")
        ]
        lengths = {len(e) for e in expansions}
        if len(lengths) > 1:
            raise ConfigError(
                f"bundle_adjustment.shared: the references {list(group)} expand to different "
                f"numbers of entries per camera ({sorted(lengths)}); tie like with like"
            )
        for slot in zip(*expansions):
            roots = [find(v * n_cols + c) for v, c in slot]
            for r in roots[1:]:
                parent[r] = roots[0]

    roots = np.array([find(a) for a in range(n_views * n_cols)])
    fixed_roots = set(roots[is_fixed.ravel()].tolist())
    var_index = np.full(n_views * n_cols, -1)
    numbering: dict[int, int] = {}
    for a, r in enumerate(roots):
        if int(r) in fixed_roots:
            continue
        var_index[a] = numbering.setdefault(int(r), len(numbering))
    var_index = var_index.reshape(n_views, n_cols)
    widened = (var_index < 0) & ~is_fixed
    if widened.any():
        log.info(
            "bundle adjustment: %d entries tied to a fixed entry are held fixed too",
            int(widened.sum()),
        )
    return ParamLayout(var_index=var_index, n_free=len(numbering))
