"""The ``flylib`` console script: inspect, export, calibration."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml

from flylib.camera.rig import CameraGroup
from flylib.cli import main
from flylib.config import Config
from flylib.interop import import_points2d, load_calibration, read_anipose_toml
from flylib.pipeline.inputs import stage_params
from flylib.pipeline.planning import config_rig, params_of
from flylib.pipeline.pose2d import import_target
from flylib.provenance import PARAMS_KEY, params_hash, provenance_report
from flylib.results import PoseResult, summarize_results
from flylib.skeleton import Skeleton

REPO = Path(__file__).resolve().parents[1]
VIEWS = ["a", "b", "c"]


@pytest.fixture
def result_file(tmp_path):
    """A small results.h5: 3 cameras, 5 frames, a 3-point chain, one point lost in frame 2."""
    skeleton = Skeleton(
        point_names=("p0", "p1", "p2"), limbs={"leg": ("p0", "p1", "p2")}, palette={}, name="t"
    )
    angles = np.deg2rad([-30.0, 0.0, 30.0])
    rvecs = np.stack([[0.0, a, 0.0] for a in angles])
    cameras = CameraGroup.from_arrays(
        VIEWS,
        rvecs,
        np.tile([0.0, 0.0, 20.0], (3, 1)),
        np.tile([800.0, 810.0, 320.0, 240.0], (3, 1)),
        np.tile([0.01, 0.0, 0.0, 0.0, 0.0], (3, 1)),
    )
    t = np.arange(5, dtype=float)
    pts3d = np.stack(
        [
            np.stack([t * 0.1, np.zeros(5), np.zeros(5)], -1),
            np.stack([t * 0.1 + 1.0, np.zeros(5), np.zeros(5)], -1),
            np.stack([t * 0.1 + 1.0, 2.0 + 0.5 * (t == 4), np.zeros(5)], -1),
        ],
        axis=1,
    )
    pts3d[2, 1] = np.nan
    pts2d = cameras.project(np.nan_to_num(pts3d))
    pts2d[:, 2, 1] = np.nan
    err = np.where(np.isfinite(pts2d).all(-1), 0.5, np.nan)
    err[0, :, 0] = 1.5
    conf = np.where(np.isfinite(pts2d).all(-1), 0.75, np.nan)
    result = PoseResult(
        cameras=cameras,
        skeleton=skeleton,
        pts2d=pts2d,
        conf=conf,
        pts3d=pts3d,
        reproj_error=err,
        image_sizes={v: (480, 640) for v in VIEWS},
    )
    path = tmp_path / "results.h5"
    result.save(path)
    return path, result


def test_summary_figures(result_file):
    path, _ = result_file
    summary = summarize_results(path)
    assert [s["stage"] for s in summary["stages"]] == ["pose2d", "triangulation"]
    tri = summary["stages"][1]
    assert tri["frames"] == 5 and tri["reconstructed"] == pytest.approx(14 / 15)
    points = {p["point"]: p for p in summary["points"]}
    assert points["p1"]["reconstructed"] == pytest.approx(0.8)
    assert points["p0"]["err_median"] == pytest.approx(0.5) and points["p0"][
        "err_p95"
    ] == pytest.approx(1.5)
    bones = {b["bone"]: b for b in summary["bones"]}
    assert bones["p0-p1"]["median_length"] == pytest.approx(1.0) and bones["p0-p1"][
        "spread"
    ] == pytest.approx(0.0)
    assert bones["p1-p2"]["frames"] == 4  # p1 lost in frame 2
    # lengths 2, 2, 2.5 over frames 0, 1, 3, 4 -> IQR 0.125 over median 2
    assert bones["p1-p2"]["spread"] == pytest.approx(0.0625)


def test_inspect_prints_tables(result_file, capsys):
    path, _ = result_file
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    for text in ("triangulation", "pose2d", "p0-p1", "p2"):
        assert text in out
    # fractions as percentages, like the end-of-run table: 14 of 15 points reconstructed
    assert re.search(r"^triangulation +3 +5 +93\.3% +93\.3% ", out, re.M), out
    assert re.search(r"^p1 +\S+ +80\.0% ", out, re.M), out


def test_inspect_provenance_covers_refinement(result_file, tmp_path, capsys):
    path, _ = result_file
    default = REPO / "config" / "config.yaml"
    config = Config.from_file(default)
    own = params_hash(stage_params(config, "refinement"))
    with h5py.File(path, "a") as f:  # what assemble copies from stages/refinement.h5
        f.create_group("refinement").attrs["meta"] = json.dumps({PARAMS_KEY: own})
    rows = {row.stage: row for row in provenance_report(path, params_of(config))}
    assert rows["refinement"].status == "ok" and rows["refinement"].recorded == own
    edited = tmp_path / "edited.yaml"
    edited.write_text(default.read_text().replace("scale_px: 3.0", "scale_px: 2.0", 1))
    assert edited.read_text() != default.read_text()
    assert main(["inspect", str(path), "--config", str(edited)]) == 2
    captured = capsys.readouterr()
    assert re.search(rf"^refinement +{own} +[0-9a-f]{{16}} +stale$", captured.out, re.M)
    assert f"{path}: refinement is stale" in captured.err


def test_export_writes_3d_and_dlc_csv_that_import_back(result_file, tmp_path, capsys):
    path, result = result_file
    csv3d, dlc_dir = tmp_path / "out" / "points3d.csv", tmp_path / "dlc"
    assert main(["export", str(path), "--csv3d", str(csv3d), "--dlc-dir", str(dlc_dir)]) == 0
    table = pd.read_csv(csv3d)
    assert len(table) == 5
    assert table.loc[2, ["p1_x", "p1_y", "p1_z", "p1_error", "p1_score"]].isna().all()
    np.testing.assert_allclose(
        table[["p2_x", "p2_y", "p2_z"]].to_numpy(), result.pts3d[:, 2], atol=0
    )
    assert table.loc[0, "p0_error"] == pytest.approx((1.5 + 0.5 + 0.5) / 3)
    config = {"cameras": {v: {} for v in VIEWS}, "skeleton": {"point_names": ["p0", "p1", "p2"]}}
    back = import_points2d(
        import_target(Config.from_dict(config)),
        dlc_dir,
        {"format": "dlc_csv", "image_size": [480, 640]},
    )
    np.testing.assert_array_equal(back.pts2d, result.pts2d)
    np.testing.assert_array_equal(back.conf, result.conf)


def test_calibration_writes_reusable_anipose_toml(result_file, tmp_path):
    path, result = result_file
    toml = tmp_path / "rig.toml"
    assert main(["calibration", str(path), "-o", str(toml)]) == 0
    assert read_anipose_toml(toml)["a"]["size"] == (640, 480)
    cams = load_calibration({"file": str(toml)}, VIEWS)
    pts = np.random.default_rng(0).uniform(-1, 1, size=(7, 3))
    np.testing.assert_allclose(cams.project(pts), result.cameras.project(pts), rtol=0, atol=1e-9)


def test_errors_are_one_line_exit_1(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "missing.h5")]) == 1
    err = capsys.readouterr().err.strip()
    assert "missing.h5" in err and "\n" not in err
    assert main(["export", str(tmp_path / "missing.h5")]) == 1
    assert "nothing to do" in capsys.readouterr().err


def test_inspect_prints_aligned_plain_text_and_imports_no_optional_package(
    result_file, capsys, monkeypatch
):
    import sys

    monkeypatch.setitem(sys.modules, "rich", None)  # importing it would now fail loudly
    monkeypatch.setitem(sys.modules, "rich.console", None)
    path, _ = result_file
    assert main(["inspect", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    header = next(line for line in lines if line.startswith("stage "))
    row = next(line for line in lines if line.startswith("triangulation "))
    # no held-out accuracy in this hand-made file: "-" under both held-out columns
    assert row.split() == ["triangulation", "3", "5", "93.3%", "93.3%", "0.5", "1.5", "-", "-", "-"]
    assert len(header) == len(row)  # columns aligned under their headers


def test_inspect_into_a_closed_pipe_exits_quietly(result_file):
    """`flylib inspect results.h5 | head -2`: no traceback, the SIGPIPE status."""
    import subprocess
    import sys
    from pathlib import Path

    path, _ = result_file
    src = str(Path(__file__).resolve().parents[1] / "src")
    code = f"import sys; sys.path.insert(0, {src!r}); from flylib.cli import main; sys.exit(main())"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "inspect", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()  # the reader is gone before the first line is written
    err = proc.stderr.read().decode()
    proc.wait(timeout=120)
    assert err == ""
    assert proc.returncode == 141


# -- flylib run: a config file never runs code; TOML for snakemake (issue 37, cases 7, 8) --

REPO = Path(__file__).resolve().parents[1]


def _flylib(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """The real ``flylib`` console script, importing this checkout."""
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    flylib = Path(sys.executable).with_name("flylib")
    return subprocess.run(
        [str(flylib), *args], cwd=cwd, capture_output=True, text=True, env=env, timeout=300
    )


@pytest.mark.slow  # runs Snakemake
def test_flylib_run_refuses_templating_and_never_runs_it(tmp_path):
    marker = tmp_path / "MARKER"
    (tmp_path / "yte.yaml").write_text(
        f"__use_yte__: true\ntriangulation:\n  ransac_threshold: ?open({str(marker)!r}, 'w') and 3\n"
    )
    proc = _flylib(tmp_path, "run", "yte.yaml", "-s", str(REPO / "Snakefile"), "-n", "--cores", "1")
    assert proc.returncode == 1
    assert proc.stderr.strip() == (
        "flylib run: invalid config: yte.yaml: __use_yte__: templating is not accepted in a "
        "flylib config (Snakemake runs the Python inside such a file while reading it, before "
        "flylib can check it); remove __use_yte__ and write the values out"
    )
    assert not marker.exists() and not (tmp_path / ".flylib").exists()
    # the control: Snakemake itself, given the file, runs its Python
    snakemake = Path(sys.executable).with_name("snakemake")
    subprocess.run(
        [str(snakemake), "-s", str(REPO / "Snakefile"), "-n", "--configfile", "yte.yaml"],
        cwd=tmp_path,
        capture_output=True,
        env=dict(os.environ, PYTHONPATH=str(REPO / "src")),
        timeout=300,
    )
    assert marker.exists()


@pytest.mark.slow  # runs Snakemake
@pytest.mark.parametrize("name", ["my.yaml", "my.toml"])
def test_flylib_run_hands_snakemake_a_checked_plain_copy(tmp_path, name):
    text = "outdir: 'res/{id}'\n" if name.endswith(".yaml") else "outdir = 'res/{id}'\n"
    (tmp_path / name).write_text(text)
    proc = _flylib(tmp_path, "run", name, "-s", str(REPO / "Snakefile"), "-n", "--cores", "1")
    assert proc.returncode == 0, proc.stderr
    (copy,) = (tmp_path / ".flylib" / "run-configs").iterdir()
    assert yaml.safe_load(copy.read_text()) == {"outdir": "res/{id}"}
    assert f"flylib run: {name} checked; snakemake reads .flylib/run-configs/{copy.name}" in (
        proc.stderr
    )
    assert "res/demo/stages" in proc.stdout  # Snakemake planned with the copy's outdir
    assert "This was a dry-run" in proc.stdout and not (tmp_path / "res").exists()


def test_flylib_run_takes_no_configfile_of_snakemakes(tmp_path):
    (tmp_path / "my.yaml").write_text("{}\n")
    proc = _flylib(tmp_path, "run", "my.yaml", "-n", "--configfile", "other.yaml")
    assert proc.returncode == 1
    assert proc.stderr.strip() == (
        "flylib run: --configfile would hand Snakemake a file flylib did not check; list every "
        "config file before the snakemake arguments: flylib run a.yaml b.yaml [snakemake args]"
    )


@pytest.mark.slow  # runs Snakemake
def test_a_toml_config_is_named_as_such_with_its_yaml_equivalent(tmp_path):
    default = str(REPO / "config" / "config.yaml")
    (tmp_path / "my.toml").write_text('[triangulation]\nmethod = "dlt"\n')
    snakemake = Path(sys.executable).with_name("snakemake")
    proc = subprocess.run(
        [str(snakemake), "-s", str(REPO / "Snakefile"), "-n", "--configfile", "my.toml"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert (
        "Config file is not valid JSON or YAML" in proc.stdout + proc.stderr
    )  # no flylib code ran
    check = _flylib(tmp_path, "check-config", default, "my.toml")
    assert check.returncode == 0, check.stderr
    assert check.stderr.strip() == (
        'my.toml: TOML, which `snakemake --configfile` cannot read (it stops with "Config file '
        'is not valid JSON or YAML"); run it with `flylib run my.toml [snakemake args]`, or '
        f"write its YAML equivalent with `flylib check-config {default} my.toml --to-yaml my.yaml`"
    )
    convert = _flylib(tmp_path, "check-config", default, "my.toml", "--to-yaml", "my.yaml")
    assert convert.returncode == 0 and convert.stdout.strip() == (
        "my.toml: valid; written as YAML to my.yaml"
    )
    assert yaml.safe_load((tmp_path / "my.yaml").read_text()) == {
        "triangulation": {"method": "dlt"}
    }
    again = _flylib(tmp_path, "check-config", default, "my.toml", "--to-yaml", "my.yaml")
    assert again.returncode == 1 and again.stderr.strip() == (
        "flylib check-config: my.yaml: already exists; choose another name or delete it"
    )
    proc = subprocess.run(
        [str(snakemake), "-s", str(REPO / "Snakefile"), "-n", "--configfile", "my.yaml"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO / "src")),
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr


def test_inspect_judges_the_handedness_of_a_file_assembled_without_a_verdict(tmp_path, capsys):
    """Issue 36: a results.h5 from before the check still gets a handedness line."""
    from flylib.demo import synthetic_fly
    from flylib.handedness import WORLD_MIRROR
    from flylib.results import PoseResult

    config = Config.default()
    rig = config_rig(config, image_sizes={v: (480, 960) for v in config.view_names()})
    for name, pts3d in (("fly", synthetic_fly(10)), ("mirror", synthetic_fly(10) @ WORLD_MIRROR)):
        path = tmp_path / f"{name}.h5"
        PoseResult(
            cameras=rig, skeleton=config.skeleton(), pts2d=rig.project(pts3d), pts3d=pts3d
        ).save(path)
        assert summarize_results(path)["handedness"]["verdict"] == (
            "right-handed" if name == "fly" else "mirrored"
        )
        main(["inspect", str(path)])
        out = capsys.readouterr().out
        expected = "handedness: right-handed: " if name == "fly" else "handedness: mirrored: "
        assert expected in out


def test_export_and_inspect_help_say_which_2d_and_what_verify_checks(capsys):
    """Issue 36 (7): `--help` says the DLC CSVs are pose2d's detections with the
    corrections applied; `inspect --help` offers --verify."""
    with pytest.raises(SystemExit):
        main(["export", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "pose2d's 2D detections" in text and "manual corrections applied" in text
    assert "not the 2D a 3D stage kept" in text
    with pytest.raises(SystemExit):
        main(["inspect", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--verify" in text and "exit status 1 when one fails" in text
