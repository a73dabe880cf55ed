"""The README's and the documentation site's statements that quote behaviour or figures,
checked against flylib: the outputs table, the commands in their code blocks, the messages
they quote, and the DeepFly3D sample's bundle-adjustment figure."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest

from flylib.config import Config, validate_config
from flylib.kinematics import FILES as KINEMATICS_FILES
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.preflight import preflight_problems
from flylib.recordings import Recording
from flylib.results.artifacts import SUMMARY_FILES
from flylib.visualization.specs import video_specs

REPO = Path(__file__).resolve().parents[2]
README = (REPO / "README.md").read_text()
#: The README and every page of the site (``docs/``): where the quoted messages live.
DOCS = "\n".join([README, *(p.read_text() for p in sorted((REPO / "docs").rglob("*.md")))])


def section(title: str) -> str:
    start = README.index(title)
    end = README.find("\n## ", start + 1)
    return README[start : end if end > 0 else None]


def code_blocks(language: str = "bash") -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", DOCS, re.S)


def test_the_outputs_table_lists_every_file_a_run_writes_per_recording():
    table = section("## What a run produces")
    videos = [v.name + ".mp4" for v in video_specs(Config.default())]
    for name in ["results.h5", "config.yaml", *SUMMARY_FILES, *KINEMATICS_FILES, *videos]:
        assert f"`{name}`" in table, name


#: The system's own commands a page may show (the cluster's, and a log's last line).
SYSTEM_COMMANDS = ("squeue ", "sacct ", "scancel ", "grep ", "tail ", "git clone ")  # + the sample


def test_every_command_in_a_code_block_runs_from_the_venv_or_is_a_set_up_script():
    for block in code_blocks():
        for line in block.strip().replace("\\\n", " ").splitlines():
            command = line.split("#")[0].strip()
            for part in filter(None, (p.strip() for p in re.split(r"&&|\|\|", command))):
                assert part.startswith((".venv/bin/", "bash ", *SYSTEM_COMMANDS)), line


def test_the_bare_command_note_is_said_once():
    assert README.count("source .venv/bin/activate") == 1


def test_the_nwb_example_writes_into_the_demo_outputs_not_the_checkout():
    (line,) = [b for b in code_blocks() if "--nwb" in b]
    target = Path(re.search(r"--nwb (\S+)", line).group(1))
    assert target.parts[:2] == ("demo", "flylib_outputs")  # git-ignored output directory
    assert "/demo/" in (REPO / ".gitignore").read_text().splitlines()


def test_the_quoted_misspelled_key_message_is_what_validation_says():
    quoted = re.search(r"`(triangulation\.methd: unknown parameter; [^`]*)`", DOCS).group(1)
    data = copy.deepcopy(Config.default().data)
    data["triangulation"]["methd"] = "dlt"
    (problem,) = validate_config(data)
    assert problem.startswith(quoted.removesuffix("...)"))


def test_the_quoted_import_file_message_is_what_validation_says(tmp_path):
    quoted = re.search(r"`(pose2d\.import\.files: /data/fly7: [^`]*)`", DOCS).group(1)
    (tmp_path / "df3d_result_2d.pkl").write_bytes(b"")
    config = Config.default()
    rec = Recording(
        id="fly7",
        path=tmp_path,
        sources={},
        outdir=tmp_path / "out",
        import_spec={"format": "deepfly3d", "files": "df3d_result.pkl"},
    )
    (problem,) = preflight_problems(config, [rec], config.stage_flags())
    assert problem.replace(str(tmp_path), "/data/fly7").startswith(quoted.removesuffix(" ..."))


def test_the_quoted_weights_message_is_what_validation_says(tmp_path, monkeypatch):
    quoted = re.search(r"`invalid config: config/config\.yaml: (pose2d\.models[^`]*)`", DOCS)
    head = quoted.group(1).split(" (")[0]  # up to the machine's own cache path
    tail = ", or set pose2d.weights: {deepfly2d: /path/to/the/file}"
    assert quoted.group(1).endswith(tail)
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path))
    data = copy.deepcopy(Config.default().data)
    data["pose2d"]["models"][0]["url"] = "http://127.0.0.1:9/sh8.tar"  # refused at once
    config = Config.from_dict(data)
    rec = Recording(id="r", path=tmp_path, sources={"vid_rh": [tmp_path]}, outdir=tmp_path)
    (problem,) = preflight_problems(config, [rec], config.stage_flags())
    assert problem.startswith(head) and problem.endswith(tail)
    assert f"put it at {tmp_path / 'sh8_deepfly.tar'}" in problem


def test_the_nothing_to_do_heading_is_the_workflows():
    heading = re.search(r"headed `([^`]*)`", DOCS).group(1)
    assert f'"\\n{heading}\\n"' in (REPO / "workflow" / "rules" / "summary.smk").read_text()


@pytest.mark.slow
def test_the_deepfly3d_sample_bundle_adjustment_figure(df3d_sample_dir, df3d_pickle, tmp_path):
    import json

    from flylib.pipeline.bundle_adjustment import run_bundle_adjustment
    from flylib.pipeline.pose2d import run_pose2d
    from flylib.results import read_stage

    quoted = float(re.search(r"the fit reaches (\d+\.\d+) px", DOCS).group(1))
    config = Config.default()
    spec = {"format": "deepfly3d", "files": df3d_pickle.name}
    run_pose2d(
        stage_inputs(config, "pose2d"), df3d_sample_dir, tmp_path / "pose2d.h5", import_spec=spec
    )
    with pytest.warns(RuntimeWarning, match="poorly determined"):  # the README says it warns
        run_bundle_adjustment(
            stage_inputs(config, "bundle_adjustment"), tmp_path / "pose2d.h5", tmp_path / "ba.h5"
        )
    summary = json.loads(read_stage(tmp_path / "ba.h5", "bundle_adjustment")["attrs"]["summary"])
    assert summary["report"]["final_median_px"] == pytest.approx(quoted, abs=0.02)
