"""Runs that protect each other, with real processes.

The output-directory claim of a whole run and its jobs, temporary files of killed
writers, a damaged artifact's root object header, copied and foreign artifacts,
templating in a config file, the file that set a key, footage of another size than
its calibration or its 2D. The workflow-level cases run two real ``snakemake``
processes (``test_workflow_*``, marked slow).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from flylib.pipeline.inputs import stage_inputs, stage_params
from flylib.pipeline.planning import config_rig, params_of

from workflow_run import snakemake_command

REPO = Path(__file__).resolve().parents[2]


def _env(**extra: str) -> dict:
    """Subprocess environment with this checkout's flylib first on the path."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]),
        **extra,
    }
    env.pop("FLYLIB_RUN_ID", None)
    return env


def _spawn(code: str, *args: str, cwd: Path) -> subprocess.Popen:
    """A Python process running ``code`` that prints one line once it is ready."""
    proc = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code), *map(str, args)],
        cwd=cwd,
        env=_env(),
        stdout=subprocess.PIPE,
        text=True,
    )
    return proc


@pytest.fixture
def no_run_id(monkeypatch):
    """No run id in this process's environment, and none left behind by the test."""
    from flylib.locking import RUN_ENV

    monkeypatch.setenv(RUN_ENV, "")
    monkeypatch.delenv(RUN_ENV)


def _damage_root_header(path: Path) -> None:
    """Flip bytes 60-61 of an HDF5 file: its root object header."""
    data = bytearray(path.read_bytes())
    data[60:62] = bytes(b ^ 0xFF for b in data[60:62])
    path.write_bytes(bytes(data))


def _dead_pid(tmp_path: Path) -> int:
    """The pid of a process that has exited (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"], cwd=tmp_path)
    proc.wait()
    return proc.pid


# -- the claim of a whole run ------------------------------------------------------------

_CLAIMER = """
    import sys, time
    from flylib.locking import claim_outdirs
    claimed = claim_outdirs(sys.argv[1:])
    import os
    print(os.environ["FLYLIB_RUN_ID"], flush=True)
    time.sleep(120)
"""


def test_a_runs_claim_passes_its_own_jobs_on_any_host_and_stops_every_other_writer(
    tmp_path, monkeypatch, no_run_id
):
    from flylib.errors import OutputError
    from flylib.locking import LOCK_NAME, RUN_ENV, outdir_lock

    out = tmp_path / "out"
    run_dir = tmp_path / "run-workdir"
    run_dir.mkdir()
    run = _spawn(_CLAIMER, out, cwd=run_dir)
    try:
        run_id = run.stdout.readline().strip()
        holder = json.loads((out / LOCK_NAME).read_text())
        assert holder["pid"] == run.pid and holder["run"] == run_id
        assert holder["job"] == "snakemake run"
        # Another run (no run id, another working directory) stops at once, naming it.
        with (
            pytest.raises(OutputError, match=rf"pid {run.pid} on .*job snakemake run, since "),
            outdir_lock(out, job="assemble"),
        ):
            pass
        # A job of the run on a cluster node: another host, but the claim's run id.
        holder["host"] = "node-17"
        (out / LOCK_NAME).write_text(json.dumps(holder))
        monkeypatch.setenv(RUN_ENV, run_id)
        with outdir_lock(out, job="triangulation"):
            pass
        assert json.loads((out / LOCK_NAME).read_text()) == holder  # the claim stays
    finally:
        run.kill()
        run.wait()


def test_a_claim_is_all_or_none_and_a_killed_runs_claim_is_taken_over(
    tmp_path, monkeypatch, no_run_id
):
    from flylib.errors import OutputError
    from flylib.locking import LOCK_NAME, RUN_ENV, claim_outdirs, release_outdirs

    free, held = tmp_path / "free", tmp_path / "held"
    other = tmp_path / "other-workdir"
    other.mkdir()
    run = _spawn(_CLAIMER, held, cwd=other)
    try:
        run.stdout.readline()
        with pytest.raises(OutputError, match=rf"^{held}: another run is writing"):
            claim_outdirs([free, held])
        assert not (free / LOCK_NAME).exists()  # the one taken before is given back
    finally:
        run.send_signal(signal.SIGKILL)  # dies holding its claim
        run.wait()
    assert json.loads((held / LOCK_NAME).read_text())["pid"] == run.pid
    monkeypatch.delenv(RUN_ENV, raising=False)
    claimed = claim_outdirs([free, held])
    assert claimed == [free, held]
    assert json.loads((held / LOCK_NAME).read_text())["pid"] == os.getpid()
    release_outdirs(claimed)
    assert not list(tmp_path.rglob(f"{LOCK_NAME}*"))


# -- temporary files of killed writers ---------------------------------------------------

_WRITER = """
    import sys, time
    from flylib.paths import atomic_path
    with atomic_path(sys.argv[1]) as tmp:
        with open(tmp, "wb") as f:
            f.write(b"x" * 100_000)
            f.flush()
            print(tmp, flush=True)
            time.sleep(120)
