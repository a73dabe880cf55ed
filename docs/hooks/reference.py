"""The site's generated pages: the config reference, the CLI reference, the API page and
the pipeline's stage table and DAG, all read from the code (one source each).

MkDocs runs :func:`on_files` (``hooks:`` in ``mkdocs.yml``), which adds the pages as
generated files; ``tests/project/test_docs.py`` calls the same functions.

- :func:`config_reference`: every key of the packaged default config
  (``src/flylib/default_config.yaml``) with its default and the comments written above
  or beside it, the typed params' (``flylib.config``'s ``*Params``) field docs, the keys
  the default leaves unset (``pose2d.import`` from its importer, the other top-level
  tables), nothing kept by hand.
- :func:`cli_reference`: ``flylib --help`` and each subcommand's help from
  ``flylib.cli.build_parser``.
- :func:`api_reference`: one mkdocstrings entry per public name of ``flylib``
  (``src/flylib/__init__.pyi``).
- :func:`stage_table`, :func:`rule_graph`: the stage registry (``flylib.stages``) and
  Snakemake's own rule graph of the workflow with every stage on.
"""

from __future__ import annotations

import argparse
import ast
import functools
import inspect
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[2]
SRC = REPO / "src" / "flylib"
DEFAULT_CONFIG = SRC / "default_config.yaml"
#: Sub-tables of the default config shown whole (their keys are data: point names, views).
WHOLE = ("skeleton.limb_points", "skeleton.limb_palette", "pose2d.output_points")
KEY_LINE = re.compile(r"^(?P<indent>\s*)(?P<dash>- )?(?P<key>[A-Za-z_][\w-]*):(?P<rest>.*)$")


# --- the config reference -----------------------------------------------------------


def _inline_comment(rest: str) -> str:
    """The ``# comment`` after a YAML value (outside quotes), or ``""``."""
    quote = None
    for i, ch in enumerate(rest):
        if ch in "'\"" and quote in (None, ch):
            quote = None if quote else ch
        elif ch == "#" and quote is None and (i == 0 or rest[i - 1] == " "):
            return rest[i + 1 :].strip()
    return ""


def config_comments(text: str) -> dict[str, str]:
    """``dotted key -> the comment written above it and beside it`` in a commented YAML
    config; a key inside a list item is ``table.list[].key``."""
    comments: dict[str, str] = {}
    stack: list[tuple[int, str]] = []  # (indent of the key, its path)
    block: list[str] = []
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith("# ---"):
            block = []
            continue
        if stripped.startswith("#"):
            block.append(stripped.lstrip("#").strip())
            continue
        match = KEY_LINE.match(line)
        if not match:
            block = []
            continue
        indent = len(match["indent"]) + (2 if match["dash"] else 0)
        if match["dash"]:  # a new list item: its keys sit under "<list>[]"
            while stack and stack[-1][0] >= indent - 1:
                stack.pop()
            stack.append((indent - 1, (stack[-1][1] if stack else "") + "[]"))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        parent = stack[-1][1] if stack else ""
        path = f"{parent}.{match['key']}" if parent else match["key"]
        stack.append((indent, path))
        text_ = " ".join(block + [_inline_comment(match["rest"])]).strip()
        if text_ and path not in comments:
            comments[path] = text_
        block = []
    return comments


def _keys(value: Any, path: str = "") -> list[tuple[str, Any]]:
    """``(dotted key, default)`` for every key of the default config, tables first-level
    down to their leaves; a list of tables as ``key[].field``; :data:`WHOLE` kept whole."""
    rows: list[tuple[str, Any]] = []
    if isinstance(value, dict) and path not in WHOLE:
        for key, sub in value.items():
            child = f"{path}.{key}" if path else str(key)
            rows.append((child, sub))
            rows += _keys(sub, child)
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        fields_: dict[str, Any] = {}
        for item in value:
            for key, sub in item.items():
                fields_.setdefault(key, sub)
        for key, sub in fields_.items():
            rows.append((f"{path}[].{key}", sub))
    return rows


