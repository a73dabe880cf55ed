"""A new stage is its home module plus its rule file: added to a copy of the checkout (the
workflow and the package), a throwaway stage runs through ``snakemake`` with no other file
touched. Its record gives its toggle, its place in the run, its config table (defaults and
checks from its params class, in neither YAML copy) and the file the run asks for."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from workflow_run import SNAKEMAKE

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow

#: The stage's home: its record, params, inputs and run, and nothing else anywhere.
HOME = '''"""centroid: each frame's centroid of the 3D points, results.h5 -> centroid.csv."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config.checks import integer, param
from ..results import PoseResult
from ..stages import Stage
from .inputs import StageInputs, register


@dataclass(frozen=True)
class CentroidParams:
    """The ``centroid`` table."""

    decimals: int = param(3, integer(minimum=0))


RECORD = Stage(
    "centroid",
    default_on=True,
    after=("assemble",),
    needs_one_of=("triangulation",),
    params=CentroidParams,
    outputs=("centroid.csv",),
)


@register
@dataclass(frozen=True)
class CentroidInputs(StageInputs):
    STAGE = "centroid"

    centroid: CentroidParams

    @classmethod
    def from_config(cls, config) -> CentroidInputs:
        return cls(centroid=config.params("centroid"))


def run_centroid(inputs: CentroidInputs, results, table) -> None:
    points = PoseResult.load(results).pts3d
    rows = np.round(np.nanmean(points, axis=1), inputs.centroid.decimals)
    table.write_text("x,y,z\\n" + "".join(",".join(map(str, row)) + "\\n" for row in rows))
'''

#: Its rule file: what every stage rule states, the script shared by such stages.
RULES = """if FLAGS["centroid"]:

    rule centroid:
        input:
            results="{outdir}/results.h5",
        output:
            table="{outdir}/centroid.csv",
        log:
            "{outdir}/logs/centroid.log",
        params:
            **job_params("centroid", recording_path=False),
        script:
            "../../scripts/stage.py"
"""


def _checkout_with_stage(root: Path) -> Path:
    """A copy of the checkout's workflow and package, plus the stage's two files."""
    checkout = root / "checkout"
    for part in ("Snakefile", "workflow", "scripts", "config", "envs", "profiles", "src/flylib"):
        source, target = REPO / part, checkout / part
        if source.is_dir():
            shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
    (checkout / "src/flylib/pipeline/centroid.py").write_text(HOME)
    (checkout / "workflow/rules/centroid.smk").write_text(RULES)
    return checkout


def _run(checkout: Path, work: Path, config: dict, *args: str) -> subprocess.CompletedProcess:
    (work / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    command = [
        str(SNAKEMAKE),
        "--snakefile",
        str(checkout / "Snakefile"),
        "--directory",
        str(work),
        "--configfile",
        str(work / "config.yaml"),
        "--replace-workflow-config",
        "--cores",
        "2",
        *args,
    ]
    env = {**os.environ, "PYTHONPATH": str(checkout / "src")}
    return subprocess.run(command, capture_output=True, text=True, env=env, cwd=work, timeout=900)


def test_a_stage_written_as_one_home_and_one_rule_file_runs_through_snakemake(tmp_path):
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    checkout = _checkout_with_stage(tmp_path)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    assert "centroid" not in config and "do_centroid" not in config["pipeline"]
    make_demo(Config.from_dict(config), tmp_path / "rec", frames=4)
    config["recordings"] = [{"path": "rec", "import": demo_import_spec(Config.from_dict(config))}]
    config["pipeline"] |= {"do_bundle_adjustment": False, "do_visualization": False}

    run = _run(checkout, tmp_path, config)
    assert run.returncode == 0, run.stderr[-3000:]
    out = tmp_path / "rec" / "flylib_outputs"
    with open(out / "centroid.csv") as file:
        rows = list(csv.reader(file))
    assert rows[0] == ["x", "y", "z"] and len(rows) == 5
    from flylib.results import PoseResult

    expected = np.round(np.nanmean(PoseResult.load(out / "results.h5").pts3d, axis=1), 3)
    np.testing.assert_array_equal(np.array(rows[1:], dtype=float), expected)
    # by hand, the shared script runs it from the config and the files by their rule names
    by_hand = subprocess.run(
        [
            sys.executable,
            str(checkout / "scripts" / "stage.py"),
            *("--rule", "centroid", "--config", str(tmp_path / "config.yaml")),
            *("--file", f"results={out / 'results.h5'}", "--file", f"table={tmp_path / 'h.csv'}"),
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(checkout / "src")},
    )
    assert by_hand.returncode == 0, by_hand.stderr[-2000:]
    assert (tmp_path / "h.csv").read_text() == (out / "centroid.csv").read_text()

    # its knob re-runs it alone; its table is checked by its params class before any work
    config["centroid"] = {"decimals": 1}
    dry = _run(checkout, tmp_path, config, "--dry-run")
    assert dry.returncode == 0, dry.stderr[-3000:]
    assert "rule centroid:" in dry.stdout and "rule assemble:" not in dry.stdout
    config["centroid"] = {"decimals": -1}
    bad = _run(checkout, tmp_path, config, "--dry-run")
    assert bad.returncode == 1 and "centroid.decimals" in bad.stderr, bad.stderr[-2000:]
    config["centroid"] = {"decimal": 1}
    bad = _run(checkout, tmp_path, config, "--dry-run")
    assert bad.returncode == 1 and "centroid.decimal" in bad.stderr, bad.stderr[-2000:]
    # its toggle turns it off: nothing left to do
    del config["centroid"]
    config["pipeline"]["do_centroid"] = False
    off = _run(checkout, tmp_path, config, "--dry-run")
    assert off.returncode == 0 and "Nothing to be done" in off.stdout + off.stderr, off.stderr
