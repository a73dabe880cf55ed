"""results.h5 never contradicts itself (flylib.results.invariants): the checks catch each
kind of contradiction, and random imports, corrections and stage toggles driven through
the stages and assemble (which refuses a contradicting file) always pass them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from flylib.config import Config
from flylib.corrections import Corrections
from flylib.errors import ResultsError
from flylib.interop.dlc import read_dlc_csv, write_dlc_csv
from flylib.pipeline.assemble import run_assemble
from flylib.pipeline.demo import demo_import_spec, make_demo
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.pose2d import run_pose2d
from flylib.pipeline.refinement import run_refinement
from flylib.pipeline.triangulation import run_triangulation
from flylib.results import (
    Pose2dData,
    PoseResult,
    check_results,
    read_detections,
    require_consistent,
)

FRAMES = 10


def _config(**tables) -> Config:
    data = Config.default().data
    data["pipeline"]["do_bundle_adjustment"] = False
    for table, values in tables.items():
        data[table].update(values)
    return Config.from_dict(data)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A demo recording: its folder, the config, and its DLC CSVs as arrays."""
    directory = tmp_path_factory.mktemp("invariants") / "rec"
    config = _config()
    make_demo(config, directory, frames=FRAMES, seed=3)
    spec = demo_import_spec(config)
    csvs = {view: read_dlc_csv(directory / name) for view, name in spec["files"].items()}
    return directory, config, spec, csvs


def _pose2d(directory: Path, config: Config, spec, out: Path) -> Path:
    """The pose2d stage, importing as ``spec`` says."""
    path = out / "stages" / "pose2d.h5"
    run_pose2d(stage_inputs(config, "pose2d"), directory, path, import_spec=spec)
    return path


def _run(directory: Path, config: Config, spec, out: Path, *, refine: bool, corrections=None):
    """pose2d (import; unless done), triangulation, refinement when asked, assemble:
    results.h5."""
    stages = out / "stages"
    if not (stages / "pose2d.h5").is_file():
        _pose2d(directory, config, spec, out)
    run_triangulation(
        stage_inputs(config, "triangulation"),
        stages / "pose2d.h5",
        stages / "triangulation.h5",
        recording_dir=directory,
        corrections_path=corrections,
    )
    files = {"pose2d": stages / "pose2d.h5", "triangulation": stages / "triangulation.h5"}
    if refine:
        run_refinement(
            stage_inputs(config, "refinement"),
            stages / "pose2d.h5",
            stages / "triangulation.h5",
            stages / "refinement.h5",
            recording_dir=directory,
        )
        files["refinement"] = stages / "refinement.h5"
    run_assemble(stage_inputs(config, "assemble"), files, out, recording_dir=directory)
    return out / "results.h5"


@pytest.fixture(scope="module")
def consistent(demo, tmp_path_factory):
    """A results.h5 with refinement, untouched."""
    directory, config, spec, _ = demo
    out = tmp_path_factory.mktemp("consistent")
    return _run(directory, config, spec, out, refine=True)


def _tampered(path: Path, tmp_path: Path, dataset: str, change) -> Path:
    copy = tmp_path / "results.h5"
    shutil.copy(path, copy)
    with h5py.File(copy, "r+") as f:
        values = f[dataset][()]
        f[dataset][...] = change(values)
    return copy


def test_a_result_the_stages_made_agrees_with_itself(consistent):
    assert check_results(consistent) == []
    require_consistent(consistent)


@pytest.mark.parametrize(
    ("dataset", "change", "invariant"),
    [
        ("/refinement/reproj_error", lambda e: np.where(np.isfinite(e), e + 0.5, e), "differs"),
        ("/refinement/reproj_error", lambda e: np.full_like(e, np.nan), "is NaN where"),
        ("/triangulation/reproj_error", lambda e: e * 1.01, "differs"),
        ("/refinement/points", lambda p: p + 3.0, "differs from the 2D it was solved from"),
        ("/triangulation/points", lambda p: p[:, :, ::-1], "differs from the 2D it was solved"),
        ("/refinement/flags", lambda f: f ^ np.uint8(4), "bit 'missing'"),
    ],
)
def test_each_contradiction_is_one_line_naming_dataset_and_worst_entry(
    consistent, tmp_path, dataset, change, invariant
):
    bad = _tampered(consistent, tmp_path, dataset, change)
    found = check_results(bad)
    assert found and all(v.dataset == dataset for v in found if invariant in v.what)
    (hit,) = [v for v in found if v.dataset == dataset and invariant in v.what]
    assert hit.count > 0 and hit.worst is not None
    line = hit.line(["rf"] * 7, [f"pt{i}" for i in range(38)])
    assert line.startswith(f"{hit.invariant}: {dataset} ") and "\n" not in line
    assert f"frame {hit.worst[-2]}" in line
    with pytest.raises(ResultsError, match="contradicts itself"):
        require_consistent(bad)


