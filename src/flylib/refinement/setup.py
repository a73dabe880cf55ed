"""From a skeleton to :func:`refine_points`'s skeleton arguments (bones, chains, mirror, rigid)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Int


def default_rigid_points(skeleton) -> list[str]:
    """The points fixed to a tethered fly's thorax: every ``*thorax_coxa`` point."""
    return [p for p in skeleton.point_names if p.endswith("thorax_coxa")]


def _twin_name(name: str) -> str | None:
    """``lf_leg`` <-> ``rf_leg``, ``l_antenna`` <-> ``r_antenna``; ``None`` if unsided."""
    if name[:1] == "l":
        return "r" + name[1:]
    if name[:1] == "r":
        return "l" + name[1:]
    return None


def mirror_bones(skeleton) -> Int[np.ndarray, " B"]:
    """``(B,)`` the left/right twin of every bone (itself when it has none): bone ``k``
    of limb ``l...`` and bone ``k`` of limb ``r...`` with equally long chains."""
    limbs = list(skeleton.limbs.items())
    index = {}
    b = 0
    for name, chain in limbs:
        for k in range(len(chain) - 1):
            index[(name, k)] = b
            b += 1
    out = np.arange(b)
    for (name, k), bone in index.items():
        twin = _twin_name(name)
        if (
            twin is not None
            and (twin, k) in index
            and len(skeleton.limbs[twin]) == len(skeleton.limbs[name])
        ):
            out[bone] = index[(twin, k)]
    return out


def skeleton_terms(skeleton, rigid_names: list[str] | None) -> dict[str, Any]:
    """``bones``, ``chains``, ``mirror`` and ``rigid`` (indices) for :func:`refine_points`.

    Parameters
    ----------
    skeleton
        The :class:`~flylib.skeleton.Skeleton`.
    rigid_names
        Point names of the rigid group; ``None`` = :func:`default_rigid_points`.

    Raises
    ------
    ConfigError
        If a rigid point is not a skeleton point.
    """
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