"""


def test_temp_files_of_killed_writers_are_removed_by_the_next_write_never_a_live_ones(
    tmp_path,
):
    from flylib.paths import atomic_path, remove_stale_temps

    target = tmp_path / "stages" / "triangulation.h5"
    live = _spawn(_WRITER, target, cwd=tmp_path)
    try:
        live_temp = Path(live.stdout.readline().strip())
        writers = [_spawn(_WRITER, target, cwd=tmp_path) for _ in range(2)]
        killed = [Path(w.stdout.readline().strip()) for w in writers]
        for writer, sig in zip(writers, (signal.SIGKILL, signal.SIGTERM)):
            writer.send_signal(sig)
            writer.wait()
        assert all(t.is_file() and t.parent == target.parent for t in killed)  # left behind
        elsewhere = target.with_name(
            f".triangulation.{_dead_pid(tmp_path)}@node-17.0123abcd.tmp.h5"
        )
        elsewhere.write_bytes(b"a cluster node's write in progress")
        unrelated = target.with_name(".pose2d.1.0123abcd.tmp.h5")  # pid 1 lives
        unrelated.write_bytes(b"")
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"new")
        assert target.read_bytes() == b"new"
        assert not any(t.exists() for t in killed)
        assert live_temp.is_file() and elsewhere.is_file() and unrelated.is_file()
        # The workflow's sweep of a claimed output directory: the same rule, recursively.
        stale = tmp_path / "stages" / f".pose2d.{_dead_pid(tmp_path)}.89abcdef.tmp.h5"
        stale.write_bytes(b"")
        assert remove_stale_temps(tmp_path, recursive=True) == [stale]
        assert live_temp.is_file()
    finally:
        live.kill()
        live.wait()


# -- a damaged artifact ------------------------------------------------------------------


def _triangulation_artifact(path: Path, config) -> None:
    from flylib.provenance import stage_provenance
    from flylib.results import write_stage

    # a pose of _pose2d_artifact's 2D that agrees with itself (assemble checks it): any
    # 3D, its errors those of that 2D on the config rig
    rng = np.random.default_rng(0)
    points = _pose2d_points()
    points3d = rng.normal(size=(4, 38, 3)) * 0.3
    rig = config_rig(config, {v: (480, 960) for v in config.view_names()})
    error = np.linalg.norm(points - rig.project(points3d), axis=-1)
    write_stage(
        path,
        "triangulation",
        {"points": points, "points3d": points3d, "reproj_error": error},
        meta=stage_provenance(stage_params(config, "triangulation"), "triangulation"),
    )


def _pose2d_points() -> np.ndarray:
    """``(7, 4, 38, 2)`` the made-up detections of :func:`_pose2d_artifact`."""
    return np.random.default_rng(1).random((7, 4, 38, 2)) * 400


def test_a_damaged_root_object_header_is_one_line_naming_the_artifact_and_its_recording(
    tmp_path,
):
    from flylib.config import Config
    from flylib.errors import ResultsError
    from flylib.provenance import foreign_artifacts
    from flylib.results import read_meta

    config = Config.default()
    recs = [
        SimpleNamespace(id=name, outdir=tmp_path / name / "flylib_outputs")
        for name in ("fly1", "fly2")
    ]
    for rec in recs:
        _triangulation_artifact(rec.outdir / "stages" / "triangulation.h5", config)
    damaged = recs[0].outdir / "stages" / "triangulation.h5"
    _damage_root_header(damaged)
    with pytest.raises(ResultsError) as err:
        read_meta(damaged)
    assert str(err.value).startswith(f"{damaged}: its root attributes is damaged (HDF5: ")
    assert "\n" not in str(err.value)
    lines = foreign_artifacts(params_of(config, run_only=True), recs, cwd=tmp_path)
    assert len(lines) == 1 and lines[0].startswith(f"{damaged}: ")
    assert lines[0].endswith("(only fly1 is affected)")


# -- copied and foreign artifacts --------------------------------------------------------


def test_a_copied_artifact_with_other_params_is_named_and_an_equal_params_stranger_is_told(
    tmp_path, monkeypatch
):
    from flylib.config import Config
    from flylib.locking import outdir_lock
    from flylib.provenance import foreign_artifacts, provenance_report

    monkeypatch.chdir(tmp_path)
    config = Config.default()
    original = tmp_path / "fly1" / "flylib_outputs"
    with outdir_lock(original, job="triangulation"):
        _triangulation_artifact(original / "stages" / "triangulation.h5", config)
    copy = tmp_path / "copy" / "flylib_outputs"
    shutil.copytree(original, copy)
    edited = Config.from_dict(
        {**config.data, "triangulation": {**config.data["triangulation"], "ransac_threshold": 9.0}}
    )
    lines = foreign_artifacts(
        params_of(edited, run_only=True), [SimpleNamespace(id="copy", outdir=copy)], cwd=tmp_path
    )
    assert lines == [
        f"{copy / 'stages' / 'triangulation.h5'}: copied from {original.resolve()} (made there "
        f"with other triangulation params, {_hash(config)}; this config gives {_hash(edited)}); "
        "Snakemake has no record of the copy and takes it as up to date: delete it or re-run "
        "with --forcerun triangulation"
    ]
    assert (
        foreign_artifacts(
            params_of(config, run_only=True),
            [SimpleNamespace(id="copy", outdir=copy)],
            cwd=tmp_path,
        )
        == []
    )

    # results.h5 assembled from one triangulation, then another with equal params put in
    # its place (from another recording): no longer silent.
    from flylib.pipeline.assemble import run_assemble

    _pose2d = _pose2d_artifact(original / "stages" / "pose2d.h5", config)
    run_assemble(
        stage_inputs(config, "assemble"),
        {"pose2d": _pose2d, "triangulation": original / "stages" / "triangulation.h5"},
        original,
    )
    assert all(
        r.status == "ok" for r in provenance_report(original / "results.h5", params_of(config))
    )
    _triangulation_artifact(original / "stages" / "triangulation.h5", config)
    rows = {r.stage: r for r in provenance_report(original / "results.h5", params_of(config))}
    assert rows["triangulation"].status == "mixed"
    assert (
        "with equal params; results.h5 is not assembled from these artifacts"
        in (rows["triangulation"].problems[0])
    )


def _hash(config) -> str:
    from flylib.provenance import params_hash

    return params_hash(stage_params(config, "triangulation"))


def _pose2d_artifact(path: Path, config) -> Path:
    from flylib.provenance import stage_provenance
    from flylib.results import Pose2dData

    rng = np.random.default_rng(2)
    views = config.view_names()
    Pose2dData(
        pts2d=_pose2d_points(),
        conf=rng.random((7, 4, 38)),
        view_names=views,
        image_sizes={v: (480, 960) for v in views},
    ).save(path, config.skeleton(), meta=stage_provenance(stage_params(config, "pose2d"), "pose2d"))
    return path


def test_inspect_config_merges_the_users_file_over_the_default_and_judges_each_stage_alone(
    tmp_path, capsys
):
    from flylib.cli import main as flylib_main
    from flylib.config import Config
    from flylib.pipeline.assemble import run_assemble

    config = Config.default()
    out = tmp_path / "fly1" / "flylib_outputs"
    pose2d = _pose2d_artifact(out / "stages" / "pose2d.h5", config)
    _triangulation_artifact(out / "stages" / "triangulation.h5", config)
    run_assemble(
        stage_inputs(config, "assemble"),
        {"pose2d": pose2d, "triangulation": out / "stages" / "triangulation.h5"},
        out,
    )
    mine = tmp_path / "my.yaml"
    mine.write_text("triangulation:\n  ransac_threshold: 9.0\n")
    status = flylib_main(["inspect", str(out / "results.h5"), "--config", str(mine)])
    printed = capsys.readouterr()
    table = printed.out[printed.out.index("provenance") :]
    rows = {line.split()[0]: line.split()[-1] for line in table.splitlines()[2:] if line.strip()}
    assert rows["pose2d"] == "ok" and rows["triangulation"] == "stale", table
    assert status == 2


# -- config files: templating, the file that set a key ------------------------------------


def test_check_config_refuses_yte_templating_naming_the_file(tmp_path, capsys):
    from flylib.cli import main as flylib_main

    marker = tmp_path / "ran"
    template = tmp_path / "my.yaml"
    template.write_text(
        f"__use_yte__: true\ntriangulation:\n  ransac_threshold: ?open({str(marker)!r}, 'w') and 3\n"
    )
    assert flylib_main(["check-config", str(REPO / "config" / "config.yaml"), str(template)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"flylib check-config: invalid config: {template}: __use_yte__: templating is not "
        "accepted in a flylib config (Snakemake runs the Python inside such a file while "
        "reading it, before flylib can check it); remove __use_yte__ and write the values out"
    ]
    assert not marker.exists()


def test_a_camera_key_set_in_the_users_defaults_names_the_users_file(tmp_path, capsys):
    from flylib.cli import main as flylib_main

    mine = tmp_path / "my.yaml"
    mine.write_text("cameras:\n  defaults:\n    focal_length_px: [.inf, 1]\n")
    base = REPO / "config" / "config.yaml"
    assert flylib_main(["check-config", str(base), str(mine)]) == 1
    err = capsys.readouterr().err.strip()
    # the non-finite value is named where the user wrote it (every number is checked)
    assert err.startswith(
        f"flylib check-config: invalid config: {mine}: cameras.defaults.focal_length_px[0]: "
        "expected a finite number"
    )
    # A camera's own key still names the file that set it on the camera.
    mine.write_text("cameras:\n  rm: {azimuth_deg: -90, focal_length_px: [.inf, 1]}\n")
    assert flylib_main(["check-config", str(base), str(mine)]) == 1
    assert f"invalid config: {mine}: cameras.rm.focal_length_px" in capsys.readouterr().err


# -- footage of another size --------------------------------------------------------------


def _anipose_toml(path: Path, views: list[str], size: tuple[int, int]) -> None:
    """An Anipose calibration in its published layout (``[cam_N]`` tables, ``size`` as
    [width, height], ``matrix``, ``distortions``, ``rotation``, ``translation``)."""
    blocks = []
    for i, view in enumerate(views):
        blocks.append(
            textwrap.dedent(f"""
                [cam_{i}]
                name = "{view}"
                size = [ {size[0]}, {size[1]},]
                matrix = [ [ 22388.1, 0.0, {size[0] / 2},], [ 0.0, 22388.1, {size[1] / 2},], [ 0.0, 0.0, 1.0,],]
                distortions = [ 0.0, 0.0, 0.0, 0.0, 0.0,]
                rotation = [ 0.0, {0.3 * i}, 0.0,]
                translation = [ 0.0, 0.0, 107.5,]
            """)
        )
    blocks.append("\n[metadata]\nadjusted = false\nerror = 0.0\n")
    path.write_text("".join(blocks))


def test_footage_of_another_size_than_its_calibration_names_the_camera_and_both_sizes(tmp_path):
    from flylib.config import Config
    from flylib.errors import FootageError
    from flylib.pipeline.planning import config_rig

    config = Config.default()
    views = config.view_names()
    _anipose_toml(tmp_path / "calibration.toml", views, (960, 480))
    config = Config.from_dict(
        {
            **config.data,
            "calibration": {"file": str(tmp_path / "calibration.toml"), "format": "anipose"},
        }
    )
    sizes = {v: (480, 960) for v in views}
    assert config_rig(config, sizes, tmp_path).names == views
    sizes[views[1]] = (360, 640)
    with pytest.raises(FootageError) as err:
        config_rig(config, sizes, tmp_path)
    assert str(err.value) == (
        f"{tmp_path}: camera {views[1]}: footage is 640x360 px but {tmp_path / 'calibration.toml'} "
        "calibrated it at 960x480 px (width x height); use that camera's original footage or a "
        "calibration made at this resolution"
    )


def test_imported_2d_outside_a_reencoded_videos_frame_names_the_camera_and_sizes(tmp_path):
    from flylib.config import Config
    from flylib.errors import FootageError
    from flylib.io import VideoWriter, open_reader
    from flylib.pipeline.demo import demo_import_spec, make_demo
    from flylib.pipeline.pose2d import run_pose2d

    config = Config.default()
    recording = tmp_path / "rec"
    make_demo(config, recording, frames=6, seed=0)
    out = recording / "flylib_outputs" / "stages" / "pose2d.h5"
    run_pose2d(
        stage_inputs(config, "pose2d"), recording, out, import_spec=demo_import_spec(config)
    )  # as made: fine
    out.unlink()
    video = recording / "camera_1.mp4"  # re-encoded at 640x360, as a user's tool might
    frames = open_reader(video)[:]  # (T, H, W, 3)
    rows = np.linspace(0, frames[0].shape[0] - 1, 360).astype(int)
    cols = np.linspace(0, frames[0].shape[1] - 1, 640).astype(int)
    small = recording / "small.mp4"
    with VideoWriter(small, fps=30) as writer:
        writer.write_frames(np.stack([f[rows][:, cols] for f in frames]))
    small.replace(video)
    with pytest.raises(FootageError) as err:
        run_pose2d(
            stage_inputs(config, "pose2d"), recording, out, import_spec=demo_import_spec(config)
        )
    view = config.view_names()[1]
    assert str(err.value).startswith(f"{recording}: camera {view}: footage is 640x360 px but "), (
        err.value
    )
    assert "of its imported 2D lies outside that frame" in str(err.value)
    assert not out.exists()


# -- the workflow: two real snakemake runs -------------------------------------------------


def _snakemake(workdir: Path, *args: str) -> list[str]:
    return snakemake_command(workdir, *args)


def _run(workdir: Path, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    """The workflow in ``workdir`` to its end, its output captured."""
    return subprocess.run(
        _snakemake(workdir, *args),
        cwd=workdir,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A work directory with two tiny recordings run to completion."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    root = tmp_path_factory.mktemp("claim")
    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    data["bundle_adjustment"]["max_nfev"] = 20
    cfg = Config.from_dict(data)
    data["recordings"] = []
    for seed, name in enumerate(("fly1", "fly2")):
        make_demo(cfg, root / name, frames=6, seed=seed)
        data["recordings"].append({"path": str(root / name), "import": demo_import_spec(cfg)})
    (root / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    proc = _run(root)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return SimpleNamespace(root=root, data=data)


def _lock(outdir: Path) -> dict | None:
    from flylib.locking import lock_holder

    return lock_holder(outdir / ".flylib.lock")


@pytest.mark.slow
def test_workflow_a_second_run_from_another_directory_touches_nothing_of_the_first(
    finished_run, tmp_path
):
    root = finished_run.root
    out = root / "fly1" / "flylib_outputs"
    pose2d = out / "stages" / "pose2d.h5"
    before = (pose2d.stat().st_ino, pose2d.stat().st_mtime_ns)
    other = tmp_path / "checkout-b"
    other.mkdir()
    shutil.copy(root / "config.yaml", other / "config.yaml")
    first = subprocess.Popen(
        _snakemake(root, "--forcerun", "kinematics"),  # a real run: its claim, its jobs
        cwd=root,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # its own process group: the run and its jobs
    )
    try:
        deadline = time.monotonic() + 300
        while (_lock(out) or {}).get("job") != "snakemake run":
            assert first.poll() is None and time.monotonic() < deadline, "the run never claimed"
            time.sleep(0.05)
        # Freeze the first run with its jobs, so that it is surely still running (alive,
        # holding its claim) however slow the machine is while the second one starts.
        os.killpg(first.pid, signal.SIGSTOP)
        claim = _lock(out)
        assert claim["pid"] == first.pid
        second = _run(other, "--forcerun", "pose2d", timeout=600)
        # What only reads passes beside a claimed directory: a dry run, --list, --summary.
        for args in (("-n",), ("--list-rules",), ("--summary",)):
            look = subprocess.run(
                _snakemake(other, *args), cwd=other, env=_env(), capture_output=True, text=True
            )
            assert look.returncode == 0, (args, look.stderr[-3000:])
    finally:
        os.killpg(first.pid, signal.SIGCONT)
        log, _ = first.communicate(timeout=900)
    assert second.returncode == 1
    assert (
        f"{out}: another run is writing this output directory (pid {first.pid} on "
        f"{claim['host']}, working directory {root}, job snakemake run, since " in second.stderr
    ), second.stderr[-3000:]
    assert "Removing output files" not in second.stderr
    assert first.returncode == 0, log[-4000:]
    assert (pose2d.stat().st_ino, pose2d.stat().st_mtime_ns) == before  # never deleted
    assert (out / "results.h5").is_file() and (out / "config.yaml").is_file()
    assert _lock(out) is None  # released at the end


@pytest.mark.slow
def test_workflow_a_killed_runs_claim_and_temp_files_are_cleared_by_the_next_run(
    finished_run, tmp_path
):
    root = finished_run.root
    out = root / "fly2" / "flylib_outputs"
    dead = _dead_pid(tmp_path)
    (out / ".flylib.lock").write_text(
        json.dumps(
            {"host": os.uname().nodename, "pid": dead, "cwd": "/elsewhere", "job": "snakemake run"}
        )
    )
    temp = out / f".results.{dead}.0123abcd.tmp.h5"
    temp.write_bytes(b"x" * 1000)
    proc = _run(root, "--forcerun", "kinematics", timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert not temp.exists() and _lock(out) is None
    assert f"removed {temp}, left by a writer that was killed" in proc.stderr


@pytest.mark.slow
def test_workflow_a_damaged_artifact_blocks_only_its_own_recording(finished_run):
    root = finished_run.root
    damaged = root / "fly1" / "flylib_outputs" / "stages" / "triangulation.h5"
    _damage_root_header(damaged)
    fly2 = root / "fly2" / "flylib_outputs" / "results.h5"
    before = fly2.stat().st_mtime_ns
    proc = _run(root, "--forcerun", "assemble", timeout=900)
    assert proc.returncode == 1
    warning = f"{damaged}: its root attributes is damaged (HDF5: "
    assert warning in proc.stderr and "(only fly1 is affected)" in proc.stderr
    assert "KeyError" not in proc.stderr
    assert fly2.stat().st_mtime_ns > before  # fly2 was assembled again
    damaged.unlink()  # later tests of the module start from a whole run
    assert _run(root, "--forcerun", "triangulation").returncode == 0


@pytest.mark.slow
def test_workflow_refuses_yte_and_warns_about_a_copied_outdir(finished_run, tmp_path):
    root = finished_run.root
    template = tmp_path / "yte.yaml"
    template.write_text("__use_yte__: true\ntriangulation:\n  ransac_threshold: ?2 + 1\n")
    proc = _run(root, "-n", "--configfile", str(root / "config.yaml"), str(template), timeout=600)
    assert proc.returncode == 1
    assert "__use_yte__: templating is not accepted in a flylib config" in proc.stdout + proc.stderr

    copy = tmp_path / "copy"
    shutil.copytree(root / "fly1" / "flylib_outputs", copy)
    data = json.loads(json.dumps(finished_run.data))
    data["recordings"] = [{**data["recordings"][0], "outdir": str(copy)}]
    data["triangulation"]["ransac_threshold"] = 9.0
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    proc = _run(tmp_path, "-n", timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    expected = f"{copy / 'stages' / 'triangulation.h5'}: copied from {(root / 'fly1' / 'flylib_outputs').resolve()}"
    assert expected in proc.stdout + proc.stderr, proc.stderr[-3000:]


def test_corrections_beside_results_that_its_triangulation_did_not_apply_are_not_ok(tmp_path):
    from flylib.config import Config
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.stage_helpers import run_inputs
    from flylib.pipeline.triangulation import run_triangulation
    from flylib.provenance import provenance_report

    from gui_fixtures import make_demo_outputs, write_seed_sidecar

    out = make_demo_outputs(tmp_path / "rec", frames=6)
    results = out / "results.h5"
    config = Config.from_file(out / "config.yaml")
    assert all(r.status == "ok" for r in provenance_report(results, params_of(config)))
    sidecar = write_seed_sidecar(out / "corrections.h5", (7, 6, 38), edits2d=[(0, 2, 5, 40, 50)])
    rows = {r.stage: r for r in provenance_report(results, params_of(config))}
    assert rows["triangulation"].status == "stale"
    assert rows["triangulation"].problems == [
        f"{sidecar}: manual corrections that the triangulation in results.h5 did not apply; "
        "re-run the workflow to apply them"
    ]
    stages = out / "stages"
    run_triangulation(
        run_inputs(config, "triangulation"),
        stages / "pose2d.h5",
        stages / "triangulation.h5",
        recording_dir=tmp_path / "rec",
        corrections_path=sidecar,
    )
    run_assemble(
        stage_inputs(config, "assemble"),
        {"pose2d": stages / "pose2d.h5", "triangulation": stages / "triangulation.h5"},
        out,
        recording_dir=tmp_path / "rec",
    )
    assert all(r.status == "ok" for r in provenance_report(results, params_of(config)))
    write_seed_sidecar(sidecar, (7, 6, 38), edits2d=[(0, 2, 5, 40, 50), (1, 3, 6, 60, 70)])
    rows = {r.stage: r for r in provenance_report(results, params_of(config))}
    assert rows["triangulation"].problems == [
        f"{sidecar}: changed since the triangulation in results.h5 applied it (1 corrections "
        "then); re-run the workflow to apply it"
    ]


# -- memory declared ---------------------------------------------------------------------


def test_jobs_declare_memory_from_the_recordings_size(tmp_path):
    from flylib.config import Config
    from flylib.pipeline.memory import FLOOR_MB, job_mem_mb, recording_shape, stage_mem_mb

    config = Config.default()
    pose2d = _pose2d_artifact(tmp_path / "pose2d.h5", config)
    assert recording_shape(pose2d) == (7, 4, 38)
    mem_mb = job_mem_mb("triangulation")
    assert mem_mb(None, {"pose2d": str(pose2d)}) == stage_mem_mb("triangulation", (7, 4, 38))
    assert mem_mb(None, {"pose2d": str(pose2d)}, attempt=2) == 2 * FLOOR_MB  # a retry: twice
    # The 100,000-frame import peaked at 2.31 GB in triangulation (mem_mb was 2000).
    assert stage_mem_mb("triangulation", (7, 100_000, 38)) > 1.5 * 2310
    for stage in ("bundle_adjustment", "triangulation", "refinement", "assemble", "kinematics"):
        small, large = (stage_mem_mb(stage, (7, t, 38)) for t in (100, 100_000))
        assert FLOOR_MB <= small < large
    # Before pose2d has run, Snakemake defers the resource: FileNotFoundError naming it.
    missing = tmp_path / "stages" / "pose2d.h5"
    with pytest.raises(FileNotFoundError) as err:
        mem_mb(None, {"pose2d": str(missing)})
    assert err.value.filename == str(missing)


# -- a job that outlived its run; a job killed or stopped (issue 37, cases 13 and 14) ----


def test_an_orphan_job_never_renames_into_a_folder_another_run_took_over(
    tmp_path, monkeypatch, no_run_id
):
    from flylib.errors import OutputError
    from flylib.locking import LOCK_NAME, RUN_ENV, claim_outdirs, lock_holder, outdir_lock
    from flylib.paths import atomic_path

    out = tmp_path / "out"
    target = out / "stages" / "refinement.h5"
    claim_outdirs([out], run="killed-run")  # the run this job belongs to
    assert os.environ[RUN_ENV] == "killed-run"
    # While the run holds its claim, its job writes as always.
    with outdir_lock(out, job="refinement"), atomic_path(target) as tmp:
        tmp.write_bytes(b"old params")
    assert target.read_bytes() == b"old params"

    new_run = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        with outdir_lock(out, job="refinement"):
            with pytest.raises(OutputError) as caught, atomic_path(target) as tmp:
                tmp.write_bytes(b"old params again")
                # The run is killed; a new run (another process, other params) takes
                # the claim over and writes its own result before this job's rename.
                new = {**lock_holder(out / LOCK_NAME), "pid": new_run.pid, "run": "new-run"}
                (out / LOCK_NAME).write_text(json.dumps(new))
                target.write_bytes(b"new params")
            assert str(caught.value) == (
                f"{target}: not written: another run took over {out.resolve()} while this "
                f"job ran (pid {new_run.pid} on {new['host']}, working directory "
                f"{new['cwd']}, job snakemake run, since {new['since']}); this job's run "
                "was stopped or killed, so its result was discarded and the new run's "
                "files are kept"
            )
        assert target.read_bytes() == b"new params"
        assert [p.name for p in target.parent.iterdir()] == ["refinement.h5"]  # no temp left
        assert lock_holder(out / LOCK_NAME)["run"] == "new-run"  # the new claim stands
    finally:
        new_run.kill()
        new_run.wait()


def _descendant(root: int, name: bytes) -> int | None:
    """A process under ``root`` whose command line holds ``name`` (Linux /proc)."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                parents[int(entry.name)] = (int(fields[1]), (entry / "cmdline").read_bytes())
            except (OSError, IndexError, ValueError):
                continue
    for pid, (_, cmdline) in parents.items():
        if name not in cmdline:
            continue
        ancestor = pid
        while ancestor in parents and ancestor != root:
            ancestor = parents[ancestor][0]
        if ancestor == root:
            return pid
    return None


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the job through /proc")
@pytest.mark.parametrize(
    ("signum", "whom", "status"),
    [
        (
            signal.SIGKILL,
            "job",
            "refinement was killed by SIGKILL: its log {log} ends without an error",
        ),
        (signal.SIGTERM, "run", "refinement was stopped by SIGTERM; re-run to resume"),
    ],
)
def test_workflow_a_killed_or_stopped_job_is_reported_so_in_the_table(
    finished_run, signum, whom, status
):
    from flylib.run_summary import job_end

    root = finished_run.root
    log = root / "fly1" / "flylib_outputs" / "logs" / "refinement.log"
    # The job is small: a signal can land after it has finished. Such a try proves
    # nothing about a killed job, so it is made again (the job always re-runs).
    for _attempt in range(5):
        output, returncode = _interrupt_refinement(root, log, signum, whom)
        if job_end(log) != "finished":
            break
    else:
        pytest.fail("the refinement job finished before every signal; nothing was tested")
    assert returncode != 0
    table = output[output.index("flylib: per-recording results") :]
    row = next(line for line in table.splitlines() if line.startswith("fly1 "))
    assert status.format(log=log) in row, table
    assert "failed: see" not in table
    assert _run(root).returncode == 0  # the resume is whole


def _interrupt_refinement(root: Path, log: Path, signum: int, whom: str) -> tuple[str, int]:
    """Re-run fly1's refinement and send ``signum`` to the job (``whom == "job"``) or to
    the whole run, as soon as the job has its own log (its stop handlers are then set);
    the run's output and exit status."""
    log.unlink(missing_ok=True)  # the finished run's log ends well: wait for this job's own
    run = subprocess.Popen(
        _snakemake(
            root, str(log.parents[1] / "stages" / "refinement.h5"), "--forcerun", "refinement"
        ),
        cwd=root,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 300
        while (job := _descendant(run.pid, b"refinement.py")) is None or not log.is_file():
            assert run.poll() is None and time.monotonic() < deadline, "refinement never ran"
            time.sleep(0.005)
        time.sleep(0.02)  # past the few statements between the log's creation and the handlers
        if whom == "job":
            os.kill(job, signum)  # like the kernel's out-of-memory killer
        else:
            os.killpg(run.pid, signum)  # the whole run stopped, as a scheduler does
        output, _ = run.communicate(timeout=600)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait()
    return output, run.returncode