def _shown(value: Any, limit: int = 70) -> str:
    """A default as one line of YAML (flow style), shortened past ``limit`` characters."""
    if isinstance(value, dict) and value:
        return "(table)"
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        return f"(list of {len(value)} tables)"
    text = yaml.safe_dump(value, default_flow_style=True, width=10_000).strip()
    text = text.removesuffix("\n...").removesuffix("...").strip()
    return text if len(text) <= limit else text[: limit - 3] + "..."


def param_docs() -> dict[str, tuple[Any, str]]:
    """``table.field -> (default, description)`` of every typed params field
    (``flylib.config``'s ``*Params`` dataclasses, descriptions from their docstrings)."""
    from dataclasses import MISSING, fields

    from flylib.config.params import PARAM_TABLES

    docs: dict[str, tuple[Any, str]] = {}
    for table, cls in PARAM_TABLES.items():
        described = _attributes(inspect.getdoc(cls) or "")
        for f in fields(cls):
            default = f.default if f.default is not MISSING else None
            if f.default_factory is not MISSING:  # type: ignore[misc]
                default = f.default_factory()  # type: ignore[misc]
            docs[f"{table}.{f.name}"] = (default, described.get(f.name, ""))
    return docs


def _attributes(doc: str) -> dict[str, str]:
    """A numpy-style docstring's ``Attributes`` section: ``name -> description``."""
    out: dict[str, str] = {}
    lines = doc.splitlines()
    try:
        start = lines.index("Attributes") + 2
    except ValueError:
        return out
    names: list[str] = []
    for line in lines[start:]:
        if line and not line.startswith(" "):
            if re.fullmatch(r"[A-Za-z_]\w*(,\s*[A-Za-z_]\w*)*(\s*:.*)?", line) is None:
                break
            names = [n.strip() for n in line.split(":")[0].split(",")]  # "a, b": one text
            out.update(dict.fromkeys(names, ""))
        elif names and line.strip():
            for name in names:
                out[name] = (out[name] + " " + line.strip()).strip()
    return out


def import_keys() -> list[tuple[str, str, str]]:
    """``(key, example, comment)`` of ``pose2d.import`` from its importer's documented
    block (``flylib.interop.importer``), checked against the keys it accepts."""
    from flylib.interop import importer

    rows = []
    for line in (importer.__doc__ or "").splitlines():
        match = re.match(r"^\s{8}(\w+):\s*(.*?)\s+#\s*(.*)$", line)
        if match:
            rows.append((match[1], match[2], match[3]))
    missing = set(importer.IMPORT_KEYS) - {r[0] for r in rows}
    if missing:
        raise RuntimeError(f"flylib.interop.importer's docstring does not document {missing}")
    return rows


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def config_reference() -> str:
    """The config reference page (Markdown)."""
    from flylib.config.constants import TOP_LEVEL_KEYS

    text = DEFAULT_CONFIG.read_text()
    data = yaml.safe_load(text)
    comments = config_comments(text)
    typed = param_docs()
    out = [
        "# Configuration reference",
        "",
        "Generated from the packaged default config (`src/flylib/default_config.yaml`, "
        "equal to `config/config.yaml`) and flylib's typed parameters when the site is "
        "built: every key, its default, and what it does. Put the keys you change in your "
        "own file and pass it with `--configfile my.yaml` (see "
        "[Your recordings](../guides/recordings.md)); tables merge key by key, a list is "
        "replaced whole. Which stages an edit re-runs: [Re-runs](../guides/reruns.md).",
        "",
    ]
    rows = _keys(data)
    seen = {key for key, _ in rows}
    tables = list(data)
    for table in tables:
        out += [f"## `{table}`", "", "| key | default | what |", "|---|---|---|"]
        for key, value in rows:
            if key != table and not key.startswith((table + ".", table + "[]")):
                continue
            what = comments.get(key) or typed.get(key, (None, ""))[1]
            out.append(f"| `{key}` | `{_cell(_shown(value))}` | {_cell(what)} |")
        extra = [k for k in typed if k.startswith(table + ".") and k not in seen]
        for key in extra:
            default, what = typed[key]
            out.append(
                f"| `{key}` | `{_cell(_shown(default))}` | {_cell(what)} (not in the default config) |"
            )
        if table == "pose2d":
            for key, example, what in import_keys():
                out.append(
                    f"| `pose2d.import.{key}` | (unset); e.g. `{_cell(example)}` | {_cell(what)} |"
                )
        out.append("")
    unset = [k for k in TOP_LEVEL_KEYS if k not in data]
    out += [
        "## Tables the default config leaves unset",
        "",
        "Accepted at the top level of a config, documented in the guides:",
        "",
    ]
    guide = {
        "calibration": "[imports](../guides/imports.md#calibrations-from-other-tools)",
        "demo": "[getting started](../getting-started.md)",
        "exports": "[NWB and movement](../guides/exports.md)",
        "nwb": "[NWB and movement](../guides/exports.md)",
        "corrections": "[reviewing](../guides/reviewing.md)",
    }
    for key in unset:
        where = comments.get(key, "")
        out.append(f"- `{key}`: {guide.get(key, '')} {where}".rstrip())
    return "\n".join(out) + "\n"


