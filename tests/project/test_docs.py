"""The documentation site (``mkdocs.yml``, ``docs/``): its generated reference pages cover
the code, every config snippet it shows is a valid flylib config, it builds with
``mkdocs build --strict`` and no internal link in the built site is broken, and the
example notebooks run."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest
import yaml

from flylib.config import validate_config
from flylib.config.layers import ConfigLayers
from flylib.paths import DEFAULT_CONFIG_PATH

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
SHARED_DATA = REPO.parent / "shared" / "data"


def _generator():
    spec = importlib.util.spec_from_file_location("docs_reference", DOCS / "hooks" / "reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


GEN = _generator()


def pages() -> dict[str, str]:
    """``README.md`` and every Markdown page of the site, by path."""
    found = {"README.md": (REPO / "README.md").read_text()}
    for path in sorted(DOCS.rglob("*.md")):
        found[str(path.relative_to(REPO))] = path.read_text()
    return found


def yaml_snippets() -> list[tuple[str, str]]:
    return [
        (name, block)
        for name, text in pages().items()
        for block in re.findall(r"^```yaml\n(.*?)^```", text, re.S | re.M)
    ]


# --- generated reference pages ------------------------------------------------------


def test_the_config_reference_lists_every_key_of_the_default_config():
    page = GEN.config_reference()
    keys = [key for key, _ in GEN._keys(yaml.safe_load(GEN.DEFAULT_CONFIG.read_text()))]
    assert len(keys) > 100
    missing = [key for key in keys if f"| `{key}` |" not in page]
    assert not missing


def test_the_config_reference_lists_every_typed_param_and_import_key():
    from flylib.interop.importer import IMPORT_KEYS

    page = GEN.config_reference()
    for key in GEN.param_docs():
        assert f"`{key}`" in page, key
    for key in IMPORT_KEYS:
        assert f"| `pose2d.import.{key}` |" in page, key
    (row,) = [line for line in page.splitlines() if "`pose2d.import.image_size`" in line]
    assert "height, width" in row


def test_the_api_page_lists_every_public_name_of_flylib():
    import flylib

    names = GEN.public_names()
    assert set(names) == set(flylib.__all__)
    page = GEN.api_reference()
    for name, module in names.items():
        assert re.search(rf"^::: {re.escape(module)}(\.{re.escape(name)})?$", page, re.M), name


def test_the_cli_reference_has_every_subcommand():
    from flylib.cli import build_parser

    page = GEN.cli_reference()
    (sub,) = [a for a in build_parser()._actions if hasattr(a, "choices") and a.choices]
    for name in sub.choices:
        assert f"## `flylib {name}`" in page


def test_the_rule_graph_is_snakemakes_and_names_every_rule():
    graph = GEN.rule_graph()
    rules = set()
    for smk in [REPO / "Snakefile", *(REPO / "workflow" / "rules").glob("*.smk")]:
        rules |= set(re.findall(r"^\s*rule (\w+):", smk.read_text(), re.M))
    drawn = set(re.findall(r"id\d+\[(\w+)\]", graph))
    assert drawn == rules - {"all"} | ({"all"} & drawn)


def test_every_placeholder_a_page_holds_is_filled():
    for path in DOCS.rglob("*.md"):
        text = GEN.on_page_markdown(path.read_text(), None, None, None)
        assert "<!-- " not in text.replace("<!-- more -->", ""), path


def test_the_run_table_example_is_flylibs_own_output():
    example = GEN.run_table_example()
    assert example.startswith("```text\nflylib: per-recording results\n")
    assert "fly7 " in example and "/results/fly7" in example


def test_the_stage_table_lists_every_registered_stage():
    from flylib.stages import REGISTRY

    table = GEN.stage_table()
    for stage in REGISTRY:
        assert f"| `{stage.name}` |" in table


def test_troubleshooting_names_every_user_facing_error_class():
    import flylib.errors as errors

    page = (DOCS / "troubleshooting.md").read_text()
    classes = [
        name
        for name, obj in vars(errors).items()
        if isinstance(obj, type)
        and issubclass(obj, errors.FlylibError)
        and obj is not errors.FlylibError
    ]
    assert len(classes) >= 7
    for name in classes:
        assert f"## {name}" in page, name


def test_the_camera_group_warning_page_quotes_the_fit_warning():
    source = (REPO / "src" / "flylib" / "bundle_adjustment" / "messages.py").read_text()
    source = re.sub(r"\"\s*\n\s*f?\"", "", source)  # the f-strings' pieces joined
    page = (DOCS / "how-it-works" / "warnings.md").read_text()
    for quoted in re.findall(r'^## "([^"]*)"', page, re.M):
        for part in quoted.split("..."):
            part = re.sub(r"\bN\b|\d+", "", part).strip(" ")
            for words in filter(None, (w.strip() for w in re.split(r"\s{2,}", part))):
                assert words in source, words


# --- config snippets ------------------------------------------------------------------


def test_the_pages_show_config_snippets():
    assert len(yaml_snippets()) >= 10


@pytest.mark.parametrize("where,snippet", yaml_snippets(), ids=lambda v: str(v)[:40])
def test_every_config_snippet_is_valid_over_the_default(tmp_path, where, snippet):
    """Merged over the default as the workflow merges a user's file (ConfigLayers)."""
    assert isinstance(yaml.safe_load(snippet), dict), f"{where}: a snippet must be a config table"
    mine = tmp_path / "my.yaml"
    mine.write_text(snippet)
    merged = ConfigLayers.from_files([DEFAULT_CONFIG_PATH, mine]).data
    assert validate_config(merged) == [], (where, snippet)


