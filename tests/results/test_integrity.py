"""Result integrity: checksums, params hashes, the config snapshot's single
writer, the output-directory lock and writes that run out of space."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from flylib.cli import main as flylib_main
from flylib.config import Config
from flylib.errors import OutputError, ResultsError
from flylib.pipeline.inputs import stage_inputs, stage_params
from flylib.pipeline.planning import config_rig, params_of
from flylib.provenance import params_hash, provenance_report
from flylib.results import (
    Pose2dData,
    PoseResult,
    assemble_results,
    fletcher32,
    read_meta,
    verify_file,
    write_stage,
)

from workflow_run import snakemake_command

REPO = Path(__file__).resolve().parents[2]


def _env() -> dict:
    """Subprocess environment with this checkout's flylib first on the path."""
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]),
    }


# -- Fletcher-32 -----------------------------------------------------------------


def _fletcher32_reference(data: bytes) -> int:
    """HDF5's H5_checksum_fletcher32, transcribed loop for loop (360-word blocks)."""
    words = len(data) // 2
    sum1 = sum2 = 0
    pos = 0
    while words:
        block = min(words, 360)
        words -= block
        for _ in range(block):
            sum1 += (data[pos] << 8) | data[pos + 1]
            pos += 2
            sum2 += sum1
        sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
        sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    if len(data) % 2:
        sum1 += data[pos] << 8
        sum2 += sum1
        sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
        sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
    sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    return (sum2 << 16) | sum1


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\x00" * 10,
        b"\xff" * 1001,
        b"\xff\xff",
        bytes(range(256)) * 9 + b"\x07",
        np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes(),
        np.random.default_rng(1).integers(250, 256, 4321, dtype=np.uint8).tobytes(),  # many carries
    ],
)
def test_fletcher32_matches_hdf5s_algorithm(data):
    assert fletcher32(data) == _fletcher32_reference(data)


def test_fletcher32_matches_the_checksum_hdf5s_own_filter_stores(tmp_path):
    rng = np.random.default_rng(2)
    arr = rng.normal(size=(900, 38, 3))
    with h5py.File(tmp_path / "ref.h5", "w") as f:  # HDF5 filters these chunks itself
        f.create_dataset("x", data=arr, chunks=(300, 38, 3), compression="gzip", fletcher32=True)
        f.create_dataset("y", data=arr[:7, :5], chunks=(7, 5, 3), fletcher32=True)
    with h5py.File(tmp_path / "ref.h5") as f:
        for name, offsets in (("x", [(0, 0, 0), (300, 0, 0), (600, 0, 0)]), ("y", [(0, 0, 0)])):
            for offset in offsets:
                _, raw = f[name].id.read_direct_chunk(offset)
                assert int.from_bytes(raw[-4:], "little") == fletcher32(raw[:-4])


# -- checksums on every dataset, damage detected --------------------------------------


@pytest.fixture(scope="module")
def rig_and_skeleton():
    config = Config.default()
    return (
        config,
        config_rig(config, {v: (480, 960) for v in config.view_names()}),
        config.skeleton(),
    )


def _stage_files(directory: Path, config, skeleton, n_frames: int = 3000) -> dict[str, Path]:
    rng = np.random.default_rng(3)
    pts2d = rng.uniform(0, 900, size=(7, n_frames, 38, 2))
    pts2d[:, :, ::5] = np.nan
    conf = rng.uniform(size=(7, n_frames, 38))
    files = {
        "pose2d": directory / "stages" / "pose2d.h5",
        "triangulation": directory / "stages" / "triangulation.h5",
    }
    Pose2dData(pts2d, conf, config.view_names(), {v: (480, 960) for v in config.view_names()}).save(
        files["pose2d"], skeleton
    )
    write_stage(
        files["triangulation"],
        "triangulation",
        {
            "points": pts2d,
            "points3d": rng.normal(size=(n_frames, 38, 3)),
            "reproj_error": rng.gamma(2.0, 2.0, size=(7, n_frames, 38)),
        },
    )
    return files


