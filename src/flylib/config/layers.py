"""A config assembled from several files, the way Snakemake assembles it, remembering which file
set each key.

Snakemake merges ``configfile:`` and ``--configfile`` files in order (tables merge key by key,
anything else -- lists included -- is replaced whole) and then applies ``--config key=value``
overrides. :class:`ConfigLayers` re-reads the same files with flylib's own parser (so ``1e-8`` is a
number, a key given twice is an error naming both lines, a syntax error names the file and line)
and merges them the same way, plus one rule: ``null`` in place of a table deletes it, and a camera
deleted so (``cameras: {f: null}``) takes its detection plan and video panels with it. Every
problem is reported against the user's own file and key, never the packaged default.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..paths import DEFAULT_CONFIG_PATH
from .loading import parse_text, read_config_text
from .sources import drop_views, pathways_of

#: The label of values given on the command line with ``--config key=value``.
OVERRIDES_LABEL = "--config"
# The table of ``cameras`` every camera inherits its unset keys from.
_CAMERA_DEFAULTS = "defaults"

# "unknown source 'vid_f'" in a problem line, and the table such a name is defined in
_UNKNOWN = re.compile(r"unknown (\w+) ('[^']*')")
_REFERENCED = {
    "source": "sources",
    "preprocessor": "pose2d.preprocessors",
    "model": "pose2d.models",
    "pathway": "pose2d.pathways",
}
_KEY_TOKEN = re.compile(r"\[(\d+)\]|([^.\[\]]+)")
_KEY_HEAD = re.compile(r"([A-Za-z_][\w-]*(?:\.[\w-]+|\[\d+\])*)(?=[:\s(]|$)")


def merge_tables(base: dict, update: Mapping) -> dict:
    """Merge ``update`` into ``base`` in place, as Snakemake's ``update_config`` does: mappings
    merge recursively; ``null`` in place of a table deletes it; every other value (lists
    included) replaces the old one."""
    for key, value in update.items():
        old = base.get(key)
        if value is None and isinstance(old, Mapping):
            del base[key]
        elif isinstance(value, Mapping):
            base[key] = merge_tables(dict(old) if isinstance(old, Mapping) else {}, value)
        else:
            base[key] = value
    return base


def _cameras(data: Mapping) -> Mapping:
    cameras = data.get("cameras")
    return cameras if isinstance(cameras, Mapping) else {}


@functools.cache
def _default_text() -> str:
    return DEFAULT_CONFIG_PATH.read_text(encoding="utf-8")


def key_path(problem: str) -> list[str | int]:
    """The key path a problem line starts with: ``"a.b[0].c: ..."`` -> ``["a", "b", 0, "c"]``."""
    match = _KEY_HEAD.match(problem)
    if not match:
        return []
    return [int(i) if i else name for i, name in _KEY_TOKEN.findall(match.group(1))]


def _step(node: Any, token: str | int) -> tuple[bool, Any]:
    """Descend one key (a mapping key, a list index, or a ``name`` in a list of tables)."""
    if isinstance(node, Mapping):
        if token in node:
            return True, node[token]
        return False, None
    if isinstance(node, list):
        if isinstance(token, int):
            return (True, node[token]) if 0 <= token < len(node) else (True, None)
        named = [e for e in node if isinstance(e, Mapping) and e.get("name") == token]
        return (True, named[0]) if named else (True, None)
    return False, None


def _value(data: Any, path: list[str | int]) -> Any:
    node = data
    for token in path:
        _, node = _step(node, token)
    return node


def _depth(data: Any, path: list[str | int]) -> int:
    """How many leading keys of ``path`` ``data`` sets."""
    depth, node = 0, data
    for token in path:
        found, node = _step(node, token)
        if not found:
            break
        depth += 1
    return depth


#: Top-level keys that make Snakemake render a config file as a YTE template (running the Python
#: expressions inside it while it reads ``--configfile``).
TEMPLATING_KEYS = ("__use_yte__",)


def refuse_templating(data: Any, label: str) -> None:
    """Refuse (a ConfigError naming file and key) a config file that asks for templating: a
    config holds values, not code.

    Snakemake renders a YAML config file whose top level sets ``__use_yte__`` with YTE, evaluating
    the Python in its ``?...`` keys and values, for ``--configfile`` before the workflow (and
    flylib) can look at the file; the workflow and ``flylib check-config`` refuse such a file
    before it is ever handed to Snakemake.
    """
    if not isinstance(data, Mapping):
        return
    for key in TEMPLATING_KEYS:
        if key in data:
            raise ConfigError(
                f"invalid config: {label}: {key}: templating is not accepted in a flylib config "
                "(Snakemake runs the Python inside such a file while reading it, before flylib can check it); remove "
                f"{key} and write the values out"
            )


@dataclass
class ConfigLayers:
    """Config files (and command-line overrides) merged in order.

    Attributes
    ----------
    layers
        ``(label, data)`` in merge order: a file's path as the user gave it, or
        :data:`OVERRIDES_LABEL`.
    data
        The merged mapping.
    texts
        ``label -> source text`` of every file layer.
    """

    layers: list[tuple[str, dict]]
    data: dict = field(default_factory=dict)
    texts: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_files(
        cls, files: Iterable[str | Path], overrides: Mapping | None = None
    ) -> ConfigLayers:
        """Read and merge config files (``.yaml``/``.yml``/``.json`` or ``.toml``), then
        ``overrides``; a ConfigError names the file (and line) that is missing, not UTF-8 or
        does not parse, or a key given twice in one file."""
        layers: list[tuple[str, dict]] = []
        texts: dict[str, str] = {}
        for f in files:
            path, label = Path(f), str(f)
            text = read_config_text(path, label)
            fmt = "toml" if path.suffix.lower() == ".toml" else "yaml"
            try:
                data = parse_text(text, fmt, label)
            except ConfigError as err:
                problems = getattr(err, "problems", None)
                if not problems:
                    raise
                lines = [f"{label}: {p}" for p in problems]
                raise ConfigError(
                    f"invalid config: {lines[0]}"
                    if len(lines) == 1
                    else f"invalid config {label} ({len(lines)} problems; fix and re-run):\n"
                    + "\n".join(f"  {line}" for line in lines)
                ) from None
            refuse_templating(data, label)
            layers.append((label, data))
            texts[label] = text
        if overrides:
            layers.append((OVERRIDES_LABEL, dict(overrides)))
        data: dict = {}
        removed: set[str] = set()
        for _, layer in layers:
            before = _cameras(data)
            removed |= {n for n, v in _cameras(layer).items() if v is None and n in before}
            merge_tables(data, layer)
        drop_views(data, removed - set(_cameras(data)))
        return cls(layers=layers, data=data, texts=texts)

    @property
    def labels(self) -> list[str]:
        """The layers' labels, in merge order."""
        return [label for label, _ in self.layers]

    def single_text(self) -> str | None:
        """The one file's exact text when the config is exactly one file, else ``None``."""
        if len(self.layers) == 1 and self.layers[0][0] in self.texts:
            return self.texts[self.layers[0][0]]
        return None

    def _walk(self, path: list[str | int]) -> tuple[str | None, str | None, int]:
        """``(owner, replaced, depth)``: the layer that set the value at ``path`` (or at its
        first ``depth`` keys, the deepest any layer sets), and the earlier layer whose list the
        owner replaced on the way (``None`` if none)."""
        candidates = list(self.layers)
        owner = replaced = None
        depth = 0
        for k in range(1, len(path) + 1):
            setters = [
                (label, layer) for label, layer in candidates if _depth(layer, path[:k]) == k
            ]
            if not setters:
                break
            owner, depth = setters[-1][0], k
            node = _value(setters[-1][1], path[:k])
            if not isinstance(node, Mapping):  # lists and scalars are replaced whole
                if isinstance(node, list) and len(setters) > 1 and k < len(path):
                    replaced = setters[-2][0]
                candidates = [setters[-1]]
        return owner, replaced, depth

    def _owner(self, path: list[str | int]) -> tuple[str | None, str | None]:
        """``(owner, replaced)`` of :meth:`_walk`; a camera's key that no layer sets on the camera
        itself is owned by whoever set it in ``cameras.defaults``, which every camera inherits."""
        owner, replaced, depth = self._walk(path)
        if depth < len(path) and len(path) >= 3 and path[0] == "cameras":
            inherited = ["cameras", _CAMERA_DEFAULTS, *path[2:]]
            fallback, fallback_replaced, fallback_depth = self._walk(inherited)
            if fallback_depth == len(inherited):
                return fallback, fallback_replaced
        return owner, replaced

    def origin(self, path: list[str | int] | str) -> str:
        """The layer that set the value at ``path`` (a key path or a problem line).

        Walking down the path, the last layer that sets each key owns it; below a list (which a
        later file replaces whole) only the layer that gave the list counts. With no match, every
        layer is named.
        """
        if isinstance(path, str):
            path = key_path(path)
        owner, _ = self._owner(path)
        return owner if owner is not None else " + ".join(self.labels) or "<config>"

    def config_dir(self, key: str) -> Path | None:
        """The folder of the config file that set top-level ``key`` (``None``: a command-line
        override or no layer)."""
        owner = self.origin([key])
        return Path(owner).absolute().parent if owner in self.texts else None

    def _hint(self, problem: str) -> str:
        path = key_path(problem)
        owner, replaced = self._owner(path)
        if replaced is None or path[:1] == ["recordings"]:  # a listing is always one's own
            return ""
        lists = [i for i in range(1, len(path)) if isinstance(path[i], int) or i == len(path) - 1]
        key = ".".join(str(t) for t in path[: lists[0]]) if lists else ".".join(map(str, path))
        hint = (
            f" ({owner} replaces the whole {key} list of {replaced}: restate every key of the entry"
        )
        if key == "pose2d.models":
            hint += ", or set only the checkpoint with pose2d.weights: {<model>: <path>}"
        return hint + ")"

    def _users(self) -> list[str]:
        """The layers the user wrote: every one but a copy of the packaged default config."""
        default = _default_text()
        return [label for label in self.labels if self.texts.get(label) != default]

    def _line(self, problem: str) -> str:
        """``problem`` naming the user's file that set its key; a key of the packaged default
        that the user's files broke is blamed on them, with the fix."""
        owner, users = self.origin(problem), self._users()
        if owner not in self.texts or owner in users or not users:
            return f"{owner}: {problem}{self._hint(problem)}"
        path = key_path(problem)
        key = ".".join(map(str, path))
        unknown = _UNKNOWN.search(problem)
        if not unknown or unknown[1] not in _REFERENCED:
            return f"{users[-1]}: {problem} ({owner}, the default config, sets {key}: set it in {users[-1]})"
        table = _REFERENCED[unknown[1]]
        user = self.origin(table.split("."))
        user = user if user in users else users[-1]
        where = ".".join(map(str, path[:3]))
        points = (self.data.get("pose2d") or {}).get("output_points") or {}
        views = [path[2]] if where.startswith("pose2d.output_points.") else []
        views = views or [v for v, t in points.items() if path[2] in pathways_of([t])]
        fix = f"add it back to {table}"
        if views:
            fix += (
                f", or remove camera {' and '.join(views)} with cameras: "
                f"{{{', '.join(f'{v}: null' for v in views)}}} (its pathways, output_points and "
                "sources go with it)"
            )
        return (
            f"{user}: {table}: no {unknown[1]} {unknown[2]}, which {where} of the default config "
            f"({owner}) reads; {fix}"
        )

    def report(self, problems: list[str]) -> str:
        """The problems as one line each, naming the user's file that set (or broke) the key;
        several get a header line naming the user's files."""
        lines = list(dict.fromkeys(self._line(p) for p in problems))
        if len(lines) == 1:
            return f"invalid config: {lines[0]}"
        count = f"{len(lines)} problems"
        return (
            f"invalid config {' + '.join(self._users() or self.labels)} ({count}; fix and re-run):\n"
            + "\n".join(f"  {line}" for line in lines)
        )
