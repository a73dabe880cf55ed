"""YAML / TOML / JSON parsing: exponent floats, duplicate keys, bounded nesting, the problem report.

Nesting is bounded before and after parsing (:data:`MAX_NESTING`): YAML by walking libyaml's event
stream (no Python recursion, stops at the first level too deep), TOML by counting each line's
dotted-key segments (tomllib takes quadratic time on a key 100,000 segments long) and catching the
recursion of its inline arrays and tables, JSON by catching the recursion of its decoder; every
parsed value is then measured without recursion (YAML aliases can make a structure that contains
itself), so what later walks a config recursively (validation, canonical forms) never meets a depth
it cannot handle.
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError


class _YamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    """SafeLoader that also reads ``1e-8`` as a float (YAML 1.1 would read it as text)."""


_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


#: Deepest nesting of mappings and lists a config (or JSON argument) may have; flylib's own nests 4.
MAX_NESTING = 64

_TOML_QUOTED = re.compile(r'"(?:[^"\\]|\\.)*"|\'[^\']*\'')


def _too_deep(source: str, where: str = "") -> ConfigError:
    return ConfigError(
        f"{source}: nested more than {MAX_NESTING} levels deep{where}; a flylib config nests "
        "a few levels (tables of keys and lists), fix the file"
    )


def yaml_nesting_line(text: str) -> int | None:
    """The line where the YAML's nesting first passes :data:`MAX_NESTING`, else ``None``."""
    depth = 0
    for event in yaml.parse(text, Loader=_YamlLoader):
        if isinstance(event, yaml.MappingStartEvent | yaml.SequenceStartEvent):
            depth += 1
            if depth > MAX_NESTING:
                return event.start_mark.line + 1
        elif isinstance(event, yaml.MappingEndEvent | yaml.SequenceEndEvent):
            depth -= 1
    return None


def toml_dotted_line(text: str) -> int | None:
    """The first line whose key or table header has more than :data:`MAX_NESTING` dotted segments
    (counted outside quotes; an over-count is harmless at that size)."""
    for number, line in enumerate(text.splitlines(), 1):
        if line.count(".") <= MAX_NESTING:
            continue
        bare = _TOML_QUOTED.sub('""', line)
        head = (
            bare.split("=", 1)[0] if "=" in bare else bare if bare.lstrip().startswith("[") else ""
        )
        if head.count(".") > MAX_NESTING:
            return number
    return None


#: Most values (scalars and containers) a config may expand to when its YAML aliases are followed:
#: a few shared anchors are fine, a "billion laughs" is not.
MAX_EXPANDED_VALUES = 1_000_000


def _children(node) -> list:
    if isinstance(node, dict):
        return list(node.values())
    return list(node) if isinstance(node, list | tuple) else []


def _one(node) -> int:
    return 1


def shape_problem(
    value,
    *,
    children: Callable[[object], list] = _children,
    weight: Callable[[object], int] = _one,
    max_values: int = MAX_EXPANDED_VALUES,
    max_depth: int = MAX_NESTING,
) -> str | None:
    """Why ``value`` nests deeper than ``max_depth``, contains itself, or expands (walked as a
    tree, a shared member counted wherever it appears) to more than ``max_values`` values; else
    ``None``. Without recursion, each shared member measured once: the cost is the size of the
    object graph, not of its expansion.

    ``children``: a node's members; ``weight``: how many values a node counts for besides them.
    """
    measured: dict[int, tuple[int, int]] = {}  # id -> (depth, expanded values)
    on_path: set[int] = set()
    stack: list[tuple[object, bool]] = [(value, False)]
    too_many = (
        f"expands to more than {max_values} values (shared members counted wherever they appear)"
    )
    while stack:
        node, leaving = stack.pop()
        key = id(node)
        if leaving:
            on_path.discard(key)
            below = [measured[id(child)] for child in children(node)]
            size = weight(node) + sum(n for _, n in below)
            if size > max_values:
                return too_many
            measured[key] = (1 + max(d for d, _ in below), size)
            continue
        members = children(node)
        if key in on_path:
            return "contains itself (a reference cycle)"
        if key not in measured and not members:
            measured[key] = (1 if isinstance(node, dict | list | tuple | set) else 0, weight(node))
            if measured[key][1] > max_values:
                return too_many
        if len(on_path) + measured.get(key, (1, 0))[0] > max_depth:
            return f"is nested more than {max_depth} levels deep"
        if key in measured:
            continue
        on_path.add(key)
        stack.append((node, True))
        stack.extend((child, False) for child in members)
    return None


