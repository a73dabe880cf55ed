"""Planning a batch scales with the batch (issue 37, "Batches of 10,000").

A ``snakemake -n`` over 10,000 recordings never finished: the outdir wildcard
constraint listed every recording's output folder, so each rule's output pattern
(which Snakemake scans for every job it makes and matches against every file) grew
with the batch, and each job recomputed its rule's runtime options from the config.
These tests check the structure, not the clock: the patterns are the same for 2 and
for 12 recordings, per-rule values are computed once per rule, and a file in a folder
that no recording writes to is still read as it is (what the constraint was for).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import pytest
import yaml

from workflow_run import REPO

pytestmark = pytest.mark.slow


def _batch(root: Path, count: int) -> dict:
    """A config over ``count`` recordings: one demo recording hard-linked ``count``
    times, 2D imported per recording from its DeepLabCut CSVs."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_files, demo_import_spec, make_demo

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg = Config.from_dict(config)
    template = root / "template"
    if not template.is_dir():
        make_demo(cfg, template, frames=2)
    names = demo_files(cfg)
    entries = []
    for i in range(count):
        rec = root / f"rec{i:02d}"
        if not rec.is_dir():
            rec.mkdir()
            for name in (*names["footage"], *names["dlc"]):
                os.link(template / name, rec / name)
        entries.append({"path": str(rec), "import": demo_import_spec(cfg)})
    return {**config, "recordings": entries}


