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