# --- the CLI reference ----------------------------------------------------------------


def cli_reference() -> str:
    """The CLI reference page: the help of ``flylib`` and of each subcommand."""
    from flylib.cli import build_parser

    os.environ.setdefault("COLUMNS", "100")
    parser = build_parser()
    out = [
        "# Command-line reference",
        "",
        "Generated from `flylib.cli.build_parser` when the site is built. Every stage is "
        "also a script with the options its rule passes: "
        "`.venv/bin/python scripts/<stage>.py --help`.",
        "",
        "## `flylib`",
        "",
        "```text",
        parser.format_help().rstrip(),
        "```",
        "",
    ]
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, subparser in sub.choices.items():
        out += [f"## `flylib {name}`", "", "```text", subparser.format_help().rstrip(), "```", ""]
    return "\n".join(out)


# --- the API page ---------------------------------------------------------------------


def public_names() -> dict[str, str]:
    """``name -> module`` of every public name of ``flylib`` (its ``__init__.pyi``)."""
    tree = ast.parse((SRC / "__init__.pyi").read_text())
    names: dict[str, str] = {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            module = "flylib" + (f".{node.module}" if node.module else "")
            for alias in node.names:
                names[alias.asname or alias.name] = (
                    module if node.module else f"flylib.{alias.name}"
                )
    return names


def api_reference() -> str:
    """The API page: every public name of ``flylib``, by module, via mkdocstrings."""
    by_module: dict[str, list[str]] = {}
    for name, module in public_names().items():
        by_module.setdefault(module, []).append(name)
    out = [
        "# Library API",
        "",
        "Every public name of `flylib` (`from flylib import ...`), grouped by the module "
        "that defines it, with its docstring. Generated from `src/flylib/__init__.pyi`.",
        "",
    ]
    for module, names in by_module.items():
        out += [f"## `{module}`", ""]
        for name in names:
            target = (
                module
                if name == module.rsplit(".", 1)[-1] and module.endswith(name)
                else f"{module}.{name}"
            )
            out += [f"::: {target}", "    options:", "      heading_level: 3", ""]
    return "\n".join(out)


# --- the pipeline --------------------------------------------------------------------


def stage_table() -> str:
    """The stage records as a Markdown table."""
    from flylib.stages import REGISTRY

    out = [
        "| stage | runs by default | needs one of | artifact (`<outdir>/stages/`) | group in `results.h5` |",
        "|---|---|---|---|---|",
    ]
    for stage in REGISTRY:
        on = {True: "yes", False: "no (opt-in)", None: "always"}[stage.default_on]
        if stage.toggled:
            on += f" (`pipeline.do_{stage.name}`)"
        needs = ", ".join(f"`{s}`" for s in stage.needs_one_of) or "-"
        artifact = f"`{stage.artifact}`" if stage.artifact else "-"
        out.append(
            f"| `{stage.name}` | {on} | {needs} | {artifact} | {'yes' if stage.results_group else '-'} |"
        )
    return "\n".join(out)


#: A config turning every stage and export on, so the graph shows every rule.
ALL_ON = """
pipeline: {do_pictorial_structures: true, do_neuromechfly: true}
bundle_adjustment: {session: true}
exports: {nwb: true}
"""


@functools.cache
def rule_graph() -> str:
    """Snakemake's rule graph of the workflow on the demo with every stage on, as a
    Mermaid flowchart (``snakemake --rulegraph mermaid-js``)."""
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "all_on.yaml").write_text(ALL_ON)
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join(
                filter(None, [str(REPO / "src"), os.environ.get("PYTHONPATH")])
            ),
        }
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "snakemake",
                "-s",
                str(REPO / "Snakefile"),
                "-d",
                tmp,
                "--configfile",
                str(Path(tmp) / "all_on.yaml"),
                "--rulegraph",
                "mermaid-js",
                "--cores",
                "1",
            ],
            capture_output=True,
            text=True,
            env=env,
            check=True,
        )
    lines = [line for line in done.stdout.splitlines() if "style id" not in line]
    body = "\n".join(lines)
    body = re.sub(r"^---\ntitle: DAG\n---\n", "", body)
    return "```mermaid\n" + body.strip() + "\n```"