@pytest.fixture()
def results(tmp_path, rig_and_skeleton) -> Path:
    config, rig, skeleton = rig_and_skeleton
    files = _stage_files(tmp_path, config, skeleton)
    out = tmp_path / "results.h5"
    # random arrays, not a solved pose: these tests are about damage, not agreement
    assemble_results(out, skeleton=skeleton, config_rig=rig, stage_files=files, verify=False)
    return out


def test_every_dataset_of_artifacts_and_results_carries_a_checksum(results):
    for path in (
        results,
        results.parent / "stages" / "pose2d.h5",
        results.parent / "stages" / "triangulation.h5",
    ):
        with h5py.File(path) as f:
            found: list = []
            f.visititems(
                lambda name, item, found=found: (
                    found.append(item) if isinstance(item, h5py.Dataset) else None
                )
            )
            unchecked = [d.name for d in found if d.size and not d.fletcher32]
            assert found and not unchecked, (path, unchecked)
        assert verify_file(path) == []
    result = PoseResult.load(results)
    assert result.skeleton.point_names[0] == "lf_thorax_coxa" and result.cameras.names[0] == "rh"


def test_inspect_notes_a_file_without_checksums_but_does_not_fail_it(
    tmp_path, rig_and_skeleton, capsys, monkeypatch
):
    from flylib.results import datasets as results_datasets

    config, rig, skeleton = rig_and_skeleton
    monkeypatch.setattr(results_datasets, "FLETCHER32", False)  # as an older flylib wrote it
    PoseResult(rig, skeleton, np.zeros((7, 500, 38, 2)), pts3d=np.zeros((500, 38, 3))).save(
        tmp_path / "old.h5"
    )
    unchecked: list[str] = []
    assert (
        verify_file(tmp_path / "old.h5", unchecked=unchecked) == []
        and "/pose2d/points" in unchecked
    )
    assert flylib_main(["inspect", str(tmp_path / "old.h5")]) == 0
    assert "datasets carry no checksum" in capsys.readouterr().err


def _damage_middle(path: Path, seed: int = 0) -> int:
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    noise = np.random.default_rng(seed).integers(0, 256, 64, dtype=np.uint8).tobytes()
    assert bytes(data[middle : middle + 64]) != noise
    data[middle : middle + 64] = noise
    path.write_bytes(bytes(data))
    return middle