def parse_json(text: str, source: str) -> object:
    """``json.loads`` with bounded nesting: one :class:`ConfigError` naming ``source`` (what the
    text came from, e.g. a command-line argument)."""
    try:
        value = json.loads(text)
    except RecursionError:
        raise _too_deep(source) from None
    except ValueError as err:
        raise ConfigError(f"{source}: not valid JSON ({err}); fix the syntax") from None
    problem = shape_problem(value)
    if problem:
        raise ConfigError(f"{source}: {problem}; fix the JSON")
    return value


def _duplicate_key_problems(
    node: yaml.Node | None, path: str = "", seen: set[int] | None = None
) -> list[str]:
    """Keys given twice in one YAML mapping (PyYAML would silently keep the last); each node is
    visited once (an alias repeats a node, and may point at its own ancestor)."""
    problems: list[str] = []
    seen = set() if seen is None else seen
    if id(node) in seen:
        return problems
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        first_line: dict[Any, int] = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                problems += _duplicate_key_problems(value_node, f"{path}.<complex key>", seen)
                continue
            key = key_node.value
            where = f"{path}.{key}" if path else str(key)
            line = key_node.start_mark.line + 1
            if key in first_line:
                what = (
                    f"(view {path.rsplit('.', 1)[-1]!r}, point {key!r}) is filled twice"
                    if path.startswith("pose2d.output_points.")
                    else "key given twice"
                )
                problems.append(f"{where}: {what} (lines {first_line[key]} and {line})")
            else:
                first_line[key] = line
            problems += _duplicate_key_problems(value_node, where, seen)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            problems += _duplicate_key_problems(item, f"{path}[{i}]", seen)
    return problems


def read_config_text(path: Path, label: str) -> str:
    """A config file's text; missing, a directory or not UTF-8 is a ConfigError naming ``label``."""
    try:
        return path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{label}: config file not found; check the path") from None
    except IsADirectoryError:
        raise ConfigError(f"{label}: is a directory, not a config file") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"{label}: not UTF-8 text ({err}); save it as UTF-8") from None


def parse_text(text: str, fmt: str, source: str) -> dict:
    if fmt == "toml":
        line = toml_dotted_line(text)
        if line is not None:
            raise _too_deep(source, f" (a dotted key on line {line})")
        try:
            data = tomllib.loads(text)
        except RecursionError:
            raise _too_deep(source, " (inline arrays or tables)") from None
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"{source}: not valid TOML ({err}); fix the syntax") from None
    else:
        try:
            line = yaml_nesting_line(text)
            if line is not None:
                raise _too_deep(source, f" (line {line})")
            duplicates = _duplicate_key_problems(yaml.compose(text, Loader=_YamlLoader))
            data = yaml.load(text, Loader=_YamlLoader)
        except yaml.YAMLError as err:
            detail = " ".join(str(err).replace(' in "<unicode string>",', " at").split())
            raise ConfigError(f"{source}: not valid YAML ({detail}); fix the syntax") from None
        if duplicates:
            raise problem_error(source, duplicates)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: the top level must be a mapping of tables, got {type(data).__name__}"
        )
    problem = shape_problem(data)
    if problem:
        raise ConfigError(f"{source}: the config {problem}; fix the file")
    return data


def problem_error(source: str, problems: list[str]) -> ConfigError:
    """One :class:`ConfigError` listing ``problems`` (also kept on it as ``.problems``)."""
    count = f"{len(problems)} problem{'s' if len(problems) != 1 else ''}"
    error = ConfigError(
        f"invalid config {source} ({count}; fix and re-run):\n"
        + "\n".join(f"  {p}" for p in problems)
    )
    error.problems = problems  # type: ignore[attr-defined]
    return error
