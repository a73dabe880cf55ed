"""The tracked skeleton: ordered point names, limb chains and the plotting palette.

A limb is an ordered chain of points (e.g. the five joints of a leg, body to claw); its bones
are the consecutive pairs along the chain. Every point belongs to at most one limb, so each
limb is a simple path and ``limb_id`` is well defined. Which view sees which point lives in
the detection plan; an unobserved ``(view, point)`` is NaN in the points arrays.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import yaml

from .errors import ConfigError, unknown_key
from .paths import DEFAULT_CONFIG_PATH

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Int

_HEX_COLOR = re.compile(r"^#[0-9a-fA-F]{6}$")
_SKELETON_KEYS = ("name", "point_names", "limb_points", "limb_palette")


@lru_cache(maxsize=1)
def default_skeleton_table() -> dict:
    """The packaged default config's ``skeleton`` table (read once; treat as read-only), read
    here because :class:`~flylib.config.Config` validates against it and so sits above."""
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    with open(DEFAULT_CONFIG_PATH, encoding="utf-8") as stream:
        return yaml.load(stream, Loader=loader)["skeleton"]


def skeleton_problems(spec: Any, path: str = "skeleton") -> list[str]:
    """Every problem with the ``skeleton`` table at key ``path``, one
    ``"<key path>: <problem>"`` line each."""
    if not isinstance(spec, Mapping):
        return [f"{path}: expected a mapping, got {type(spec).__name__}"]
    problems = [
        f"{path}.{key}: {unknown_key('key', key, _SKELETON_KEYS)}"
        for key in spec
        if key not in _SKELETON_KEYS
    ]
    if "name" in spec and not isinstance(spec["name"], str):
        problems.append(f"{path}.name: expected a string, got {spec['name']!r}")
    names = spec.get("point_names")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        problems.append(f"{path}.point_names: expected a non-empty list of point-name strings")
        return problems
    seen: set[str] = set()
    for name in names:
        if name in seen:
            problems.append(f"{path}.point_names: point {name!r} is listed twice")
        seen.add(name)

    limbs = spec.get("limb_points", {}) or {}
    if not isinstance(limbs, Mapping):
        problems.append(f"{path}.limb_points: expected a mapping limb -> list of points")
        limbs = {}
    owner: dict[str, str] = {}
    for limb, points in limbs.items():
        where = f"{path}.limb_points.{limb}"
        if not isinstance(points, list) or not points:
            problems.append(f"{where}: expected a non-empty list of point names")
            continue
        for point in points:
            if not isinstance(point, str) or point not in seen:
                problems.append(f"{where}: unknown point {point!r} (known: {', '.join(names)})")
            elif point in owner:
                problems.append(
                    f"{where}: point {point!r} already belongs to limb {owner[point]!r}"
                    " (a point can be in one limb only)"
                )
            else:
                owner[point] = str(limb)

    palette = spec.get("limb_palette", {}) or {}
    if not isinstance(palette, Mapping):
        problems.append(f"{path}.limb_palette: expected a mapping limb -> '#rrggbb'")
        palette = {}
    for limb, color in palette.items():
        where = f"{path}.limb_palette.{limb}"
        if limb not in limbs:
            problems.append(f"{where}: unknown limb {limb!r} (known: {', '.join(map(str, limbs))})")
        if not isinstance(color, str) or not _HEX_COLOR.match(color):
            problems.append(f"{where}: expected a hex colour like '#1a8daf', got {color!r}")
    return problems


class HasSkeletonTable(Protocol):
    """What :meth:`Skeleton.from_config` reads of a config: its ``skeleton`` table."""

    def skeleton_table(self) -> Mapping: ...


@dataclass(frozen=True, eq=False)
class Skeleton:
    """An ordered set of tracked points (``point_names``) with limb chains (``limbs``:
    ``limb -> ordered point names``, config order), a plotting ``palette`` (``limb ->
    '#rrggbb'``; other limbs use a default colormap) and a ``name`` (e.g. ``"fly38"``)."""

    point_names: tuple[str, ...]
    limbs: dict[str, tuple[str, ...]] = field(default_factory=dict)
    palette: dict[str, str] = field(default_factory=dict)
    name: str = "skeleton"

    def __post_init__(self) -> None:
        object.__setattr__(self, "point_names", tuple(str(p) for p in self.point_names))
        object.__setattr__(
            self, "limbs", {str(k): tuple(str(p) for p in v) for k, v in self.limbs.items()}
        )
        object.__setattr__(self, "palette", {str(k): str(v) for k, v in self.palette.items()})
        problems = skeleton_problems(
            {
                "name": self.name,
                "point_names": list(self.point_names),
                "limb_points": {k: list(v) for k, v in self.limbs.items()},
                "limb_palette": self.palette,
            }
        )
        if problems:
            raise ConfigError("; ".join(problems))

    @classmethod
    def fly(cls) -> Skeleton:
        """The default 38-point Drosophila skeleton, read from the packaged default config."""
        return cls.from_spec(default_skeleton_table())

    @classmethod
    def from_config(cls, config: HasSkeletonTable) -> Skeleton:
        """The skeleton of a :class:`~flylib.config.Config`'s ``skeleton`` table (ConfigError
        when it has none or it is invalid)."""
        return cls.from_spec(config.skeleton_table())

    @classmethod
    def from_spec(cls, spec: Mapping) -> Skeleton:
        """The skeleton of a parsed ``skeleton`` table (``point_names`` and optional ``name``,
        ``limb_points``, ``limb_palette``); ConfigError lists every problem with it."""
        problems = skeleton_problems(spec)
        if problems:
            raise ConfigError("; ".join(problems))
        return cls(
            point_names=tuple(spec["point_names"]),
            limbs={k: tuple(v) for k, v in (spec.get("limb_points") or {}).items()},
            palette=dict(spec.get("limb_palette") or {}),
            name=spec.get("name", "skeleton"),
        )

    @classmethod
    def from_arrays(
        cls,
        point_names: Sequence[str],
        limb_names: Sequence[str],
        limb_id: Int[np.ndarray, " P"],
        bones: Int[np.ndarray, "B 2"],
        palette: Mapping[str, str] | None = None,
        name: str = "skeleton",
    ) -> Skeleton:
        """Rebuild a skeleton from its stored arrays (the ``skeleton/`` HDF5 group): ``limb_id``
        ``(P,)`` (``-1``: in no limb) and ``bones`` ``(B, 2)`` point-index pairs.

        Each limb's chain order is recovered by walking its bones from the end that no bone
        points into; a limb without bones keeps its points in index order.
        """
        limb_id = np.asarray(limb_id, dtype=int).reshape(-1)
        bones = np.asarray(bones, dtype=int).reshape(-1, 2)
        next_point = {int(a): int(b) for a, b in bones}
        has_parent = {int(b) for _, b in bones}
        limbs: dict[str, tuple[str, ...]] = {}
        for index, limb in enumerate(limb_names):
            members = [int(i) for i in np.flatnonzero(limb_id == index)]
            starts = [i for i in members if i not in has_parent]
            chain = [starts[0]] if len(starts) == 1 else []
            while chain and chain[-1] in next_point and len(chain) < len(members):
                chain.append(next_point[chain[-1]])
            order = chain if sorted(chain) == members else members
            limbs[str(limb)] = tuple(point_names[i] for i in order)
        return cls(
            point_names=tuple(point_names), limbs=limbs, palette=dict(palette or {}), name=name
        )

    @property
    def n_points(self) -> int:
        """Number of tracked points ``P``."""
        return len(self.point_names)

    @property
    def n_limbs(self) -> int:
        """Number of limbs."""
        return len(self.limbs)

    def __len__(self) -> int:
        return self.n_points

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Skeleton):
            return NotImplemented
        return (
            self.point_names == other.point_names
            and list(self.limbs.items()) == list(other.limbs.items())
            and self.palette == other.palette
            and self.name == other.name
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-dict fields: not hashable

    @property
    def limb_names(self) -> tuple[str, ...]:
        """Limb names in config order."""
        return tuple(self.limbs)

    def index(self, name: str) -> int:
        """Index of point ``name`` (KeyError listing the known points if there is none)."""
        try:
            return self._index_of[name]
        except KeyError:
            raise KeyError(
                f"unknown point {name!r} (known: {', '.join(self.point_names)})"
            ) from None

    @cached_property
    def _index_of(self) -> dict[str, int]:
        return {n: i for i, n in enumerate(self.point_names)}

    @cached_property
    def limb_id(self) -> Int[np.ndarray, " P"]:
        """``(P,)`` int array: the limb index of each point, ``-1`` if in no limb."""
        out = np.full(self.n_points, -1, dtype=np.int64)
        for li, chain in enumerate(self.limbs.values()):
            out[[self._index_of[p] for p in chain]] = li
        out.flags.writeable = False
        return out

    @cached_property
    def bones(self) -> Int[np.ndarray, "B 2"]:
        """``(B, 2)`` int array of point-index pairs: consecutive points of each limb chain."""
        pairs = [
            (self._index_of[a], self._index_of[b])
            for chain in self.limbs.values()
            for a, b in zip(chain[:-1], chain[1:])
        ]
        out = np.array(pairs, dtype=np.int64).reshape(-1, 2)
        out.flags.writeable = False
        return out

    @property
    def n_bones(self) -> int:
        """Number of bones ``B``."""
        return int(self.bones.shape[0])

    def bone_index_pairs(self) -> tuple[Int[np.ndarray, " B"], Int[np.ndarray, " B"]]:
        """Endpoint index arrays ``(i, j)``, ``(B,)`` each, for vectorised bone-length maths."""
        return self.bones[:, 0], self.bones[:, 1]

    def limb_color(self, limb: str, default: str = "#808080") -> str:
        """The palette colour of ``limb``, or ``default`` when it has none."""
        return self.palette.get(limb, default)


def _twin_name(name: str) -> str | None:
    """``lf_leg`` <-> ``rf_leg``, ``l_antenna`` <-> ``r_antenna``; ``None`` if unsided."""
    if name[:1] == "l":
        return "r" + name[1:]
    if name[:1] == "r":
        return "l" + name[1:]
    return None


def mirror_bones(skeleton: Skeleton) -> Int[np.ndarray, " B"]:
    """``(B,)`` the left/right twin of every bone (itself when it has none): bone ``k`` of
    limb ``l...`` and bone ``k`` of limb ``r...`` with equally long chains."""
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
