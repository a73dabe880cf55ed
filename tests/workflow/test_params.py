"""A rule's params reach Snakemake as they are: a `{index}` or `{view}` in a config
value (an import pattern, NWB session metadata) is the user's text, not a wildcard of
the rule, so the DAG builds (Snakemake formats a plain string param as a pattern)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml

from workflow_run import snakemake_command

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow

#: The recording's CSVs by camera index, as a pattern.
PATTERN = "camera_{index}DLC_x.csv"

NWB = {
    "session_start_time": "2024-05-01T10:00:00+00:00",
    "experimenter": ["Doe, Jane"],
    "session_description": "camera {index} and view {view} as typed",
    "subject": {"subject_id": "fly_{index}", "sex": "F", "age": "P3D"},
}


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """A 4-frame synthetic recording whose DeepLabCut CSVs are named by camera index
    (:data:`PATTERN`), and its ``view -> CSV`` files."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    root = tmp_path_factory.mktemp("params") / "rec"
    config = Config.from_file(REPO / "config" / "config.yaml")
    make_demo(config, root, frames=4, seed=0)
    files = {}
    for index, (view, name) in enumerate(demo_import_spec(config)["files"].items()):
        files[view] = PATTERN.format(index=index)
        (root / name).rename(root / files[view])
    return root, files


def dry_run(workdir: Path, config: dict) -> tuple[str, set[str]]:
    """The output of a dry run of ``config`` and the rules it schedules."""
    (workdir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    proc = subprocess.run(
        snakemake_command(workdir, "--dry-run"),
        capture_output=True,
        text=True,
        timeout=600,
        cwd=workdir,
        check=False,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    return out, {line.split()[-1].rstrip(":") for line in out.splitlines() if "rule " in line}


def base(recording_dir: Path, files: str | dict[str, str]) -> dict:
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["recordings"] = [str(recording_dir)]
    config["pose2d"]["import"] = {"format": "dlc_csv", "files": files}
    return config


def test_an_import_pattern_in_the_config_is_text_not_a_wildcard(recording, tmp_path):
    out, planned = dry_run(tmp_path, base(recording[0], PATTERN))
    assert "WildcardError" not in out
    assert {"pose2d", "triangulation", "assemble"} <= planned


def test_braces_in_the_nwb_metadata_are_text_not_wildcards(recording, tmp_path):
    config = {**base(*recording), "exports": {"nwb": True}, "nwb": NWB}
    out, planned = dry_run(tmp_path, config)
    assert "WildcardError" not in out
    assert {"pose2d", "export_nwb"} <= planned
