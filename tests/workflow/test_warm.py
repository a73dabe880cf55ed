"""Warm processes (flylib.warm): a job handed to a warm process behaves as the job's own
process would (its files, directory, environment, arguments, exit status, signals), and
a workflow run through warm processes writes what a run without them writes."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest
import yaml

from flylib.warm import SCHEDULER_VARIABLES
from tests.workflow_run import demo_batch, snakemake_command

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="warm processes fork: Linux only"
)

#: A job script as the stage scripts use flylib.warm: offered to the warm process
#: first, else (and in the warm process's child) its body runs.
JOB = textwrap.dedent(
    """
    import os, signal, sys, time
    from pathlib import Path
    from flylib.warm import forward

    status = forward(__file__)
    if status is not None:
        print(f"client {os.getpid()}", flush=True)
        sys.exit(status)
    mode, marker = sys.argv[1], Path(sys.argv[2])
    print(f"body pid={os.getpid()} cwd={os.getcwd()} var={os.environ.get('JOB_VAR')} "
          f"argv={sys.argv[1:]} stdin={sys.stdin.readline().strip()}", flush=True)
    print("body stderr", file=sys.stderr, flush=True)

    def stopped(signum, frame):
        marker.write_text(signal.Signals(signum).name)
        print("stopped", flush=True)
        sys.exit(128 + signum)

    signal.signal(signal.SIGTERM, stopped)
    if mode == "exit":
        sys.exit(3)
    if mode == "raise":
        raise RuntimeError("the job's own error")
    if mode == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if mode == "wait":
        marker.write_text("waiting")
        time.sleep(120)
    """
)


@pytest.fixture
def env() -> dict:
    """The jobs' environment: warm processes on, their sockets in a folder of this test's
    own (short: a socket's path has at most 107 bytes)."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("FLYLIB_WARM")}
    for name in SCHEDULER_VARIABLES:
        environ.pop(name, None)
    runtime = tempfile.mkdtemp(prefix="fw", dir="/tmp")
    environ["XDG_RUNTIME_DIR"] = runtime
    yield environ
    shutil.rmtree(runtime, ignore_errors=True)


def _socket(env: dict) -> Path:
    out = subprocess.run(
        [sys.executable, "-c", "from flylib.warm import socket_path; print(socket_path())"],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return Path(out.stdout.strip())


def _wait_for(condition, seconds: float = 90.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


@pytest.fixture
def warm(env, tmp_path):
    """A warm process serving ``env``'s jobs (idle for at most 30 s); its socket path."""
    path = _socket(env)
    path.parent.mkdir(mode=0o700, exist_ok=True)
    server = subprocess.Popen(
        [sys.executable, "-m", "flylib.warm", str(path), "30"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=open(path.with_suffix(".log"), "ab"),  # noqa: SIM115
    )
    _wait_for(lambda: path.exists() or server.poll() is not None)
    assert server.poll() is None, path.with_suffix(".log").read_text()
    yield path
    server.terminate()
    server.wait(30)


def _job(tmp_path: Path, env: dict, mode: str, **kwargs) -> subprocess.Popen:
    script = tmp_path / "job.py"
    script.write_text(JOB)
    work = tmp_path / "work"
    work.mkdir(exist_ok=True)
    return subprocess.Popen(
        [sys.executable, str(script), mode, str(tmp_path / "marker")],
        cwd=work,
        env={**env, "JOB_VAR": mode},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


def test_a_job_runs_in_a_child_of_the_warm_process_with_its_own_files_and_status(
    warm, env, tmp_path
):
    job = _job(tmp_path, env, "exit")
    out, err = job.communicate("a line on stdin\n", timeout=60)
    assert job.returncode == 3
    body = next(line for line in out.splitlines() if line.startswith("body"))
    client = next(line for line in out.splitlines() if line.startswith("client"))
    assert f"pid={job.pid}" not in body and client == f"client {job.pid}"
    assert f"cwd={tmp_path / 'work'}" in body and "var=exit" in body
    assert f"argv=['exit', '{tmp_path / 'marker'}']" in body
    assert "stdin=a line on stdin" in body  # its stdin, stdout and stderr are the job's
    assert "body stderr" in err
    assert "job.py in" in warm.with_suffix(".log").read_text()


def test_a_job_error_is_printed_and_fails_the_job(warm, env, tmp_path):
    job = _job(tmp_path, env, "raise")
    out, err = job.communicate("\n", timeout=60)
    assert job.returncode == 1
    assert "body pid" in out and "RuntimeError: the job's own error" in err


def _waiting_job(tmp_path: Path, env: dict) -> tuple[subprocess.Popen, Path]:
    """A job whose child waits (its stop handler set), and the child's marker file."""
    job = _job(tmp_path, env, "wait")
    job.stdin.write("\n")
    job.stdin.flush()
    marker = tmp_path / "marker"
    _wait_for(lambda: marker.exists())
    return job, marker


def test_a_stop_signal_reaches_the_child_and_the_job_ends_with_its_status(warm, env, tmp_path):
    job, marker = _waiting_job(tmp_path, env)
    job.send_signal(signal.SIGTERM)
    out, _ = job.communicate(timeout=60)
    assert marker.read_text() == "SIGTERM"  # the child's own handler ran
    assert "stopped" in out and job.returncode == 128 + signal.SIGTERM


def test_a_job_killed_outright_takes_its_child_with_it(warm, env, tmp_path):
    job, marker = _waiting_job(tmp_path, env)
    job.kill()  # SIGKILL (the out-of-memory killer's): the job cannot pass anything on
    out, _ = job.communicate(timeout=30)
    child = int(out.split("body pid=")[1].split()[0])
    _wait_for(lambda: not Path(f"/proc/{child}").exists(), 30)  # killed and reaped
    assert marker.read_text() == "waiting"  # no stop handler ran: killed, as the job was


def test_a_child_killed_by_a_signal_ends_its_job_by_the_same_signal(warm, env, tmp_path):
    job = _job(tmp_path, env, "kill")
    job.communicate("\n", timeout=60)
    assert job.returncode == -signal.SIGKILL


def test_without_a_warm_process_the_job_runs_itself_and_starts_one(env, tmp_path):
    path = _socket(env)
    job = _job(tmp_path, env, "exit")
    out, _ = job.communicate("\n", timeout=60)
    assert job.returncode == 3 and f"body pid={job.pid}" in out  # ran in its own process
    _wait_for(path.exists)  # ... and started a warm process for the next jobs
    pid = int(path.with_suffix(".lock").read_text().split()[0])
    job = _job(tmp_path, env, "exit")
    out, _ = job.communicate("\n", timeout=60)
    assert job.returncode == 3 and f"body pid={job.pid}" not in out
    os.kill(pid, signal.SIGTERM)


@pytest.mark.parametrize("setting", [{"FLYLIB_WARM": "0"}, {"SLURM_JOB_ID": "12"}])
def test_off_by_setting_and_on_a_batch_scheduler(env, tmp_path, setting):
    env = {**env, **setting}
    job = _job(tmp_path, env, "exit")
    out, _ = job.communicate("\n", timeout=60)
    assert job.returncode == 3 and f"body pid={job.pid}" in out
    time.sleep(1)
    assert not _socket(env).parent.exists() or not any(_socket(env).parent.iterdir())


def test_a_folder_others_may_enter_is_not_used(env, tmp_path):
    folder = _socket(env).parent
    folder.mkdir(mode=0o755)
    folder.chmod(0o755)
    job = _job(tmp_path, env, "exit")
    out, _ = job.communicate("\n", timeout=60)
    assert job.returncode == 3 and f"body pid={job.pid}" in out
    time.sleep(1)
    assert not any(folder.iterdir())


def test_the_warm_process_leaves_when_idle(env):
    path = _socket(env)
    path.parent.mkdir(mode=0o700)
    server = subprocess.run(
        [sys.executable, "-m", "flylib.warm", str(path), "0.5"], env=env, timeout=120
    )
    assert server.returncode == 0 and not path.exists()


def _outputs(root: Path) -> dict:
    """Each output file's content (``root/<recording>/...``): an HDF5 file's datasets,
    summary.json without its times, any other file's bytes (logs, Snakemake's benchmark
    files and the run's lock left out)."""
    import json

    import h5py

    def untimed(value):
        if isinstance(value, dict):
            clock = ("time", "second", "created")
            return {k: untimed(v) for k, v in value.items() if not any(c in k for c in clock)}
        return [untimed(v) for v in value] if isinstance(value, list) else value

    contents = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if not path.is_file() or rel.parts[1] in ("logs", "benchmarks", ".flylib.lock"):
            continue
        if path.suffix == ".h5":
            with h5py.File(path, "r") as f:
                names: list[str] = []
                f.visit(names.append)
                datasets = {
                    n: f[n][()].tobytes()
                    for n in names
                    if isinstance(f[n], h5py.Dataset) and f[n].shape
                }
            contents[str(rel)] = datasets
        elif path.name == "summary.json":
            contents[str(rel)] = untimed(json.loads(path.read_text()))
        else:
            contents[str(rel)] = path.read_bytes()
    return contents


def test_a_workflow_run_through_warm_processes_writes_what_a_run_without_them_writes(env, tmp_path):
    """The demo's 2-frame recording imported from its DeepLabCut files, run with warm
    processes and again (--forceall) without: the same artifacts, results, videos and
    figures, and the later jobs ran warm."""
    base = yaml.safe_load((Path(__file__).parents[2] / "config" / "config.yaml").read_text())
    config = {**base, "recordings": str(demo_batch(tmp_path / "batch", 1, base))}
    work = tmp_path / "work"
    work.mkdir()
    (work / "config.yaml").write_text(yaml.safe_dump({**config, "outdir": "results/{id}"}))
    outputs = {}
    for name, extra in (("warm", {}), ("cold", {"FLYLIB_WARM": "0"})):
        proc = subprocess.run(
            snakemake_command(work, "--cores", "1", "--forceall"),
            env={**env, **extra},
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        outputs[name] = _outputs(work / "results")
    # one warm process per thread count (Snakemake sets OMP_NUM_THREADS... per job)
    log = "".join(p.read_text() for p in _socket(env).parent.glob("*.log"))
    ran_warm = {line.split()[3].split(".", 1)[-1] for line in log.splitlines() if " in " in line}
    assert {"refinement.py", "assemble.py", "kinematics.py"} <= ran_warm, log
    assert outputs["warm"].keys() == outputs["cold"].keys()
    for name, content in outputs["cold"].items():
        assert outputs["warm"][name] == content, name
