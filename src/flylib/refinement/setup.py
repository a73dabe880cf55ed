"""From a skeleton to :func:`refine_points`'s skeleton arguments (bones, chains, mirror, rigid)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import ConfigError
from ..skeleton import mirror_bones


def default_rigid_points(skeleton) -> list[str]:
    """The points fixed to a tethered fly's thorax: every ``*thorax_coxa`` point."""
    return [p for p in skeleton.point_names if p.endswith("thorax_coxa")]


def skeleton_terms(skeleton, rigid_names: list[str] | None) -> dict[str, Any]:
    """``bones``, ``chains``, ``mirror`` and ``rigid`` (indices) for :func:`refine_points`;
    ``rigid_names`` ``None``: :func:`default_rigid_points`. ConfigError for an unknown point."""
    names = default_rigid_points(skeleton) if rigid_names is None else list(rigid_names)
    unknown = [n for n in names if n not in skeleton.point_names]
    if unknown:
        raise ConfigError(
            f"refinement.rigid_points: unknown point(s) {unknown} "
            f"(known: {', '.join(skeleton.point_names)})"
        )
    chains = [[skeleton.index(p) for p in chain] for chain in skeleton.limbs.values()]
    return {
        "bones": np.asarray(skeleton.bones, np.int64),
        "chains": chains,
        "mirror": mirror_bones(skeleton),
        "rigid": [skeleton.index(n) for n in names],
    }
