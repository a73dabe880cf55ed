"""Value checks: a check takes a value and returns what is wrong with it ("expected ..."), or None."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
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
    """A list of numbers, each as :func:`_number` checks it."""
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


def param(
    default: Any, check: Check, *, kind: type | None = None, track_default: bool = True
) -> Any:
    """A typed-parameter field: its default, its value check, and a conversion.

    ``track_default=False`` is for a field added after results were made without it:
    the field enters a stage's tracked params (:func:`tracked_table`,
    :meth:`~flylib.config.params.TriangulationParams.method_params`) only when it differs
    from its default, so adding it leaves every existing params hash, and the results
    made under them, as they were. Every field that existed before this marker keeps
    ``True`` (always tracked), so its hashes stay equal too.
    """
    return field(
        default=default,
        metadata={"check": check, "kind": kind, "track_default": track_default},
    )


def is_tracked(params: Any, name: str) -> bool:
    """Whether field ``name`` of the typed params ``params`` enters its tracked params:
    always, unless marked ``track_default=False`` (:func:`param`) and at its default."""
    spec = params.__dataclass_fields__[name]
    return spec.metadata.get("track_default", True) or getattr(params, name) != spec.default


def tracked_table(params: Any) -> dict[str, Any]:
    """A typed params object as its stage's params track it: :func:`dataclasses.asdict`
    without the ``track_default=False`` fields that hold their default."""
    return {k: v for k, v in asdict(params).items() if is_tracked(params, k)}