def test_the_worst_entry_is_the_one_most_off(consistent, tmp_path):
    with h5py.File(consistent) as f:
        finite = np.argwhere(np.isfinite(f["refinement/reproj_error"][()]))
    small, large = tuple(int(i) for i in finite[3]), tuple(int(i) for i in finite[-5])

    def bump(error):
        error = np.array(error)
        error[small] += 2.0
        error[large] += 40.0
        return error

    bad = _tampered(consistent, tmp_path, "/refinement/reproj_error", bump)
    (hit,) = check_results(bad)
    assert hit.worst == large and hit.count == 2 and hit.amount == pytest.approx(40.0)


def test_inspect_verify_exits_non_zero_with_one_line_per_failed_invariant(consistent, tmp_path):
    cmd = [sys.executable, "-m", "flylib.cli", "inspect", "--verify"]
    ok = subprocess.run([*cmd, str(consistent)], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert "consistent" in ok.stdout
    bad = _tampered(consistent, tmp_path, "/refinement/reproj_error", lambda e: e + 1.0)
    failed = subprocess.run([*cmd, str(bad)], capture_output=True, text=True)
    assert failed.returncode == 1
    lines = failed.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "reprojection: /refinement/reproj_error differs" in lines[0]
    assert "worst by 1 px at view" in lines[0]


def _import(csvs, directory: Path, rng, drop: float) -> dict:
    """The demo's CSVs (each view its own points) rewritten with a fraction ``drop`` of
    the points removed and random likelihoods; returns the import spec reading them."""
    files = {}
    for view, kp in csvs.items():
        gone = rng.random(kp.xy.shape[:2]) < drop
        xy = np.where(gone[..., None], np.nan, kp.xy)
        likelihood = rng.uniform(0.05, 1.0, kp.xy.shape[:2])
        write_dlc_csv(directory / f"{view}_imported.csv", xy, likelihood, list(kp.names), "lab")
        files[view] = f"{view}_imported.csv"
    return {"format": "dlc_csv", "files": files}


@st.composite
def scenarios(draw):
    """An import (dropouts, likelihoods), corrections and stage toggles."""
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    n_edits = draw(st.integers(0, 6))
    n_invisible = draw(st.integers(0, 3))
    n_fixed = draw(st.integers(0, n_edits))
    n_edits3d = draw(st.integers(0, 2))
    return {
        "rng": rng,
        "drop": draw(st.floats(0.0, 0.4)),
        "edits": n_edits,
        "invisible": n_invisible,
        "fixed": n_fixed,
        "edits3d": n_edits3d,
        "offset": draw(st.floats(0.0, 60.0)),
        "refine": draw(st.booleans()),
        "method": draw(st.sampled_from(["ransac", "greedy", "dlt"])),
    }


@pytest.mark.slow
@settings(
    max_examples=10,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(case=scenarios())
def test_random_imports_corrections_and_toggles_never_make_a_contradicting_result(
    demo, tmp_path_factory, case
):
    directory, _, _, csvs = demo
    rng = case["rng"]
    spec = _import(csvs, directory, rng, case["drop"])
    config = _config(triangulation={"method": case["method"]})
    out = tmp_path_factory.mktemp("case")
    detected = Pose2dData.load(_pose2d(directory, config, spec, out)).pts2d
    shape = detected.shape[:3]
    n_points = shape[2]

    corr = Corrections.empty(*shape, source="results.h5")
    seen = np.argwhere(np.isfinite(detected).all(-1))
    picks = seen[rng.permutation(len(seen))[: case["edits"] + case["invisible"]]]
    for i, (v, t, p) in enumerate(picks):
        if i < case["edits"]:
            move = rng.normal(size=2) * case["offset"]
            corr.set_point(int(v), int(t), int(p), detected[v, t, p] + move)
            if i < case["fixed"]:
                corr.fixed[v, t, p] = True
        else:
            corr.set_invisible(int(v), int(t), int(p))
    for _ in range(case["edits3d"]):
        t, p = int(rng.integers(FRAMES)), int(rng.integers(n_points))
        corr.points3d[t, p] = rng.normal(size=3)
        corr.edited3d[t, p] = True
    sidecar = None
    if corr.count():
        sidecar = out / "corrections.h5"
        corr.save(sidecar)

    results = _run(directory, config, spec, out, refine=case["refine"], corrections=sidecar)
    assert check_results(results) == []  # assemble would have refused it otherwise
    result = PoseResult.load(results)
    kept = np.isfinite(result.pts2d).all(-1)
    # the stored 2D at an edited observation is the edit, never the detection
    edited = corr.edited & ~corr.invisible & kept
    np.testing.assert_array_equal(result.pts2d[edited], corr.points[edited])
    assert not (kept & corr.invisible).any()
    # the detections with corrections applied: what the DLC export writes
    det = read_detections(results)
    expect = np.where(corr.touched()[..., None], corr.edited_2d(), detected)
    np.testing.assert_array_equal(det.points, expect)
    assert det.corrected == int(corr.touched().sum())
    with h5py.File(results) as f:
        attrs = json.loads(f["triangulation"].attrs.get("corrections", "null"))
    assert (attrs is None) == (sidecar is None)
