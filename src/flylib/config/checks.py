"""Value checks: a check takes a value and returns what is wrong with it ("expected ..."), or None."""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, field
from typing import Any

Check = Callable[[Any], "str | None"]


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def got(value: Any) -> str:
    return f"got {value!r} ({type(value).__name__})"


def integer(minimum: int | None = None, nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if value is None and nullable:
            return None
        if is_int(value) and (minimum is None or value >= minimum):
            return None
        bound = "" if minimum is None else f" >= {minimum}"
        return f"expected an integer{bound}{' or null' if nullable else ''}, {got(value)}"

    return check


def number(minimum: float | None = None, exclusive: bool = False, nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if value is None and nullable:
            return None
        if _is_number(value) and (
            minimum is None or (value > minimum if exclusive else value >= minimum)
        ):
            return None
        bound = "" if minimum is None else f" {'>' if exclusive else '>='} {minimum:g}"
        hint = (
            "; write exponents with a dot, e.g. 1.0e-8"
            if isinstance(value, str) and re.fullmatch(r"[-+]?[\d.]+[eE][-+]?\d+", value)
            else ""
        )
        return f"expected a number{bound}{' or null' if nullable else ''}, {got(value)}{hint}"

    return check


def boolean(value: Any) -> str | None:
    return None if isinstance(value, bool) else f"expected true or false, {got(value)}"


def string(value: Any) -> str | None:
    return None if isinstance(value, str) else f"expected a string, {got(value)}"


def choice(*options: Any) -> Check:
    def check(value: Any) -> str | None:
        if any(value == o and type(value) is type(o) for o in options):
            return None
        return f"expected one of {', '.join(map(repr, options))}, got {value!r}"

    return check


def string_list(nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if value is None and nullable:
            return None
        if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            return None
        return f"expected a list of strings{' or null' if nullable else ''}, {got(value)}"

    return check


def number_list(minimum: float, exclusive: bool = False) -> Check:
    """A list of numbers, each as :func:`number` checks it."""
    one = number(minimum, exclusive)

    def check(value: Any) -> str | None:
        if isinstance(value, (list, tuple)) and not any(one(v) for v in value):
            return None
        bound = f" {'>' if exclusive else '>='} {minimum:g}"
        return f"expected a list of numbers{bound}, {got(value)}"

    return check


def string_groups(value: Any) -> str | None:
    if isinstance(value, (list, tuple)) and all(
        isinstance(g, (list, tuple)) and all(isinstance(s, str) for s in g) for g in value
    ):
        return None
    return f"expected a list of lists of strings, {got(value)}"


def mapping(nullable: bool = False) -> Check:
    def check(value: Any) -> str | None:
        if (value is None and nullable) or isinstance(value, Mapping):
            return None
        return f"expected a mapping{' or null' if nullable else ''}, {got(value)}"

    return check


#: The config keys that accept an infinite number (YAML ``.inf``, TOML ``inf``) and what it means
#: there. ``.inf``, ``-.inf`` and ``.nan`` anywhere else (and ``-.inf`` or ``.nan`` here) are
#: refused by :func:`non_finite_problems`, which ``validate_config`` runs over the whole config.
INFINITE_OK: dict[str, str] = {
    "refinement.outlier_px": "no limit: no observation is left out after the first pass",
}


def _numbers(value: Any, path: str) -> Iterator[tuple[str, float]]:
    """Every float in a parsed config with its key path (``a.b[0].c``), without recursion."""
    stack: list[tuple[Any, str]] = [(value, path)]
    seen: set[int] = set()
    while stack:
        node, where = stack.pop()
        if isinstance(node, Mapping | list | tuple):
            if id(node) in seen:  # a YAML alias: its members are reported where first met
                continue
            seen.add(id(node))
            if isinstance(node, Mapping):
                members = [(f"{where}.{k}" if where else str(k), v) for k, v in node.items()]
            else:
                members = [(f"{where}[{i}]", v) for i, v in enumerate(node)]
            stack.extend((v, k) for k, v in reversed(members))
        elif isinstance(node, float):
            yield where, node


def non_finite_problems(data: Any) -> dict[str, str]:
    """``key path -> problem`` for every non-finite number in ``data``, except ``+inf`` at a key
    of :data:`INFINITE_OK`."""
    problems: dict[str, str] = {}
    for where, value in _numbers(data, ""):
        if math.isfinite(value) or (value > 0 and where in INFINITE_OK):
            continue
        if where in INFINITE_OK:
            expected = f"a finite number or .inf ({INFINITE_OK[where]})"
        else:
            expected = "a finite number" + (
                f" (.inf is accepted only by {', '.join(INFINITE_OK)})" if INFINITE_OK else ""
            )
        problems[where] = f"{where}: expected {expected}, got {value!r}"
    return problems


def param(
    default: Any, check: Check, *, kind: type | None = None, track_default: bool = True
) -> Any:
    """A typed-parameter field: its default, its value check, and a conversion.

    ``track_default=False`` is for a field added after results were made without it: the field
    enters a stage's tracked params (:func:`tracked_table`, ``TriangulationParams.method_params``)
    only when it differs from its default, so adding it leaves every existing params hash, and
    the results made under them, as they were.
    """
    return field(
        default=default,
        metadata={"check": check, "kind": kind, "track_default": track_default},
    )


def is_tracked(params: Any, name: str) -> bool:
    """Whether field ``name`` of ``params`` enters its tracked params: always, unless marked
    ``track_default=False`` (:func:`param`) and at its default."""
    spec = params.__dataclass_fields__[name]
    return spec.metadata.get("track_default", True) or getattr(params, name) != spec.default


def tracked_table(params: Any) -> dict[str, Any]:
    """:func:`dataclasses.asdict` of typed params without the ``track_default=False`` fields
    that hold their default: what its stage's params track."""
    return {k: v for k, v in asdict(params).items() if is_tracked(params, k)}