def _dry_run(tmp_path: Path, data: dict) -> subprocess.CompletedProcess:
    config = tmp_path / "snippet.yaml"
    config.write_text(yaml.safe_dump(data))
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "snakemake",
            "-s",
            str(REPO / "Snakefile"),
            "-d",
            str(tmp_path),
            "--configfile",
            str(config),
            "-n",
            "--cores",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.parametrize(
    "where,snippet",
    [(w, s) for w, s in yaml_snippets() if "recordings" in yaml.safe_load(s)],
    ids=lambda v: str(v)[:40],
)
def test_every_whole_run_config_snippet_plans_on_the_demo(tmp_path, where, snippet):
    """A snippet that lists recordings is a run's config: with its recordings pointed at
    the demo (which the workflow makes), Snakemake plans it."""
    data = yaml.safe_load(snippet)
    data["recordings"] = [{"path": "demo", "demo": True}]
    data.pop("recursive", None)
    done = _dry_run(tmp_path, data)
    assert done.returncode == 0, (where, done.stderr[-2000:])


def test_the_fewer_cameras_report_is_flylibs_own_output(tmp_path):
    """The rig report the rig guide shows under its first snippet, and the last line it
    quotes for the default rig, are what `flylib check-config` prints (recordings: the demo)."""
    page = (DOCS / "guides" / "cameras.md").read_text()
    section = page.split("### Fewer cameras")[1].split("\n## ")[0]
    snippet = re.findall(r"^```yaml\n(.*?)^```", section, re.S | re.M)[0]
    shown = re.findall(r"^```text\n(.*?)^```", section, re.S | re.M)[0]
    default_line = " ".join(re.search(r"the last line is `(.*?)`", section, re.S)[1].split())
    data = yaml.safe_load(snippet)
    data["recordings"] = [{"path": "demo", "demo": True}]
    reports = []
    for mine in (data, {"recordings": data["recordings"]}):
        (tmp_path / "my.yaml").write_text(yaml.safe_dump(mine))
        done = subprocess.run(
            [sys.executable, "-m", "flylib.cli", "check-config", "my.yaml"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr
        reports.append(done.stdout.splitlines()[1:])
    assert reports[0] == shown.splitlines()
    assert reports[1][-1] == default_line


# --- Python snippets and pictures ----------------------------------------------------


def python_snippets(page: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", page.read_text(), re.S | re.M)


@pytest.mark.slow
@pytest.mark.shared
def test_every_python_block_of_the_library_guide_runs_in_order(tmp_path, monkeypatch):
    """The library guide's blocks, one after the other in one namespace, in an empty folder,
    as a reader pastes them; its DeepFly3D folder (`fly1_df3d`) is DeepFly3D's package example."""
    example = SHARED_DATA / "deepfly3d-package-example"
    if not example.is_dir():
        pytest.skip(f"{example} is absent: the guide's last block reads DeepFly3D's example")
    page = DOCS / "guides" / "library.md"
    blocks = python_snippets(page)
    assert len(blocks) >= 8
    (tmp_path / "fly1_df3d").symlink_to(example)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for number, block in enumerate(blocks, 1):
        exec(compile(block, f"{page.name}, block {number}", "exec"), namespace)
    assert (tmp_path / "results.h5").is_file() and (tmp_path / "calibration.toml").is_file()


def test_the_library_guide_imports_only_public_names():
    import flylib

    code = "\n".join(python_snippets(DOCS / "guides" / "library.md"))
    imported = re.findall(r"^from flylib import \(?([^)]*?)\)?$", code, re.M | re.S)
    names = {n.strip() for group in imported for n in group.split(",") if n.strip()}
    assert names and names <= set(flylib.__all__), names - set(flylib.__all__)
    assert not re.search(r"^(from|import) flylib\.", code, re.M)


@pytest.mark.slow
def test_the_developer_pages_block_runs_on_a_demo_result_with_public_names(tmp_path, monkeypatch):
    """docs/developers/bundle-adjustment.md's block, pasted in a folder holding a demo run's
    results.h5 (where the README's run writes it), imports only public names and runs."""
    import flylib

    from gui_fixtures import make_demo_outputs

    (block,) = python_snippets(DOCS / "developers" / "bundle-adjustment.md")
    assert not re.search(r"^(from|import) flylib\.", block, re.M)
    names = re.findall(r"^from flylib import (.*)$", block, re.M)[0].split(", ")
    assert set(names) <= set(flylib.__all__), set(names) - set(flylib.__all__)
    make_demo_outputs(tmp_path / "demo", frames=4)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block, "bundle-adjustment.md", "exec"), namespace)
    assert namespace["pts3d"].shape == (4, 38, 3) and len(namespace["cameras"].names) == 7


def test_the_keypoints_page_lists_the_skeletons_points_limbs_and_cameras():
    from flylib import Config, Skeleton

    page = (DOCS / "reference" / "keypoints.md").read_text()
    rows = re.findall(r"^\| (\d+) \| `(\w+)` \| `(\w+)` \| [^|]+ \| ([^|]*) \|$", page, re.M)
    skeleton, config = Skeleton.fly(), Config.default()
    limb_of = {p: limb for limb, points in skeleton.limbs.items() for p in points}
    plan = config.data["pose2d"]["output_points"]
    assert [(int(i), name) for i, name, _, _ in rows] == list(enumerate(skeleton.point_names))
    for _, name, limb, cameras in rows:
        assert limb == limb_of[name], name
        assert cameras.strip() == ", ".join(v for v in config.view_names() if name in plan[v])


def test_the_pictures_are_drawn_by_their_script(tmp_path):
    """docs/images/make_figures.py draws both pictures from flylib's facts; the committed
    ones have the size it draws and stay small."""
    from matplotlib.image import imread

    spec = importlib.util.spec_from_file_location(
        "make_figures", DOCS / "images" / "make_figures.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    for drawn in module.main(tmp_path):
        committed = DOCS / "images" / drawn.name
        assert committed.stat().st_size < 200_000, committed
        assert imread(committed).shape == imread(drawn).shape, "re-run docs/images/make_figures.py"
        assert f"images/{drawn.name})" in "".join(pages().values()), drawn.name


# --- the built site -----------------------------------------------------------------


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.links: list[str] = []
        self.ids: set[str] = set()

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if "id" in attrs:
            self.ids.add(attrs["id"])
        for key in ("href", "src"):
            if attrs.get(key):
                self.links.append(attrs[key])


def parse_site(site: Path) -> dict[Path, _Links]:
    """Every page of a built site (but the 404 page, whose links are site-absolute)."""
    parsed = {}
    for html in site.rglob("*.html"):
        if html.name == "404.html":
            continue
        parser = _Links()
        parser.feed(html.read_text(errors="replace"))
        parsed[html] = parser
    return parsed


def broken_links(site: Path, parsed: dict[Path, _Links]) -> list[str]:
    """Internal links (and images) of a built site whose file or anchor does not exist."""
    broken = []
    for html, parser in parsed.items():
        for link in parser.links:
            parts = urlsplit(link)
            if parts.scheme or parts.netloc or link.startswith(("mailto:", "data:", "javascript:")):
                continue
            path = unquote(parts.path)
            base = site if path.startswith("/") else html.parent
            target = (base / path.lstrip("/")).resolve() if path else html
            if target.is_dir():
                target = target / "index.html"
            if not target.exists():
                broken.append(f"{html.relative_to(site)}: {link}")
            elif parts.fragment and target.suffix == ".html" and target in parsed:
                if unquote(parts.fragment) not in parsed[target].ids:
                    broken.append(f"{html.relative_to(site)}: {link} (no such anchor)")
    return broken


def test_the_link_check_finds_a_missing_page_and_a_missing_anchor(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "index.html").write_text('<h2 id="here">x</h2><a href="#here">ok</a>')
    (tmp_path / "index.html").write_text(
        '<a href="a/">ok</a><a href="a/#here">ok</a><a href="a/#gone">x</a>'
        '<a href="b/">x</a><img src="pic.png"><a href="https://example.org/x">ext</a>'
    )
    assert sorted(broken_links(tmp_path, parse_site(tmp_path))) == [
        "index.html: a/#gone (no such anchor)",
        "index.html: b/",
        "index.html: pic.png",
    ]


@pytest.mark.slow
def test_the_site_builds_strict_with_no_broken_internal_link(tmp_path):
    site = tmp_path / "site"
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(site)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    parsed = parse_site(site)
    broken = broken_links(site, parsed)
    assert not broken, broken
    api = parsed[site / "reference" / "api" / "index.html"].ids
    missing = [
        f"{module}.{name}"
        for name, module in GEN.public_names().items()
        if f"{module}.{name}" not in api and module not in api
    ]
    assert not missing  # each public name rendered by mkdocstrings, under its own anchor
    for name in (
        "reference/api/index.html",
        "reference/config/index.html",
        "examples/deepfly3d_sample/index.html",
    ):
        assert (site / name).is_file(), name


# --- the example notebooks ------------------------------------------------------------

NOTEBOOKS = sorted((DOCS / "examples").glob("*.ipynb"))


def test_the_examples_are_stored_with_their_outputs():
    import nbformat

    assert len(NOTEBOOKS) >= 2
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert code and all(
            c.outputs for c in code if "import" not in c.source.split("\n")[0] or c.outputs
        ), path
        assert not any(o.output_type == "error" for c in code for o in c.outputs), path


@pytest.mark.slow
@pytest.mark.shared
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_the_example_notebook_runs(path, tmp_path):
    """Executed by nbmake's runner (what ``pytest --nbmake docs/examples`` runs: a fresh
    kernel, the notebook's folder as working directory, stored outputs cleared first)."""
    if not (SHARED_DATA / "deepfly3d-sample").is_dir():
        pytest.skip(
            f"{SHARED_DATA / 'deepfly3d-sample'} is absent: the examples read the DeepFly3D sample"
        )
    import nbformat
    from nbmake.nb_run import NotebookRun

    result = NotebookRun(path, default_timeout=600, kernel="python3").execute()
    assert result.error is None, result.error.summary + "\n" + result.error.trace[-3000:]
    # the figures the site shows (the stored outputs) are what the code prints now
    stored = nbformat.read(path, as_version=4)
    assert _printed(result.nb) == _printed(stored), "re-run the notebook and store its outputs"


def _printed(nb) -> list[str]:
    """What a notebook's code cells print to stdout, cell by cell (figures and logs aside)."""
    return [
        "".join(o.get("text", "") for o in cell.outputs if o.get("name") == "stdout")
        for cell in nb.cells
        if cell.cell_type == "code"
    ]


# --- figures the pages quote ------------------------------------------------------------
