"""YAML / TOML parsing: exponent floats, duplicate keys, the problem report."""

from __future__ import annotations

import re
import tomllib
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


def _duplicate_key_problems(node: yaml.Node | None, path: str = "") -> list[str]:
    """Keys given twice in one YAML mapping (PyYAML would silently keep the last)."""
    problems: list[str] = []
    if isinstance(node, yaml.MappingNode):
        first_line: dict[Any, int] = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                problems += _duplicate_key_problems(value_node, f"{path}.<complex key>")
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
            problems += _duplicate_key_problems(value_node, where)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            problems += _duplicate_key_problems(item, f"{path}[{i}]")
    return problems


def _parse_text(text: str, fmt: str, source: str) -> dict:
    if fmt == "toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"{source}: not valid TOML ({err}); fix the syntax") from None
    else:
        try:
            duplicates = _duplicate_key_problems(yaml.compose(text, Loader=_YamlLoader))
            data = yaml.load(text, Loader=_YamlLoader)
        except yaml.YAMLError as err:
            detail = " ".join(str(err).replace(' in "<unicode string>",', " at").split())
            raise ConfigError(f"{source}: not valid YAML ({detail}); fix the syntax") from None
        if duplicates:
            error = ConfigError(_problem_report(source, duplicates))
            error.problems = duplicates  # type: ignore[attr-defined]
            raise error
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: the top level must be a mapping of tables, got {type(data).__name__}"
        )
    return data


def _problem_report(source: str, problems: list[str]) -> str:
    count = f"{len(problems)} problem{'s' if len(problems) != 1 else ''}"
    return f"invalid config {source} ({count}; fix and re-run):\n" + "\n".join(
        f"  {p}" for p in problems
    )
