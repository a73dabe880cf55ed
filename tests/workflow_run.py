"""The command line that runs the repository's workflow on a work directory: one place
for the tests and benchmarks that drive Snakemake."""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"


def load_script(name: str):
    """Import ``scripts/<name>.py`` as a module (its ``_cli`` import resolved): a stage
    script's ``main`` run in this process."""
    import importlib.util

    sys.path.insert(0, str(REPO / "scripts"))
    try:
        spec = importlib.util.spec_from_file_location(
            f"flylib_script_{name}", REPO / "scripts" / f"{name}.py"
        )
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(REPO / "scripts"))
    return module


def snakemake_command(workdir: Path, *args: str, cores: int = 2) -> list[str]:
    """``snakemake`` on the repo's Snakefile in ``workdir`` with its ``config.yaml``, a
    whole config that replaces the checkout's (``--replace-workflow-config``), so the
    snapshot is its byte-for-byte copy."""
    return [
        str(SNAKEMAKE),
        "--snakefile",
        str(REPO / "Snakefile"),
        "--directory",
        str(workdir),
        "--configfile",
        str(workdir / "config.yaml"),
        "--replace-workflow-config",
        "--cores",
        str(cores),
        *args,
    ]


def demo_batch(root: Path, count: int, config: dict, frames: int = 2) -> Path:
    """A recordings sheet (``root/recordings_<count>.tsv``) of ``count`` recordings, each
    the demo's recording of ``frames`` frames hard-linked into a folder of its own under
    ``root/data``, its 2D imported from its DeepLabCut CSVs: a lab's batch without
    detector weights. The demo is made once (``root/template``)."""
    import os

    from flylib.config import Config
    from flylib.pipeline.demo import demo_files, demo_import_spec, make_demo

    parsed = Config.from_dict(config)
    template = root / "template"
    if not template.is_dir():
        make_demo(parsed, template, frames=frames)
    spec = demo_import_spec(parsed)
    names = demo_files(parsed)
    files = ";".join(f"{view}={name}" for view, name in spec["files"].items())
    rows = ["path\timport_format\timport_files"]
    for i in range(count):
        rec = root / "data" / f"rec{i:05d}"
        if not rec.is_dir():
            rec.mkdir(parents=True)
            for name in (*names["footage"], *names["dlc"]):
                os.link(template / name, rec / name)
        rows.append(f"{rec}\t{spec['format']}\t{files}")
    sheet = root / f"recordings_{count}.tsv"
    sheet.write_text("\n".join(rows) + "\n")
    return sheet