# --- the end-of-run table ----------------------------------------------------------------


def _held(median: float, p95: float) -> dict:
    return {"held_out_px": {"median": median, "p95": p95, "n": 3500}, "per_view": {}}


def run_table_example() -> str:
    """The end-of-run table as ``flylib.run_summary.run_table`` prints it, for a recording
    whose ``summary.json`` holds made-up figures (the format is the code's)."""
    import json

    from flylib.run_summary import RunRecording, run_table

    points = {f"p{i}": {"median": 5.0, "p95": 15.0, "n": 500} for i in range(30)}
    summary = {
        "frames": 9000,
        "reconstructed_3d_fraction": 0.974,
        "reprojection_error_px": {"median": 2.31, "p95": 8.9},
        "suspects": 41,
        "accuracy": {
            "frames_evaluated": 500,
            "frames_total": 9000,
            "triangulation": _held(5.87, 16.97),
            "refinement": _held(5.83, 16.71),
            "output": {**_held(5.78, 16.70), "per_point": points},
            "kept_triangulation": [f"p{i}" for i in range(8, 30)],
            "kept_everywhere": False,
            "output_stage": "refinement",
        },
    }
    with tempfile.TemporaryDirectory() as tmp:
        outdir = Path(tmp) / "fly7"
        outdir.mkdir()
        (outdir / "summary.json").write_text(json.dumps(summary))
        table = run_table([RunRecording("fly7", outdir)])
        table = table.replace(str(outdir), "/results/fly7")
    return "```text\n" + table + "\n```"


# --- the MkDocs hook -------------------------------------------------------------------

GENERATED = {
    "reference/config.md": config_reference,
    "reference/cli.md": cli_reference,
    "reference/api.md": api_reference,
}


def on_files(files, config):  # noqa: D103 (MkDocs hook)
    from mkdocs.structure.files import File

    for uri, make in GENERATED.items():
        files.append(File.generated(config, uri, content=make()))
    return files


def on_page_markdown(markdown, page, config, files):  # noqa: D103 (MkDocs hook)
    if "<!-- stage-table -->" in markdown:
        markdown = markdown.replace("<!-- stage-table -->", stage_table())
    if "<!-- run-table -->" in markdown:
        markdown = markdown.replace("<!-- run-table -->", run_table_example())
    if "<!-- rule-graph -->" in markdown:
        markdown = markdown.replace("<!-- rule-graph -->", rule_graph())
    return markdown
