"""The demo through ``--profile profiles/slurm`` on a real single-node SLURM cluster.

The test brings the cluster up itself from Debian's ``slurm-wlm`` and ``munge`` (which
``bash install.sh --test-system-packages`` installs where it can; without them the test
skips with that advice): a private
``slurm.conf`` in a temporary directory (``SLURM_CONF``), ``munged``, ``slurmctld``
and ``slurmd`` started by the test and stopped again by their process ids. Where any
of that is impossible it skips with the reason. Every step is bounded in time.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from workflow_run import demo_batch, snakemake_command

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
DAEMONS = ("slurmctld", "slurmd", "munged", "sbatch", "squeue", "sinfo")

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1500)]


def _run(cmd, timeout, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kwargs)


def _ensure_installed() -> None:
    # Installing is the set-up's job (install.sh --test-system-packages, run by .ci/run),
    # never a test's.
    missing = [d for d in DAEMONS if not shutil.which(d)]
    if missing:
        pytest.skip(
            f"SLURM is not installed ({', '.join(missing)} not found): run "
            "`bash install.sh --test-system-packages` as root, or apt-get install slurm-wlm munge"
        )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _slurm_conf(root: Path, host: str) -> str:
    cpus = os.cpu_count() or 2
    return "\n".join(
        [
            "ClusterName=flylibtest",
            f"SlurmctldHost={host}(127.0.0.1)",
            f"SlurmctldPort={_free_port()}",
            f"SlurmdPort={_free_port()}",
            "SlurmUser=root",
            "SlurmdUser=root",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"StateSaveLocation={root}/state",
            f"SlurmdSpoolDir={root}/spool",
            f"SlurmctldPidFile={root}/slurmctld.pid",
            f"SlurmdPidFile={root}/slurmd.pid",
            f"SlurmctldLogFile={root}/slurmctld.log",
            f"SlurmdLogFile={root}/slurmd.log",
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "SchedulerType=sched/backfill",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core",
            "MpiDefault=none",
            "ReturnToService=2",
            "MinJobAge=3600",
            "SlurmdParameters=config_overrides",
            f"NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory=16000 State=UNKNOWN",
            "PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
            "",
        ]
    )


def _start_munge() -> tuple[subprocess.Popen | None, Path | None]:
    """A munged of our own (socket in a world-traversable temp dir), unless munge works."""
    if _run(["sh", "-c", "munge -n | unmunge"], 10).returncode == 0:
        return None, None
    socket_dir = Path(tempfile.mkdtemp(prefix="flylib-munge-"))
    socket_dir.chmod(0o755)  # munged insists that everyone can reach its socket
    shutil.chown(socket_dir, "munge", "munge")
    proc = subprocess.Popen(
        [
            "runuser",
            "-u",
            "munge",
            "--",
            "munged",
            "--foreground",
            f"--socket={socket_dir}/munge.socket.2",
            f"--pid-file={socket_dir}/munged.pid",
            f"--seed-file={socket_dir}/munged.seed",
            f"--log-file={socket_dir}/munged.log",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    for _ in range(50):
        if (socket_dir / "munge.socket.2").exists():
            return proc, socket_dir
        time.sleep(0.2)
    proc.kill()
    pytest.skip(f"munged did not start: {proc.communicate(timeout=10)[1][-300:]}")


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=20)


@pytest.fixture(scope="module")
def slurm_cluster(tmp_path_factory):
    _ensure_installed()
    if os.geteuid() != 0:
        pytest.skip("starting slurmctld/slurmd for the test needs root")
    root = tmp_path_factory.mktemp("slurm")
    for sub in ("state", "spool"):
        (root / sub).mkdir()
    host = socket.gethostname().split(".")[0]
    conf = root / "slurm.conf"
    conf.write_text(_slurm_conf(root, host))
    env = {**os.environ, "SLURM_CONF": str(conf)}
    munged, socket_dir = _start_munge()
    if socket_dir is not None:
        # the clients (sinfo, sbatch, ...) and the daemons take the socket from slurm.conf
        conf.write_text(conf.read_text() + f"AuthInfo=socket={socket_dir}/munge.socket.2\n")
    # Job steps (srun inside the batch script) read the default slurm.conf location;
    # point it at ours when the machine has none, and take it away afterwards.
    system_conf = Path("/etc/slurm/slurm.conf")
    linked = not system_conf.exists() and system_conf.parent.is_dir()
    if linked:
        system_conf.symlink_to(conf)
    daemons: list[subprocess.Popen] = []
    try:
        for daemon in ("slurmctld", "slurmd"):
            daemons.append(
                subprocess.Popen(
                    [daemon, "-D", "-f", str(conf)],
                    env=env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
            time.sleep(1.0)
        deadline = time.monotonic() + 90
        state = ""
        while time.monotonic() < deadline:
            state = _run(["sinfo", "-h", "-o", "%t"], 15, env=env).stdout.strip()
            if state in ("idle", "mix", "alloc"):
                break
            time.sleep(1.0)
        else:
            logs = "".join(
                (root / f).read_text()[-600:]
                for f in ("slurmctld.log", "slurmd.log")
                if (root / f).exists()
            )
            pytest.skip(f"SLURM did not come up (sinfo: {state!r}): {logs}")
        yield env
    finally:
        for proc in reversed(daemons):
            _stop(proc)
        if linked:
            system_conf.unlink(missing_ok=True)
        if munged is not None:
            pid_file = socket_dir / "munged.pid"
            pid = int(pid_file.read_text()) if pid_file.is_file() else None
            _stop(munged)
            if pid is not None:
                try:
                    os.kill(pid, signal.SIGTERM)  # the munged we started, if runuser left it
                except ProcessLookupError:
                    pass
            shutil.rmtree(socket_dir, ignore_errors=True)


def test_demo_runs_to_completion_through_the_slurm_profile(slurm_cluster, tmp_path):
    from flylib.results import PoseResult

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["demo"] = {**(config.get("demo") or {}), "frames": 8}
    config["bundle_adjustment"]["max_nfev"] = 20
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    cmd = [
        str(SNAKEMAKE),
        "--profile",
        str(REPO / "profiles" / "slurm"),
        "--snakefile",
        str(REPO / "Snakefile"),
        "--directory",
        str(tmp_path),
        "--configfile",
        str(tmp_path / "config.yaml"),
        "--replace-workflow-config",
        "--jobs",
        "4",
        "--set-resources",
        "pose2d:mem_mb=2000",
        "visualization:mem_mb=2000",
    ]
    env = {**slurm_cluster, "PATH": f"{Path(sys.executable).parent}:{os.environ.get('PATH', '')}"}
    try:
        proc = _run(cmd, 900, env=env, cwd=tmp_path)
    except subprocess.TimeoutExpired:
        pytest.fail("the SLURM run did not finish within 15 minutes")
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    # two submissions: the demo rule, then the recording's group (imported 2D ... videos)
    assert _submissions(proc.stdout + proc.stderr) == 2
    out = tmp_path / "demo" / "flylib_outputs"
    result = PoseResult.load(out / "results.h5")
    assert result.pts3d.shape == (8, 38, 3)
    assert (out / "pose3d.mp4").stat().st_size > 0


def _submissions(text: str) -> int:
    """The sbatch calls of a run (the SLURM executor logs each submission)."""
    return len(re.findall(r"has been submitted with SLURM jobid \d+", text))


def _arrays(path: Path) -> dict[str, np.ndarray]:
    """Every numeric dataset of an HDF5 file (provenance attributes left out)."""
    found: dict[str, np.ndarray] = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset) and obj.dtype.kind in "fiub":
            found[name] = obj[()]

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return found


def test_a_batch_is_one_submission_per_recording_with_the_results_of_a_local_run(
    slurm_cluster, tmp_path
):
    """Issue 38: each recording's CPU chain (imported 2D, bundle adjustment, ...,
    kinematics) is one sbatch job, its resources derived from its jobs; the outputs are
    those of a local run. Two recordings: one submission each, not one for the batch."""
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["bundle_adjustment"]["max_nfev"] = 20
    config["pipeline"]["do_kinematics"] = True
    config["recordings"] = str(demo_batch(tmp_path / "batch", 2, config, frames=8))
    config["outdir"] = "results/{id}"
    runs = {}
    for name in ("local", "slurm"):
        work = tmp_path / name
        work.mkdir()
        (work / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
        runs[name] = work
    local = _run(snakemake_command(runs["local"]), 900, cwd=runs["local"])
    assert local.returncode == 0, local.stdout[-3000:] + local.stderr[-3000:]

    # --cores 2: the test node's CPUs, which bound what a group asks for (Snakemake
    # runs a group's side-by-side jobs one after another where they would exceed it)
    cmd = [
        *snakemake_command(runs["slurm"], cores=2),
        "--profile",
        str(REPO / "profiles" / "slurm"),
        "--jobs",
        "4",
    ]
    env = {**slurm_cluster, "PATH": f"{Path(sys.executable).parent}:{os.environ.get('PATH', '')}"}
    try:
        proc = _run(cmd, 900, env=env, cwd=runs["slurm"])
    except subprocess.TimeoutExpired:
        pytest.fail("the SLURM run did not finish within 15 minutes")
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-6000:]
    assert _submissions(log) == 2, log[-6000:]

    for rec in ("rec00000", "rec00001"):
        mine = runs["slurm"] / "results" / rec
        theirs = runs["local"] / "results" / rec
        for name in ("results.h5", "kinematics.h5", "stages/bundle_adjustment.h5"):
            a, b = _arrays(mine / name), _arrays(theirs / name)
            assert a.keys() == b.keys(), name
            for key in a:
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{rec}/{name}:{key}")
        for name in ("angles.csv", "calibration.toml", "suspects.csv"):
            assert (mine / name).read_bytes() == (theirs / name).read_bytes(), name
        for name in ("pose3d.mp4", "summary.png", "angles.png"):
            assert (mine / name).stat().st_size > 0, name
