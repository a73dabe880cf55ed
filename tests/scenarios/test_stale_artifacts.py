"""An artifact made under other settings is never used (issue 45): a job of a killed
run that was suspended finishes after a new run with another setting and replaces a
stage artifact with its old-setting result. The next run refuses it in one line and
sets it aside instead of assembling a mix; the run after makes it again;
``flylib inspect --verify`` names it."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
import yaml

from flylib.config import Config
from flylib.pipeline.demo import demo_import_spec, make_demo
from flylib.pipeline.planning import params_of
from flylib.provenance import params_hash, provenance_report
from flylib.results import read_meta
from tests.scenarios.lab import env

from workflow_run import REPO, snakemake_command

pytestmark = pytest.mark.slow


def _run(root, *args):
    return subprocess.run(
        snakemake_command(root, *args), cwd=root, env=env(), capture_output=True, text=True
    )


def _verify(results):
    return subprocess.run(
        [sys.executable, "-m", "flylib.cli", "inspect", "--verify", str(results)],
        env=env(),
        capture_output=True,
        text=True,
    )


def test_a_late_writers_artifact_of_other_settings_is_refused_named_and_made_again(tmp_path):
    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    data["bundle_adjustment"]["max_nfev"] = 20
    cfg = Config.from_dict(data)
    make_demo(cfg, tmp_path / "fly", frames=6, seed=0)
    data["recordings"] = [{"path": str(tmp_path / "fly"), "import": demo_import_spec(cfg)}]
    out = tmp_path / "fly" / "flylib_outputs"
    artifact, results = out / "stages" / "refinement.h5", out / "results.h5"

    # the earlier run, with another setting: its refinement is the late writer's result
    (tmp_path / "config.yaml").write_text(
        yaml.safe_dump({**data, "refinement": {**data["refinement"], "smooth_weight": 3.0}})
    )
    first = _run(tmp_path)
    assert first.returncode == 0, first.stderr[-4000:]
    late = shutil.copy(artifact, tmp_path / "late_refinement.h5")
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    second = _run(tmp_path)
    assert second.returncode == 0, second.stderr[-4000:]
    config = Config.from_file(tmp_path / "config.yaml")
    expected = params_hash(params_of(config)("refinement"))
    stale = read_meta(late)["params_sha256"]
    assert read_meta(artifact)["params_sha256"] == expected != stale

    shutil.copy(late, artifact)  # the suspended job finishes: newer than results.h5
    verify = _verify(results)
    assert verify.returncode == 1
    assert f"{artifact}: made with other refinement settings (params {stale})" in verify.stderr

    third = _run(tmp_path)
    said = third.stdout + third.stderr
    assert third.returncode == 1, said[-4000:]
    refused = [line for line in said.splitlines() if f"{artifact}: made with other" in line]
    assert refused and "re-run the workflow" in refused[0], said[-4000:]
    assert not artifact.exists() and (out / "stages" / f"refinement.stale-{stale}.h5").is_file()
    # nothing was assembled from it
    assert (
        not results.exists()
        or read_meta(results)["upstream_params_sha256"]["refinement"] == expected
    )

    fourth = _run(tmp_path)
    assert fourth.returncode == 0, fourth.stderr[-4000:]
    assert read_meta(artifact)["params_sha256"] == expected
    rows = provenance_report(results, params_of(config))
    assert all(row.status == "ok" for row in rows), rows
    assert _verify(results).returncode == 0
