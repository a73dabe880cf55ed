"""The workflow's stages: each stage's home, ``flylib.pipeline.<stage>``, declares its
:class:`Stage` record as ``RECORD``; :func:`registry` finds them, in run order.

Every fact the package keeps about a stage as a whole is a field of its record. The tables
the config, results and workflow layers read (``flylib.config.STAGES``, ``STAGE_DEFAULTS``,
``PARAM_STAGES``, ``PARAM_TABLES``, ``flylib.results.ARTIFACTS``, ``STAGE_GROUPS``,
:data:`SOLVES_3D`, :data:`FINAL_3D`) are derived from them on first use (:func:`derived`):
the homes import those layers, so the tables cannot be computed while they load.

:func:`registry` imports each module of ``flylib.pipeline`` that declares ``RECORD =
Stage(`` (the planner, a job reading ``results.h5``); a job looks up its own stage alone
(:func:`by_name` imports one home).
"""

from __future__ import annotations

import functools
import pkgutil
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from importlib import import_module
from pathlib import Path
from typing import Any, TypeVar

__all__ = [
    "FINAL_3D",
    "REGISTRY",
    "SOLVES_3D",
    "Stage",
    "by_name",
    "derived",
    "register",
    "registry",
    "run_function",
]

_HOMES = "flylib.pipeline"


@dataclass(frozen=True)
class Stage:
    """One workflow stage.

    Attributes
    ----------
    name
        Its rule, its config table, ``pipeline.do_<name>``, its home ``flylib.pipeline.<name>``.
    default_on
        Whether it runs when ``pipeline.do_<name>`` is absent; ``None``: no key toggles it.
    after
        The stages it runs after (its place in the run order).
    needs_one_of
        Upstream stages it starts from: it runs only while one of them runs (empty: no such
        condition).
    params
        The params class of its config table (defaults, checks, the reference), or ``None``.
    artifact
        Its artifact's file name inside ``<outdir>/stages/``, or ``None``.
    outputs
        The files it writes in ``<outdir>`` that a run asks for while it is on.
    results_group
        Whether it owns a group in ``results.h5`` (assembly copies it from the artifact).
    solves_3d
        Whether it solves a 3D pose (its group holds ``points3d`` and the 2D ``points``).
    hint
        What to check when its numerical step fails on a recording's data (the end of the
        one-line error), or ``None``.
    memory
        ``(fixed MB, MB per million (frame, point, view) elements)``: its job's measured peak
        (``benchmarks/stage_memory.py``), or ``None`` (its rule states a fixed ``mem_mb``).
    """

    name: str
    default_on: bool | None
    after: tuple[str, ...] = ()
    needs_one_of: tuple[str, ...] = ()
    params: type | None = None
    artifact: str | None = None
    outputs: tuple[str, ...] = ()
    results_group: bool = False
    solves_3d: bool = False
    hint: str | None = None
    memory: tuple[int, int] | None = None

    @property
    def toggled(self) -> bool:
        """Whether ``pipeline.do_<name>`` turns the stage on and off."""
        return self.default_on is not None

    @property
    def home(self) -> str:
        """The module that declares the record, the inputs class and the run function."""
        return f"{_HOMES}.{self.name}"

    def inputs_class(self) -> type:
        """The stage's :class:`~flylib.pipeline.inputs.StageInputs` class (imports its home)."""
        if self.name not in _INPUTS:
            import_module(self.home)
        return _INPUTS[self.name]

    def run_function(self) -> Any:
        """``run_<name>`` of the stage's home (importing it on first use)."""
        return getattr(import_module(self.home), f"run_{self.name}")


#: ``stage -> its inputs class``, filled by :func:`register` as the stage homes import.
_INPUTS: dict[str, type] = {}
_finding = False