@contextlib.contextmanager
def _workflow(workdir: Path, config: dict):
    """The parsed workflow (Snakemake's API, in this process) over ``config``."""
    from snakemake.api import SnakemakeApi
    from snakemake.settings.types import ConfigSettings, OutputSettings, ResourceSettings

    (workdir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    with SnakemakeApi(OutputSettings(quiet={"all"})) as api:
        yield api.workflow(
            resource_settings=ResourceSettings(cores=1),
            config_settings=ConfigSettings(
                configfiles=[workdir / "config.yaml"], replace_workflow_config=True
            ),
            snakefile=REPO / "Snakefile",
            workdir=workdir,
        )


def _patterns(workdir: Path, config: dict) -> dict[str, list[str]]:
    """Every rule's output, log and benchmark patterns as Snakemake holds them."""
    with _workflow(workdir, config) as workflow:
        return {
            rule.name: [str(f) for f in (*rule.output, *rule.log, rule.benchmark) if f]
            for rule in workflow._workflow.rules
        }


def test_output_patterns_do_not_grow_with_the_batch(tmp_path):
    (tmp_path / "two").mkdir()
    (tmp_path / "twelve").mkdir()
    two = _patterns(tmp_path / "two", _batch(tmp_path, 2))
    twelve = _patterns(tmp_path / "twelve", _batch(tmp_path, 12))
    assert two == twelve
    assert not any(str(tmp_path) in p for patterns in twelve.values() for p in patterns)


def test_runtime_options_are_computed_once_per_rule_not_per_job(tmp_path, monkeypatch):
    from snakemake.settings.types import DAGSettings

    import flylib.pipeline.planning as planning

    calls: list[str] = []
    original = planning.stage_runtime

    def counted(config, stage):
        calls.append(stage)
        return original(config, stage)

    # where RunPlan looks it up (patching flylib.pipeline.inputs misses it once planning
    # has been imported by an earlier test)
    monkeypatch.setattr(planning, "stage_runtime", counted)
    with _workflow(tmp_path, _batch(tmp_path, 6)) as workflow:
        workflow.dag(DAGSettings()).execute_workflow(executor="dryrun")
        rules = {rule.name for rule in workflow._workflow.rules}
    assert {"pose2d", "assemble"} <= set(calls)  # the 42 jobs did ask for them
    assert len(calls) == len(set(calls)) <= len(rules)


def test_calibration_file_in_another_runs_output_folder_is_read_not_made(tmp_path):
    """A rig file named like assemble's output, in a folder no recording of this run
    writes to (another run's outputs): an input of this run, never a job's output."""
    from flylib.config import Config
    from flylib.interop.anipose import write_anipose_toml
    from flylib.pipeline.planning import config_rig
    from tests.workflow.test_workflow import planned

    config = _batch(tmp_path, 2)
    config["pipeline"]["do_visualization"] = False
    rig_file = tmp_path / "reference" / "flylib_outputs" / "calibration.toml"
    rig_file.parent.mkdir(parents=True)
    cfg = Config.from_dict(config)
    write_anipose_toml(config_rig(cfg, {v: (480, 960) for v in cfg.view_names()}), rig_file)
    config["calibration"] = {"file": str(rig_file), "format": "anipose"}
    stages = ("pose2d", "bundle_adjustment", "triangulation", "refinement", "assemble")
    assert planned(tmp_path, config) == {
        (stage, rec) for stage in (*stages, "kinematics") for rec in ("rec00", "rec01")
    }


def test_a_dry_run_finds_each_recordings_import_files_once(tmp_path, monkeypatch):
    """Issue 38: the pose2d rule's inputs are the import files the run's preflight
    found, not looked up again per job (a 1,000-recording dry run paid for it twice)."""
    from snakemake.settings.types import DAGSettings

    import flylib.interop.importer as importer

    found: list[Path] = []
    original = importer.import_files

    def counted(target, spec, recording_dir):
        found.append(Path(recording_dir))
        return original(target, spec, recording_dir)

    monkeypatch.setattr(importer, "import_files", counted)
    with _workflow(tmp_path, _batch(tmp_path, 6)) as workflow:
        workflow.dag(DAGSettings()).execute_workflow(executor="dryrun")
    assert len(found) == 6 == len(set(found))


def test_the_slurm_profile_submits_one_job_per_recording(tmp_path):
    """Issue 38: through profiles/slurm each recording's jobs are one group job (imported
    2D included): 3 recordings, 3 submissions, where every job was one before (21).
    tests/workflow/test_slurm.py counts the real sbatch calls on a SLURM cluster."""
    import re
    import subprocess

    from workflow_run import snakemake_command

    (tmp_path / "config.yaml").write_text(yaml.safe_dump(_batch(tmp_path, 3), sort_keys=False))
    cmd = [*snakemake_command(tmp_path), "--profile", str(REPO / "profiles" / "slurm"), "-n"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text[-3000:]
    groups = re.findall(r"^\[[^\]]*\] Group job recording", text, re.M)
    alone = [r for r in re.findall(r"^rule (\w+):", text, re.M) if r != "all"]
    assert (len(groups), alone) == (3, []), text[-3000:]


def test_the_cluster_guides_archive_recipe_plans_every_recording_once(tmp_path):
    """docs/guides/cluster.md, "An archive of 10,000 recordings": its script, run as
    written on a sheet of 5 recordings in parts of 2 (each part's `snakemake` a dry
    run), plans each recording in exactly one part."""
    import re
    import subprocess

    from workflow_run import demo_batch, snakemake_command

    guide = (REPO / "docs" / "guides" / "cluster.md").read_text()
    section = guide.split("## An archive of 10,000 recordings")[1].split("\n## ")[0]
    script = re.search(r"```sh\n(.*?)```", section, re.S).group(1)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    sheet = demo_batch(tmp_path / "batch", 5, config)
    (tmp_path / "archive.tsv").write_text(sheet.read_text())
    (tmp_path / "config.yaml").write_text(
        yaml.safe_dump({**config, "outdir": "results/{id}"}, sort_keys=False)
    )
    script = script.replace("rows=1000", "rows=2")
    dry_run = " ".join(snakemake_command(tmp_path, "--dry-run"))
    assert ".venv/bin/snakemake --profile profiles/slurm" in script
    script = script.replace(".venv/bin/snakemake --profile profiles/slurm", dry_run)
    proc = subprocess.run(
        ["bash", "-euc", script], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "parts").iterdir()) == [
        "part_000.tsv",
        "part_001.tsv",
        "part_002.tsv",
    ]
    planned = re.findall(r"rule pose2d:.*?wildcards: outdir=results/(rec\d+)", proc.stdout, re.S)
    assert sorted(planned) == [f"rec{i:05d}" for i in range(5)], proc.stdout[-3000:]