def test_random_bytes_in_the_middle_of_results_fail_to_load_naming_file_and_dataset(
    results, capsys
):
    _damage_middle(results)
    with pytest.raises(ResultsError) as info:
        PoseResult.load(results)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{results}: dataset /") and "is damaged" in message
    assert "Fletcher-32 checksum mismatch in the chunk at (" in message
    assert flylib_main(["inspect", str(results)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err and all(line.startswith(f"flylib inspect: {results}: dataset /") for line in err)


@pytest.mark.parametrize("seed", range(6))
def test_damage_anywhere_is_caught_or_harmless(results, seed):
    """64 random bytes at a random place: the load fails naming the file, or (unused
    bytes of an index node) gives exactly the stored arrays."""
    reference = PoseResult.load(results)
    data = bytearray(results.read_bytes())
    rng = np.random.default_rng(100 + seed)
    at = int(rng.integers(0, len(data) - 64))
    data[at : at + 64] = rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
    results.write_bytes(bytes(data))
    try:
        loaded = PoseResult.load(results)
    except ResultsError as exc:
        assert str(exc).startswith(f"{results}:") and "\n" not in str(exc)
        return
    for name in ("pts2d", "pts3d", "reproj_error", "conf"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(reference, name))


def test_damaged_object_header_is_a_results_error(results):
    with h5py.File(results) as f:
        address = h5py.h5o.get_info(f["triangulation"].id).addr
    data = bytearray(results.read_bytes())
    data[address + 8 : address + 24] = b"\xa5" * 16
    results.write_bytes(bytes(data))
    with pytest.raises(ResultsError, match=rf"^{results}: .* is damaged \(HDF5: .*checksum"):
        PoseResult.load(results)


def test_a_complex_dataset_is_refused_not_cast(results):
    with h5py.File(results, "r+") as f:
        shape = f["triangulation/points3d"].shape
        del f["triangulation/points3d"]
        f["triangulation/points3d"] = np.ones(shape, np.complex128)
    with pytest.raises(ResultsError, match=r"points3d holds complex numbers") as info:
        PoseResult.load(results)
    assert str(info.value).startswith(f"{results}:") and "\n" not in str(info.value)


def test_damaged_stage_artifact_stops_assembly_naming_the_artifact(tmp_path, rig_and_skeleton):
    config, rig, skeleton = rig_and_skeleton
    files = _stage_files(tmp_path, config, skeleton)
    _damage_middle(files["triangulation"])
    with pytest.raises(
        ResultsError, match=rf"^{files['triangulation']}: dataset /triangulation/\w+ is damaged"
    ):
        assemble_results(
            tmp_path / "results.h5", skeleton=skeleton, config_rig=rig, stage_files=files
        )
    assert not (tmp_path / "results.h5").exists()


# -- params hashes ------------------------------------------------------------------


def _small_run(tmp_path: Path, config: Config) -> tuple[Path, Path]:
    """Import the demo's 2D for a 6-frame recording, triangulate, assemble."""
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.demo import demo_import_spec, make_demo
    from flylib.pipeline.pose2d import run_pose2d
    from flylib.pipeline.stage_helpers import run_inputs
    from flylib.pipeline.triangulation import run_triangulation

    recording = tmp_path / "rec"
    make_demo(config, recording, frames=6, seed=0)
    out = recording / "flylib_outputs"
    run_pose2d(
        stage_inputs(config, "pose2d"),
        recording,
        out / "stages" / "pose2d.h5",
        import_spec=demo_import_spec(config),
    )
    run_triangulation(
        run_inputs(config, "triangulation"),
        out / "stages" / "pose2d.h5",
        out / "stages" / "triangulation.h5",
        recording_dir=recording,
    )
    run_assemble(
        stage_inputs(config, "assemble"),
        {
            "pose2d": out / "stages" / "pose2d.h5",
            "triangulation": out / "stages" / "triangulation.h5",
        },
        out,
        recording_dir=recording,
        snapshot_path=out / "config.yaml",
        snapshot_text=config.snapshot_text(),
    )
    return recording, out


def _config(tmp_path: Path, name: str, edit=None) -> Config:
    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    data["pipeline"].update(do_bundle_adjustment=False, do_visualization=False)
    if edit:
        edit(data)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return Config.from_file(path)


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_artifacts_record_the_hash_of_their_params_and_inspect_tells_a_stale_mix(tmp_path, capsys):
    config = _config(tmp_path, "config.yaml")
    recording, out = _small_run(tmp_path, config)
    expected = {
        stage: params_hash(stage_params(config, stage))
        for stage in ("pose2d", "triangulation", "assemble")
    }
    assert read_meta(out / "stages" / "pose2d.h5")["params_sha256"] == expected["pose2d"]
    tri = read_meta(out / "stages" / "triangulation.h5")
    assert tri["params_sha256"] == expected["triangulation"]
    assert tri["upstream_params_sha256"] == {"pose2d": expected["pose2d"]}
    with h5py.File(out / "results.h5") as f:  # results.h5 records each stage's hash
        for stage in ("pose2d", "triangulation"):
            assert json.loads(f[stage].attrs["meta"])["params_sha256"] == expected[stage]
        assert json.loads(f.attrs["meta"])["params_sha256"] == expected["assemble"]
    assert json.loads((out / "summary.json").read_text())["params_sha256"] == expected
    assert (out / "config.yaml").read_bytes() == (tmp_path / "config.yaml").read_bytes()
    assert all(
        row.status == "ok" for row in provenance_report(out / "results.h5", params_of(config))
    )
    assert flylib_main(["inspect", str(out / "results.h5")]) == 0  # against the snapshot beside it
    capsys.readouterr()

    # A config edit, then only triangulation re-runs (the run was interrupted before assemble).
    edited = _config(
        tmp_path, "edited.yaml", lambda d: d["triangulation"].update(ransac_threshold=7.5)
    )
    from flylib.pipeline.stage_helpers import run_inputs
    from flylib.pipeline.triangulation import run_triangulation

    run_triangulation(
        run_inputs(edited, "triangulation"),
        out / "stages" / "pose2d.h5",
        out / "stages" / "triangulation.h5",
        recording_dir=recording,
    )
    rows = {row.stage: row for row in provenance_report(out / "results.h5", params_of(edited))}
    assert rows["triangulation"].status == "stale" and rows["pose2d"].status == "ok"
    assert (
        flylib_main(["inspect", str(out / "results.h5"), "--config", str(tmp_path / "edited.yaml")])
        == 2
    )
    err = capsys.readouterr().err
    assert (
        f"{out / 'results.h5'}: triangulation is stale: made with params {expected['triangulation']}"
        in err
    )
    assert (
        f"{out / 'stages' / 'triangulation.h5'}: params " in err
        and "not assembled from these artifacts" in err
    )

    # pose2d re-made with other params beside a triangulation built on the old one: mixed.
    other = _config(tmp_path, "other.yaml", lambda d: d["pose2d"].update(precision="float32"))
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.demo import demo_import_spec
    from flylib.pipeline.pose2d import run_pose2d

    run_pose2d(
        stage_inputs(other, "pose2d"),
        recording,
        out / "stages" / "pose2d.h5",
        import_spec=demo_import_spec(other),
    )
    run_assemble(
        stage_inputs(other, "assemble"),
        {
            "pose2d": out / "stages" / "pose2d.h5",
            "triangulation": out / "stages" / "triangulation.h5",
        },
        out,
        recording_dir=recording,
    )
    rows = {row.stage: row for row in provenance_report(out / "results.h5")}
    assert rows["triangulation"].status == "mixed"
    assert any("was built from pose2d params" in p for p in rows["triangulation"].problems)


# -- the config snapshot: written by assemble only, after the results ---------------------


def _snakemake(
    workdir: Path, config: dict, *args: str, check: bool = True
) -> subprocess.CompletedProcess:
    (workdir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    cmd = snakemake_command(workdir, *args)
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=600, cwd=workdir, env=_env(), check=False
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}")
    return proc


@pytest.mark.slow
def test_only_assemble_writes_the_config_snapshot_after_the_results(tmp_path):
    from flylib.pipeline.demo import demo_import_spec, make_demo

    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    data["pipeline"].update(do_bundle_adjustment=False, do_visualization=False)
    make_demo(Config.from_dict(data), tmp_path / "rec", frames=6, seed=0)
    data["recordings"] = [
        {"path": str(tmp_path / "rec"), "import": demo_import_spec(Config.from_dict(data))}
    ]
    out = tmp_path / "rec" / "flylib_outputs"
    _snakemake(tmp_path, data)
    first = (tmp_path / "config.yaml").read_bytes()
    assert (out / "config.yaml").read_bytes() == first
    results_before = (out / "results.h5").read_bytes()

    # After an edit, a run stopped before assemble (as an interrupted one is) leaves the
    # old snapshot beside the old results: no other job writes it.
    data["triangulation"]["ransac_threshold"] = 7.5
    _snakemake(tmp_path, data, "--omit-from", "assemble")
    assert read_meta(out / "stages" / "triangulation.h5")["params_sha256"] == params_hash(
        stage_params(Config.from_dict(data), "triangulation")
    )
    assert (out / "config.yaml").read_bytes() == first
    assert (out / "results.h5").read_bytes() == results_before
    assert not list(out.glob(".flylib.lock*"))

    # assemble's completion replaces it, together with the results it describes.
    _snakemake(tmp_path, data)
    assert (out / "config.yaml").read_bytes() == (tmp_path / "config.yaml").read_bytes() != first
    snapshot = Config.from_file(out / "config.yaml")
    assert all(
        row.status == "ok" for row in provenance_report(out / "results.h5", params_of(snapshot))
    )

    # A run from another working directory with another config over the same outdir:
    # its Snakemake has no record of these artifacts; the recorded hashes tell.
    other = tmp_path / "other-workdir"
    other.mkdir()
    data["triangulation"]["ransac_threshold"] = 9.0
    proc = _snakemake(other, data, "--dry-run")
    assert (
        f"{out / 'stages' / 'triangulation.h5'}: written by a run from {tmp_path} on "
        in proc.stderr + proc.stdout
    ), proc.stderr[-3000:]
    assert (
        "pose2d.h5: written by" not in proc.stderr + proc.stdout
    )  # same pose2d params: not foreign


def test_no_stage_script_but_assemble_writes_a_snapshot(tmp_path):
    rules = "\n".join(p.read_text() for p in (REPO / "workflow" / "rules").glob("*.smk"))
    assert "--snapshot-dir" not in rules and rules.count('"{outdir}/config.yaml"') == 1
    writers = [
        p.name for p in sorted((REPO / "scripts").glob("*.py")) if "--snapshot" in p.read_text()
    ]
    assert writers == ["assemble.py"]


def test_foreign_artifacts_are_those_of_another_workdir_with_other_params(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from flylib.provenance import foreign_artifacts

    monkeypatch.chdir(tmp_path)
    config = _config(tmp_path, "config.yaml")
    _, out = _small_run(tmp_path, config)
    recordings = [SimpleNamespace(outdir=out)]
    assert (
        foreign_artifacts(params_of(config, run_only=True), recordings, cwd=tmp_path / "elsewhere")
        == []
    )  # same params
    edited = _config(
        tmp_path, "edited.yaml", lambda d: d["triangulation"].update(ransac_threshold=7.5)
    )
    assert (
        foreign_artifacts(params_of(edited, run_only=True), recordings) == []
    )  # this workdir: Snakemake's own params tracking
    lines = foreign_artifacts(
        params_of(edited, run_only=True), recordings, cwd=tmp_path / "elsewhere"
    )
    assert [line.split(":")[0] for line in lines] == [str(out / "stages" / "triangulation.h5")]
    assert (
        f"written by a run from {tmp_path} on " in lines[0]
        and "--forcerun triangulation" in lines[0]
    )


# -- the output-directory lock -----------------------------------------------------------


_HOLDER = textwrap.dedent("""
    import sys, time
    from flylib.locking import outdir_lock
    with outdir_lock(sys.argv[1], job="triangulation"):
        print("locked", flush=True)
        time.sleep(120)
""")


def _pose2d_for_script(tmp_path: Path) -> tuple[Path, Path]:
    config = _config(tmp_path, "config.yaml")
    from flylib.pipeline.demo import demo_import_spec, make_demo
    from flylib.pipeline.pose2d import run_pose2d

    recording = tmp_path / "rec"
    make_demo(config, recording, frames=6, seed=0)
    out = recording / "flylib_outputs"
    run_pose2d(
        stage_inputs(config, "pose2d"),
        recording,
        out / "stages" / "pose2d.h5",
        import_spec=demo_import_spec(config),
    )
    return recording, out


def test_a_second_writer_of_an_outdir_fails_naming_the_holder_and_a_dead_holder_is_taken_over(
    tmp_path,
):
    recording, out = _pose2d_for_script(tmp_path)
    elsewhere = tmp_path / "other-workdir"
    elsewhere.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(out)],
        cwd=elsewhere,
        env=_env(),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        cmd = [
            sys.executable,
            str(REPO / "scripts" / "triangulation.py"),
            "--config",
            str(tmp_path / "config.yaml"),
            "--pose2d",
            str(out / "stages" / "pose2d.h5"),
            "--recording",
            str(recording),
            "--out",
            str(out / "stages" / "triangulation.h5"),
        ]
        proc = subprocess.run(
            cmd, capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=300, check=False
        )
        assert proc.returncode == 1
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1, proc.stderr
        assert lines[0].startswith(
            f"error: {out}: another run is writing this output directory (pid {holder.pid} on "
        )
        assert f"working directory {elsewhere}, job triangulation" in lines[0]
        assert not (out / "stages" / "triangulation.h5").exists()
    finally:
        holder.send_signal(signal.SIGKILL)  # dies without releasing: a stale lock
        holder.wait()
    assert json.loads((out / ".flylib.lock").read_text())["pid"] == holder.pid
    proc = subprocess.run(
        cmd, capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert (out / "stages" / "triangulation.h5").is_file()
    assert not list(out.glob(".flylib.lock*"))  # released after the job


def test_lock_is_exclusive_between_two_live_processes(tmp_path):
    from flylib.locking import outdir_lock

    elsewhere = tmp_path / "other-workdir"
    elsewhere.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(tmp_path)],
        env=_env(),
        cwd=elsewhere,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        started = time.monotonic()
        with (
            pytest.raises(
                OutputError, match=rf"pid {holder.pid} on .*delete {tmp_path / '.flylib.lock'}$"
            ),
            outdir_lock(tmp_path, job="assemble"),
        ):
            pass
        assert time.monotonic() - started < 5
    finally:
        holder.kill()
        holder.wait()


def test_jobs_of_one_run_share_the_lock_and_only_its_owner_releases_it(tmp_path):
    from flylib.locking import outdir_lock

    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(tmp_path)],
        env=_env(),
        cwd=os.getcwd(),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with outdir_lock(
            tmp_path, job="kinematics"
        ):  # same host and working directory: a sibling job
            pass
        assert json.loads((tmp_path / ".flylib.lock").read_text())["pid"] == holder.pid
    finally:
        holder.kill()
        holder.wait()


# -- out of space ------------------------------------------------------------------------


_WRITE_UNDER_LIMIT = textwrap.dedent("""
    import resource, signal, sys
    from pathlib import Path
    import numpy as np
    from flylib.errors import FlylibError
    from flylib.results import Pose2dData, assemble_results, write_stage
    from flylib.config import Config
    from flylib.pipeline.planning import config_rig

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))

    rng = np.random.default_rng(0)
    config = Config.default()
    target, kind = Path(sys.argv[1]), sys.argv[2]
    try:
        if kind == "stage":
            limit()
            write_stage(target, "triangulation", {"points3d": rng.normal(size=(20000, 38, 3))})
        elif kind == "pose2d":
            limit()
            Pose2dData(rng.normal(size=(7, 5000, 38, 2)), rng.uniform(size=(7, 5000, 38)),
                       config.view_names(), {}).save(target, config.skeleton())
        else:  # assemble: the stage files fit, results.h5 does not
            pose2d = target.parent / "stages" / "big_pose2d.h5"
            Pose2dData(rng.normal(size=(7, 5000, 38, 2)), rng.uniform(size=(7, 5000, 38)),
                       config.view_names(), {}).save(pose2d, config.skeleton())
            limit()
            assemble_results(target, skeleton=config.skeleton(), stage_files={"pose2d": pose2d},
                             config_rig=config_rig(config, {v: (480, 960) for v in config.view_names()}))
    except FlylibError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
""")


@pytest.mark.parametrize(
    "kind,name",
    [
        ("stage", "stages/triangulation.h5"),
        ("pose2d", "stages/pose2d.h5"),
        ("assemble", "results.h5"),
    ],
)
def test_a_write_over_the_file_size_limit_is_one_line_and_keeps_earlier_artifacts(
    tmp_path, kind, name
):
    stages = tmp_path / "stages"
    earlier = stages / "earlier.h5"
    write_stage(earlier, "triangulation", {"points3d": np.ones((10, 38, 3))})
    target = tmp_path / name
    write_stage(target, "triangulation", {"points3d": np.zeros((3, 38, 3))})  # a previous version
    before = {p: p.read_bytes() for p in (earlier, target)}
    proc = subprocess.run(
        [sys.executable, "-c", _WRITE_UNDER_LIMIT, str(target), kind],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=300,
        check=False,
    )
    assert proc.returncode == 1
    assert proc.stderr.strip() == (
        f"error: {target}: could not be written (File too large); nothing was kept (the previous file is "
        "unchanged); free disk space or raise the file-size limit and re-run"
    )
    assert {p: p.read_bytes() for p in (earlier, target)} == before
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]