@functools.cache
def registry() -> tuple[Stage, ...]:
    """Every stage's record, in run order: each after the stages it names in ``after``,
    else in name order. ValueError for a cycle or an unknown stage in ``after``."""
    global _finding
    if _finding:
        raise RuntimeError(
            "the stage records were read while a stage home was being imported; "
            "read them (and the tables derived from them) at call time, not at import"
        )
    _finding = True
    try:
        package = import_module(_HOMES)
        found = {}
        for module in sorted(m.name for m in pkgutil.iter_modules(package.__path__)):
            if not _declares_record(Path(package.__path__[0], f"{module}.py")):
                continue  # the planner, the helpers: not imported by a job that reads tables
            record = getattr(import_module(f"{_HOMES}.{module}"), "RECORD", None)
            if isinstance(record, Stage):
                found[record.name] = record
    finally:
        _finding = False
    order: list[Stage] = []
    while len(order) < len(found):
        placed = {stage.name for stage in order}
        ready = [s for s in found.values() if s.name not in placed and placed.issuperset(s.after)]
        if not ready:
            rest = sorted(set(found) - placed)
            raise ValueError(
                f"stages {', '.join(rest)}: their 'after' names a stage that is not a stage "
                f"home in {_HOMES} or forms a cycle (known: {', '.join(sorted(found))})"
            )
        order.append(ready[0])
    return tuple(order)


def _declares_record(path: Path) -> bool:
    """Whether the module at ``path`` declares a stage record (``RECORD = Stage(`` at the start
    of a line)."""
    try:
        return "\nRECORD = Stage(" in path.read_text(encoding="utf-8")
    except OSError:
        return False


def by_name(name: str) -> Stage:
    """The record of stage ``name``: its home's ``RECORD`` (ValueError for an unknown stage)."""
    try:
        record = getattr(import_module(f"{_HOMES}.{name}"), "RECORD", None)
    except ModuleNotFoundError as exc:
        if exc.name != f"{_HOMES}.{name}":
            raise
        record = None
    if isinstance(record, Stage) and record.name == name:
        return record
    known = ", ".join(s.name for s in registry())
    raise ValueError(f"unknown stage {name!r} (known: {known})")


def run_function(name: str) -> Any:
    """``run_<name>`` of stage ``name``'s home (:meth:`Stage.run_function`)."""
    return by_name(name).run_function()


T = TypeVar("T", bound=type)


def register(cls: T) -> T:
    """Class decorator: make ``cls`` the inputs class of stage ``cls.STAGE`` (ValueError for
    an unknown stage)."""
    by_name(cls.STAGE)  # type: ignore[attr-defined]
    _INPUTS[cls.STAGE] = cls  # type: ignore[attr-defined]
    return cls


class _Derived:
    """A table made from the records on first use (``kind``: tuple or dict)."""

    kind: type = tuple

    def __init__(self, make: Callable[[], Any]) -> None:
        self._make = make

    @functools.cached_property
    def _value(self) -> Any:
        return self.kind(self._make())

    def __getitem__(self, key):
        return self._value[key]

    def __iter__(self) -> Iterator:
        return iter(self._value)

    def __len__(self) -> int:
        return len(self._value)

    def __repr__(self) -> str:
        return repr(self._value)


class _DerivedNames(_Derived, Sequence):
    def __eq__(self, other: object) -> bool:
        return self._value == (tuple(other) if isinstance(other, _DerivedNames) else other)

    __hash__ = None  # type: ignore[assignment]


class _DerivedMap(_Derived, Mapping):
    kind = dict


def derived(make: Callable[[], Any], *, mapping: bool = False) -> Any:
    """A read-only table derived from the records: ``make()``'s tuple (a dict with
    ``mapping``), made once it is first read, so a module below the stage homes can define
    it at import."""
    return _DerivedMap(make) if mapping else _DerivedNames(make)


#: Every stage's record, in run order (:func:`registry`).
REGISTRY: Sequence[Stage] = _DerivedNames(registry)
#: The stages that solve a 3D pose (:attr:`Stage.solves_3d`), in run order.
SOLVES_3D: Sequence[str] = _DerivedNames(lambda: [s.name for s in registry() if s.solves_3d])
#: Where a result's final 3D comes from: the first of these that ran (last in run order first).
FINAL_3D: Sequence[str] = _DerivedNames(lambda: SOLVES_3D[::-1])
