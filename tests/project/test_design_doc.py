"""docs/DESIGN.md maps the tree: it names every module, script and folder, and every
path it names exists.

A name is a backticked span outside code blocks. A table row whose first cell names a
folder (``pipeline/``, ``workflow/rules/``), or a path in one (``interop/nwb.py``), and
the lines under a heading that names a folder, are *about* that folder: there a module
may be named on its own (``stages`` or ``stages.py``) and a path is resolved against
that folder as well as against the repository root and ``src/flylib``.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SRC = REPO / "src" / "flylib"
DOC = REPO / "docs" / "DESIGN.md"
SHARED = REPO.parent / "shared"

#: Folders whose every file of these suffixes the doc names (in the folder's row).
FOLDER_FILES = {
    "workflow/rules": "*.smk",
    "scripts": "*.py",
    "benchmarks": "*.py",
    "workflow/report": "*.rst",
}
PATH_SUFFIXES = (".py", ".pyi", ".smk", ".yaml", "/")
TICKED = re.compile(r"`([^`\n]+)`")


def resolve_dirs(token: str) -> set[Path]:
    """The folders a token such as ``pipeline/`` or ``workflow/rules/`` names (``config/``: two)."""
    return {(base / token).resolve() for base in (REPO, SRC) if (base / token).is_dir()}


def folders_in(text: str) -> set[Path]:
    """Folders named in ``text``: ``x/`` itself, or the folder of ``x/y.py``."""
    found = set()
    for token in TICKED.findall(text):
        if "/" in token and " " not in token:
            found |= resolve_dirs(token[: token.rindex("/") + 1])
    return found


def doc_lines(text: str) -> list[tuple[set[Path], str]]:
    """``(folders the line is about, line)`` for every line outside code blocks."""
    lines, section, fenced = [], set(), False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif fenced:
            continue
        elif line.startswith("#"):
            section = folders_in(line)
            lines.append((section, line))
        elif line.startswith("|"):
            first_cell = line.split("|")[1]
            lines.append((section | folders_in(first_cell), line))
        else:
            lines.append((section, line))
    return lines


def ticked(text: str) -> set[str]:
    return set(TICKED.findall(text))


def about(lines: list[tuple[set[Path], str]], folder: Path) -> set[str]:
    """The names on the lines about ``folder``."""
    return ticked("\n".join(line for folders, line in lines if folder.resolve() in folders))


def tracked_folders() -> set[str]:
    """Top-level folders of the checkout that hold tracked files (none outside git)."""
    try:
        out = subprocess.run(
            ["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return set()
    return {path.split("/")[0] for path in out.splitlines() if "/" in path}


def missing_names(text: str) -> list[str]:
    """What the doc should name and does not."""
    lines = doc_lines(text)
    everywhere = ticked("\n".join(line for _, line in lines))
    named_folders = set().union(*(resolve_dirs(t) for t in everywhere if t.endswith("/")))
    missing = []

    def check_folder(folder: Path) -> None:
        folder = folder.resolve()
        if not any(f == folder or folder in f.parents for f in named_folders):
            missing.append(f"{folder.relative_to(REPO)}/")

    def check_file(path: Path, *aliases: str) -> None:
        rel = path.relative_to(REPO).as_posix()
        full_names = {rel, path.relative_to(SRC).as_posix()} if SRC in path.parents else {rel}
        if full_names & everywhere:
            return
        if {path.name, *aliases} & about(lines, path.parent):
            return
        missing.append(rel)

    for path in sorted(SRC.iterdir()):
        if path.is_file():
            if path.name not in everywhere:
                missing.append(path.relative_to(REPO).as_posix())
        elif (path / "__init__.py").is_file():
            check_folder(path)
            for module in sorted(path.glob("*.py")):
                if module.name != "__init__.py":
                    check_file(module, module.stem)
    for folder, pattern in FOLDER_FILES.items():
        check_folder(REPO / folder)
        for path in sorted((REPO / folder).glob(pattern)):
            check_file(path)
    check_folder(REPO / "tests")
    for path in sorted((REPO / "tests").glob("*.py")):
        if not path.name.startswith("test_"):
            check_file(path)
    for name in sorted(tracked_folders()):
        check_folder(REPO / name)
    return list(dict.fromkeys(missing))


def is_repo_path(token: str) -> bool:
    """Heuristic: a backticked span meant as a path in the repository."""
    if any(c in token for c in " <>{}") or "://" in token:
        return False
    return "/" in token or token.endswith(PATH_SUFFIXES)


def exists(base: Path, token: str) -> bool:
    """``token`` under ``base``: a glob matches, or a module (``pose2d/plan``) is a file."""
    if "*" in token:
        return any(base.glob(token))
    return (base / token).exists() or (base / f"{token}.py").is_file()


def missing_paths(text: str) -> list[str]:
    """Paths the doc names that do not exist."""
    missing = []
    for folders, line in doc_lines(text):
        for token in TICKED.findall(line):
            if not is_repo_path(token):
                continue
            if token.startswith("../shared/") and not SHARED.is_dir():
                continue
            if not any(exists(base, token) for base in (REPO, SRC, *folders)):
                missing.append(token)
    return missing


def test_the_doc_names_every_module_script_and_folder():
    missing = missing_names(DOC.read_text(encoding="utf-8"))
    assert not missing, f"docs/DESIGN.md does not name: {', '.join(missing)}"


def test_every_path_the_doc_names_exists():
    missing = missing_paths(DOC.read_text(encoding="utf-8"))
    assert not missing, f"docs/DESIGN.md names what does not exist: {', '.join(missing)}"


# -- names and their modules -----------------------------------------------------------

PACKAGE_HEADING = "## The package"
IDENTIFIER = re.compile(r"[A-Za-z_]\w*")
MODULE_HEADER = re.compile(r"`(\w+)`:")


def module_names(path: Path, *, imports: bool = False) -> set[str]:
    """The names ``path`` defines at its top level (functions, classes, assignments),
    plus the names it imports when ``imports`` (a package's ``__init__`` re-exports)."""
    import ast

    names: set[str] = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                names |= {n.id for n in ast.walk(target) if isinstance(n, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif imports and isinstance(node, (ast.Import, ast.ImportFrom)):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names}
    return names


def package_rows(text: str) -> list[tuple[str, str]]:
    """``(first cell, last cell)`` of each row of the package table."""
    section = text[text.index(PACKAGE_HEADING) :]
    section = section[: section.index("\n## ", 1)]
    rows = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].startswith("`") and not set(cells[0]) <= {"-"}:
            rows.append((cells[0].strip("`"), cells[-1]))
    return rows


def misplaced_names(text: str) -> list[str]:
    """Names the package table lists under a module that does not define them.

    A row's first cell is a module (``accuracy.py``) or a package (``camera/``). In a
    package row, ```module`:`` starts that module's names; a name before any such header
    belongs to the package's ``__init__`` (defined or re-exported there), and a bare
    module name is a mention of that module. Paths, dotted names and code are skipped.
    """
    wrong = []
    for first, cell in package_rows(text):
        target = SRC / first
        if target.is_file():
            modules = {None: [target]}
        elif target.is_dir():
            modules = {p.stem: [p] for p in target.glob("*.py") if p.stem != "__init__"}
            init = [p for p in (target / "__init__.py", target / "__init__.pyi") if p.is_file()]
            modules[None] = modules["__init__"] = init
        else:
            wrong.append(f"{first}: no such module or package")
            continue
        headers = {m.start(1): m.group(1) for m in MODULE_HEADER.finditer(cell)}
        current = None
        for match in TICKED.finditer(cell):
            token = match.group(1)
            if match.start(1) in headers:
                current = token
                if token not in modules:
                    wrong.append(f"{first}: no module {token!r}")
                continue
            if not IDENTIFIER.fullmatch(token) or (current is None and token in modules):
                continue
            files = modules.get(current, [])
            is_init = current in (None, "__init__")
            defined = set().union(*(module_names(f, imports=is_init) for f in files))
            if token not in defined:
                where = f"{first}{current}.py" if current not in (None, "__init__") else first
                wrong.append(f"{token} (listed under {where})")
    return wrong


def test_every_name_in_the_package_table_is_defined_in_its_module():
    wrong = misplaced_names(DOC.read_text(encoding="utf-8"))
    assert not wrong, f"docs/DESIGN.md places names where they are not defined: {', '.join(wrong)}"


def test_the_name_check_sees_a_misplaced_name():
    """The check is not blind: a name moved to another module of its package is caught."""
    row = "| `camera/` | primitives | `model`: `CameraGroup`; `rig`: `Camera` |"
    text = f"{PACKAGE_HEADING}\n\n| module | layer | what |\n|---|---|---|\n{row}\n\n## Next\n"
    assert misplaced_names(text) == ["CameraGroup (listed under camera/model.py)"]


def test_the_paths_in_the_internals_page_exist():
    text = (REPO / "docs" / "internals.md").read_text(encoding="utf-8")
    missing = missing_paths(text)
    assert not missing, f"docs/internals.md names what does not exist: {', '.join(missing)}"
