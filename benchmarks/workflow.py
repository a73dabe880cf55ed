"""Workflow benchmarks: a batch's planning time, each job's fixed cost, the submissions.

Every figure is measured for this checkout and, with ``--baseline DIR`` (a checkout of
the last release: ``git worktree add /tmp/rel <commit>``), for that one in the same
run, each with its own ``PYTHONPATH`` and Snakefile, in pairs whose order alternates
(A B, then B A, ...) so that a machine shared with other work loads both alike.

1. Planning table: ``snakemake --dry-run`` of N recordings (``--recordings
   100,1000,10000``): the demo's recording at 2 frames (7 videos, DeepLabCut CSVs)
   hard-linked N times and listed in a sheet with its 2D imported per recording, as a
   lab lists a batch (no detector weights needed). Per checkout its first dry run
   (cold: flylib's frame-count cache empty, every video's header read) and the best of
   ``--repeats`` later ones (warm: the counts cached; one run above 1,000 recordings):
   wall clock, CPU and peak memory of the whole run and of its part up to Snakemake's
   "Building DAG of jobs..." (Snakemake's start, the Snakefile, flylib's planning:
   flylib's part; the rest, the DAG and the job listing, Snakemake's, flylib's input
   functions included). "snakemake alone" is a Snakefile of the same shape (seven plain
   ``shell:`` jobs per recording, no flylib): Snakemake's own floor. A dry run longer
   than ``--cap`` (the baseline's: ``--baseline-cap``) seconds is stopped ("> cap").
   Targets: 1,000 recordings <= 20 s cold; 10,000 <= 120 s and <= 2 GB cold.
2. Fixed cost per recording: one such recording of ``--frames`` frames (60: the demo's)
   run through ``snakemake --cores 1``; each job's wall time (its Snakemake benchmark
   file, the median of ``--repeats`` runs) against the stage's compute (the same stage
   function run again in one process, the least of three warm runs: no process start,
   imports or JIT).
   Fixed cost = job - compute (process start, Snakemake's script preamble, imports,
   JIT compilation, re-reading the config). Target: the CPU stages' total at most 0.6
   of the baseline's. The first run's jobs' total is printed apart, as a batch's first
   recording (its file cache cold); the table is the median of the later runs, as its
   later recordings.
3. SLURM submissions of a batch of 3 recordings: the jobs and job groups that
   ``snakemake --profile profiles/slurm --dry-run`` would submit (no cluster needed;
   tests/workflow/test_slurm.py counts the real sbatch calls).
4. (``--overhead``) The demo through Snakemake (one process per job) against the stage
   functions called directly in one process.

    python benchmarks/workflow.py [--recordings 100,1000] [--baseline /tmp/rel]
        [--repeats 3] [--frames 60] [--cap 600] [--baseline-cap S] [--skip-planning]
        [--skip-fixed]
        [--skip-slurm] [--overhead]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from math import inf
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
sys.path.insert(0, str(REPO / "tests"))

from flylib.stages import REGISTRY  # noqa: E402

from workflow_run import SNAKEMAKE, demo_batch

#: The stages of one recording a default run makes jobs of, in registry order (the
#: registry owns the list; pose2d, bundle adjustment, triangulation, refinement first).
CPU_STAGES = tuple(s.name for s in REGISTRY if s.default_on is not False)


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _command(repo: Path, workdir: Path, *args: str) -> list[str]:
    """``snakemake`` on ``repo``'s Snakefile in ``workdir`` with its ``config.yaml``."""
    return [
        str(SNAKEMAKE),
        "--snakefile",
        str(repo / "Snakefile"),
        "--directory",
        str(workdir),
        "--configfile",
        str(workdir / "config.yaml"),
        "--replace-workflow-config",
        *args,
    ]


def _env(repo: Path) -> dict[str, str]:
    """The environment that runs ``repo``'s flylib (its own ``src`` first)."""
    return {**os.environ, "PYTHONPATH": str(repo / "src")}


def _snakemake(
    repo: Path, workdir: Path, *args: str, cap: float | None = None, env: dict | None = None
) -> tuple[float, float, str]:
    """Wall-clock and CPU seconds of one snakemake call, and its output. A call longer
    than ``cap`` seconds is stopped: ``inf``."""
    cpu_before = _children_cpu()
    start = time.perf_counter()
    try:
        proc = subprocess.run(
            _command(repo, workdir, *args),
            capture_output=True,
            text=True,
            timeout=cap,
            env={**_env(repo), **(env or {})},
        )
    except subprocess.TimeoutExpired:
        return float("inf"), float("inf"), ""
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return elapsed, _children_cpu() - cpu_before, proc.stdout + proc.stderr


def _paired(checkouts: dict[str, Path], repeats: int):
    """``(repeat, name, repo)`` in pairs whose order alternates."""
    names = list(checkouts)
    for i in range(repeats):
        for name in names if i % 2 == 0 else names[::-1]:
            yield i, name, checkouts[name]


def _workdirs(root: Path, checkouts: dict[str, Path], config: dict) -> dict[str, Path]:
    """A working directory per checkout (its outputs under ``results/``): each checkout's
    own default config with the tables ``config`` changes from this checkout's (a release
    may not know a key this checkout added)."""
    changed = {k: v for k, v in config.items() if _base_config().get(k) != v}
    dirs = {}
    for name, repo in checkouts.items():
        work = root / name
        work.mkdir(parents=True, exist_ok=True)
        own = {**_base_config(repo), **changed, "outdir": "results/{id}"}
        (work / "config.yaml").write_text(yaml.safe_dump(own, sort_keys=False))
        dirs[name] = work
    return dirs


def _base_config(repo: Path = REPO) -> dict:
    return yaml.safe_load((repo / "config" / "config.yaml").read_text())


#: Snakemake prints this once the Snakefile is read, flylib's planning done, and the DAG begins.
DAG_LINE = "Building DAG of jobs..."


def _cpu_rss(pid: int) -> tuple[float, float]:
    """CPU seconds and peak resident GB of a running process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    status = Path(f"/proc/{pid}/status").read_text()
    return cpu, int(re.search(r"VmHWM:\s+(\d+)", status)[1]) / 1e6


def _plan(command: list[str], env: dict, cap: float) -> dict:
    """One dry run: ``{"wall", "cpu", "gb"}`` of the whole of it and, under ``"flylib"``, of
    its start up to :data:`DAG_LINE` (Snakemake's start, the Snakefile and flylib's planning:
    flylib's part; the rest is Snakemake's DAG and job listing). All ``inf``: stopped at ``cap``."""
    start = time.perf_counter()
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    timer = threading.Timer(cap, proc.kill)
    timer.start()
    flylib, tail = None, []
    for line in proc.stdout:
        if flylib is None and line.startswith(DAG_LINE):
            cpu, gb = _cpu_rss(proc.pid)
            flylib = {"wall": time.perf_counter() - start, "cpu": cpu, "gb": gb}
        tail = [*tail[-40:], line]
    _, status, usage = os.wait4(proc.pid, 0)
    timer.cancel()
    if os.waitstatus_to_exitcode(status) == -9:
        return {"wall": inf, "cpu": inf, "gb": inf, "flylib": None}
    if status != 0 or flylib is None:
        raise SystemExit("snakemake failed:\n" + "".join(tail))
    return {
        "wall": time.perf_counter() - start,
        "cpu": usage.ru_utime + usage.ru_stime,
        "gb": usage.ru_maxrss / 1e6,
        "flylib": flylib,
    }


def _floor_snakefile(root: Path, count: int) -> Path:
    """Snakemake alone: a Snakefile of the plan's shape (``count`` recordings, one job per
    stage of a default run, each reading the artifacts made before it, the last two
    assemble's) with plain ``shell:`` rules: no input functions, params, resources, scripts,
    groups or flylib."""
    final = ["assemble", "kinematics", "visualization"]
    rules = [f"rule all:\n    input: expand('out/{{i}}/{{f}}', i=range({count}), f={final})\n"]
    done: list[str] = []
    for stage in CPU_STAGES:
        inputs = ["assemble"] if stage in final[1:] else done
        rules.append(
            f"rule {stage}:\n    input: {[f'out/{{i}}/{d}' for d in inputs] or ['src']}\n"
            f"    output: 'out/{{i}}/{stage}'\n    shell: 'touch {{output}}'\n"
        )
        done.append(stage)
    snakefile = root / "Snakefile"
    snakefile.write_text("\n".join(rules))
    (root / "src").touch()
    return snakefile


def bench_planning(
    checkouts: dict[str, Path], counts: list[int], caps: dict[str, float], repeats: int
):
    """Yields ``{n: {checkout: {"cold": run, "warm": run}, "snakemake alone": run}}`` (runs as
    :func:`_plan`): each checkout's first dry run of ``n`` recordings (its frame-count cache
    empty: a cache folder of the benchmark's own), the best (CPU) of ``repeats`` later ones
    (one above 1,000 recordings), and Snakemake alone on a DAG of that shape. A checkout's
    dry runs stop at its ``caps`` seconds."""
    base = _base_config()
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for n in counts:
            config = {**base, "recordings": str(demo_batch(root / "batch", n, base))}
            work = _workdirs(root / f"plan{n}", checkouts, config)
            results[n] = {name: {"cold": None, "warm": []} for name in checkouts}
            for name, repo in checkouts.items():
                env = {**_env(repo), "FLYLIB_CACHE": str(root / f"cache{n}-{name}")}
                command = _command(repo, work[name], "--dry-run")
                results[n][name]["cold"] = _plan(command, env, caps[name])
            for _, name, repo in _paired(checkouts, repeats if n <= 1000 else 1):
                if results[n][name]["cold"]["wall"] == inf:
                    continue
                env = {**_env(repo), "FLYLIB_CACHE": str(root / f"cache{n}-{name}")}
                command = _command(repo, work[name], "--dry-run")
                results[n][name]["warm"].append(_plan(command, env, caps[name]))
            for runs in results[n].values():
                runs["warm"] = min(runs["warm"], key=lambda r: r["cpu"], default=None)
            floor = root / f"floor{n}"
            floor.mkdir()
            command = [str(SNAKEMAKE), "-s", str(_floor_snakefile(floor, n)), "-d", str(floor)]
            alone = _plan([*command, "--dry-run"], dict(os.environ), caps["this"])
            results[n]["snakemake alone"] = alone
            yield {n: results[n]}


def _job_seconds(outdir: Path) -> dict[str, float]:
    """Each job's wall seconds from its Snakemake benchmark file."""
    seconds = {}
    for stage in CPU_STAGES:
        path = outdir / "benchmarks" / f"{stage}.tsv"
        if path.is_file():
            rows = list(csv.DictReader(path.open(), delimiter="\t"))
            seconds[stage] = float(rows[-1]["s"])
    return seconds


def bench_fixed(checkouts: dict[str, Path], frames: int, repeats: int) -> dict:
    """``{checkout: {"job": {stage: s}, "compute": {stage: s}, "jobs cpu": s,
    "compute cpu": s}}`` for one recording: the jobs' wall seconds (median of the runs)
    and the CPU seconds of all its jobs together (a run's minus its dry run's, the
    least of the runs: a busy machine inflates CPU time much less than wall time)."""
    base = _base_config()
    base["pipeline"]["do_kinematics"] = True
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        config = {**base, "recordings": str(demo_batch(root / "batch", 1, base, frames=frames))}
        work = _workdirs(root, checkouts, config)
        jobs: dict[str, list[dict[str, float]]] = {name: [] for name in checkouts}
        cpu: dict[str, list[float]] = {name: [] for name in checkouts}
        for _, name, repo in _paired(checkouts, repeats):
            _, planning, _ = _snakemake(repo, work[name], "--cores", "1", "--forceall", "-n")
            _, run, _ = _snakemake(repo, work[name], "--cores", "1", "--forceall")
            jobs[name].append(_job_seconds(work[name] / "results" / "rec00000"))
            cpu[name].append(run - planning)
        results = {}
        for name, repo in checkouts.items():
            out = root / f"direct-{name}"
            subprocess.run(
                [sys.executable, __file__, "--direct", str(work[name]), str(out)],
                check=True,
                env=_env(repo),
            )
            compute = json.loads((out / "compute.json").read_text())
            later = jobs[name][1:] or jobs[name]
            results[name] = {
                "first": sum(jobs[name][0].values()),
                "job": {s: statistics.median(r[s] for r in later) for s in jobs[name][0]},
                "compute": compute["wall"],
                "jobs cpu": min(cpu[name]),
                "compute cpu": compute["cpu"],
            }
    return results


def _direct_stages(config, rec_dir: Path, out: Path, spec: dict) -> dict[str, float]:
    """Run one recording's CPU stages in this process; each stage's seconds."""
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.bundle_adjustment import run_bundle_adjustment
    from flylib.pipeline.inputs import stage_inputs
    from flylib.pipeline.kinematics import run_kinematics
    from flylib.pipeline.pose2d import run_pose2d
    from flylib.pipeline.refinement import run_refinement
    from flylib.pipeline.triangulation import run_triangulation
    from flylib.pipeline.visualization import run_visualization
    from flylib.results.artifacts import artifact_path

    out.mkdir(parents=True, exist_ok=True)
    path = {s: artifact_path(out, s) for s in CPU_STAGES[:4]}
    seconds = {}

    def timed(stage, run, *args, **kwargs):
        start = time.perf_counter()
        run(stage_inputs(config, stage), *args, **kwargs)
        seconds[stage] = time.perf_counter() - start

    timed("pose2d", run_pose2d, rec_dir, path["pose2d"], import_spec=spec)
    ba = path["bundle_adjustment"]
    timed("bundle_adjustment", run_bundle_adjustment, path["pose2d"], ba, recording_dir=rec_dir)
    tri = path["triangulation"]
    timed(
        "triangulation", run_triangulation, path["pose2d"], tri, ba_path=ba, recording_dir=rec_dir
    )
    timed(
        "refinement",
        run_refinement,
        path["pose2d"],
        tri,
        path["refinement"],
        ba_path=ba,
        recording_dir=rec_dir,
    )
    timed("assemble", run_assemble, {**path}, out, recording_dir=rec_dir)
    timed("visualization", run_visualization, out / "results.h5", rec_dir, out)
    timed("kinematics", run_kinematics, out / "results.h5", out)
    return seconds


def _direct(workdir: Path, out: Path, warm_runs: int = 3) -> None:
    """The stages of the batch's one recording run 1 + ``warm_runs`` times in this process;
    the least of the warm runs' seconds per stage and CPU seconds (imports done, JIT
    compiled; a single run on a shared machine can be doubled) to ``out/compute.json``."""
    from flylib.config import Config
    from flylib.pipeline.planning import plan_recordings

    config = Config.from_yaml(workdir / "config.yaml")
    (rec,) = plan_recordings(config)
    _direct_stages(config, rec.path, out / "first", rec.import_spec)
    runs, cpus = [], []
    for k in range(warm_runs):
        cpu = time.process_time()
        runs.append(_direct_stages(config, rec.path, out / f"warm{k}", rec.import_spec))
        cpus.append(time.process_time() - cpu)
    seconds = {stage: min(run[stage] for run in runs) for stage in runs[0]}
    (out / "compute.json").write_text(json.dumps({"wall": seconds, "cpu": min(cpus)}))


def bench_submissions(checkouts: dict[str, Path], count: int = 3) -> dict[str, int]:
    """The SLURM submissions of a batch: jobs and job groups of a dry run through
    ``profiles/slurm`` (local rules left out)."""
    base = _base_config()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        config = {**base, "recordings": str(demo_batch(root / "batch", count, base))}
        work = _workdirs(root, checkouts, config)
        for name, repo in checkouts.items():
            _, _, text = _snakemake(
                repo, work[name], "--profile", str(repo / "profiles" / "slurm"), "--dry-run"
            )
            groups = len(re.findall(r"^\[[^\]]*\] Group job", text, re.M))
            jobs = [r for r in re.findall(r"^rule (\w+):", text, re.M) if r != "all"]
            results[name] = groups + len(jobs)
    return results


def _direct_pipeline(config, rec_dir: Path, out: Path, truth: Path) -> None:
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.bundle_adjustment import run_bundle_adjustment
    from flylib.pipeline.demo import demo_import_spec
    from flylib.pipeline.inputs import stage_inputs
    from flylib.pipeline.pose2d import run_pose2d
    from flylib.pipeline.triangulation import run_triangulation
    from flylib.pipeline.visualization import run_visualization
    from flylib.results.artifacts import artifact_path

    p2d = artifact_path(out, "pose2d")
    ba = artifact_path(out, "bundle_adjustment")
    tri = artifact_path(out, "triangulation")
    run_pose2d(stage_inputs(config, "pose2d"), rec_dir, p2d, import_spec=demo_import_spec(config))
    run_bundle_adjustment(stage_inputs(config, "bundle_adjustment"), p2d, ba, recording_dir=rec_dir)
    run_triangulation(
        stage_inputs(config, "triangulation"), p2d, tri, ba_path=ba, recording_dir=rec_dir
    )
    run_assemble(
        stage_inputs(config, "assemble"),
        {"pose2d": p2d, "bundle_adjustment": ba, "triangulation": tri},
        out,
        recording_dir=rec_dir,
        truth_path=truth,
    )
    run_visualization(stage_inputs(config, "visualization"), out / "results.h5", rec_dir, out)


def bench_overhead(frames: int) -> dict:
    """The demo through ``snakemake --cores 1`` against its stage functions called
    directly in one fresh process (this checkout only)."""
    base = _base_config()
    base["demo"] = {**(base.get("demo") or {}), "frames": frames}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "config.yaml").write_text(yaml.safe_dump(base, sort_keys=False))
        _snakemake(REPO, root, "--cores", "1", "demo")  # the demo recording, made by its rule
        cpu_before = _children_cpu()
        start = time.perf_counter()
        subprocess.run([sys.executable, __file__, "--direct-demo", str(root)], check=True)
        direct = time.perf_counter() - start
        direct_cpu = _children_cpu() - cpu_before
        workflow, workflow_cpu, _ = _snakemake(REPO, root, "--cores", "1")
    return {
        "direct": direct,
        "workflow": workflow,
        "direct cpu": direct_cpu,
        "workflow cpu": workflow_cpu,
    }


def _print_planning(plan: dict, caps: dict[str, float], header: bool = True) -> None:
    """The planning table: per batch size and checkout, the first (cold) and a later (warm)
    dry run: wall, CPU, peak memory, and flylib's part of each (up to the DAG line)."""
    if header:
        print(
            "planning (snakemake --dry-run; cold: the frame-count cache empty, warm: filled); "
            "flylib = Snakemake's start, the Snakefile and flylib's planning, up to "
            f"'{DAG_LINE}'; Snakemake = the DAG and the job listing after it"
        )
        print(f"{'':32}{'whole dry run':>26}{'flylib':>24}{'Snakemake':>16}")
        print(
            f"{'recordings':>10} {'checkout':>15} {'cache':>5}"
            + f"{'wall s':>8}{'CPU s':>8}{'peak GB':>10}" * 2
            + f"{'wall s':>8}{'CPU s':>8}"
        )
    for n, runs in plan.items():
        for name, run in runs.items():
            for cache, r in [("", run)] if name == "snakemake alone" else run.items():
                line = f"{n:>10} {name:>15} {cache:>5}"
                if r is None or r["wall"] == inf:
                    cap = caps.get(name, caps["this"])
                    print(f"{line}{'> ' + format(cap, '.0f'):>8} (stopped at the cap)")
                    continue
                f = r["flylib"]
                print(
                    line
                    + "".join(f"{x['wall']:8.1f}{x['cpu']:8.1f}{x['gb']:10.2f}" for x in (r, f))
                    + f"{r['wall'] - f['wall']:8.1f}{r['cpu'] - f['cpu']:8.1f}"
                )
        if n == 1000 and runs["this"]["cold"]["wall"] != inf:
            wall = runs["this"]["cold"]["wall"]
            print(
                f"  1,000 cold: {wall:.1f} s wall (target <= 20 s: "
                f"{'ok' if wall <= 20 else 'MISSED'})"
            )
        if n == 10000 and runs["this"]["cold"]["wall"] != inf:
            r = runs["this"]["cold"]
            ok = r["wall"] <= 120 and r["gb"] <= 2
            print(
                f"  10,000 cold: {r['wall']:.1f} s wall, {r['gb']:.2f} GB (target <= 120 s, "
                f"<= 2 GB: {'ok' if ok else 'MISSED'})"
            )


def _print_fixed(fixed: dict, frames: int) -> None:
    names = list(fixed)
    print(
        f"per recording ({frames} frames), seconds: job (Snakemake benchmark file, median "
        "of the runs after the first), compute (warm, in one process), fixed = job - compute"
    )
    print(
        f"{'stage':18s}" + "".join(f"{n + ' job':>15s}{'compute':>9s}{'fixed':>8s}" for n in names)
    )
    totals = {n: [0.0, 0.0, 0.0] for n in names}
    for stage in CPU_STAGES:
        line = f"{stage:18s}"
        for n in names:
            job = fixed[n]["job"].get(stage, float("nan"))
            compute = fixed[n]["compute"].get(stage, float("nan"))
            line += f"{job:15.2f}{compute:9.2f}{job - compute:8.2f}"
            for k, v in enumerate((job, compute, job - compute)):
                totals[n][k] += v
        print(line)
    print(
        f"{'all CPU stages':18s}"
        + "".join(f"{t[0]:15.2f}{t[1]:9.2f}{t[2]:8.2f}" for t in totals.values())
    )
    print("first run, jobs' total: " + ", ".join(f"{n} {fixed[n]['first']:.2f} s" for n in names))
    for n in names:
        jobs_cpu, compute_cpu = fixed[n]["jobs cpu"], fixed[n]["compute cpu"]
        print(
            f"CPU seconds, {n}: all jobs {jobs_cpu:.2f}, compute {compute_cpu:.2f}, "
            f"fixed {jobs_cpu - compute_cpu:.2f}"
        )
    if "baseline" in totals:
        cpu_fixed = {n: fixed[n]["jobs cpu"] - fixed[n]["compute cpu"] for n in names}
        print(
            f"fixed CPU, this checkout / baseline: {cpu_fixed['this'] / cpu_fixed['baseline']:.2f}"
        )
        ratio = totals["this"][2] / totals["baseline"][2]
        print(
            f"fixed cost, this checkout / baseline: {ratio:.2f} "
            f"(target <= 0.6: {'ok' if ratio <= 0.6 else 'MISSED'}); jobs' total "
            f"{totals['this'][0] / totals['baseline'][0]:.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recordings", default="100,1000", help="batch sizes, comma-separated")
    parser.add_argument("--baseline", type=Path, help="a checkout of the last release")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cap", type=float, default=600.0, help="stop a dry run after this")
    parser.add_argument("--baseline-cap", type=float, help="the baseline's (default: --cap)")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--skip-planning", action="store_true")
    parser.add_argument("--skip-fixed", action="store_true")
    parser.add_argument("--skip-slurm", action="store_true")
    parser.add_argument("--overhead", action="store_true")
    parser.add_argument("--direct", nargs=2, type=Path, help=argparse.SUPPRESS)  # internal
    parser.add_argument("--direct-demo", type=Path, help=argparse.SUPPRESS)  # internal
    args = parser.parse_args()
    if args.direct:
        _direct(*args.direct)
        return
    if args.direct_demo:
        from flylib.config import Config

        root = args.direct_demo
        (root / "direct").mkdir()
        config = Config.from_yaml(root / "config.yaml")
        _direct_pipeline(config, root / "demo", root / "direct", root / "demo" / "truth.h5")
        return

    checkouts = {"this": REPO}
    if args.baseline:
        checkouts["baseline"] = args.baseline.resolve()
    print("checkouts: " + ", ".join(f"{n} = {p}" for n, p in checkouts.items()), flush=True)
    if not args.skip_planning:
        counts = [int(n) for n in args.recordings.split(",")]
        caps = {"this": args.cap, "baseline": args.baseline_cap or args.cap}
        for n, plan in enumerate(bench_planning(checkouts, counts, caps, args.repeats)):
            _print_planning(plan, caps, header=n == 0)
    if not args.skip_fixed:
        _print_fixed(bench_fixed(checkouts, args.frames, args.repeats), args.frames)
    if not args.skip_slurm:
        for name, count in bench_submissions(checkouts).items():
            print(f"SLURM submissions for 3 recordings, {name}: {count}")
    if not args.overhead:
        return
    over = bench_overhead(args.frames)
    ratio = over["workflow"] / over["direct"] - 1
    ratio_cpu = over["workflow cpu"] / over["direct cpu"] - 1
    print(
        f"demo ({args.frames} frames), stage functions in one process: "
        f"{over['direct']:6.2f} s wall, {over['direct cpu']:6.2f} s CPU"
    )
    print(
        f"demo ({args.frames} frames), snakemake --cores 1:            "
        f"{over['workflow']:6.2f} s wall, {over['workflow cpu']:6.2f} s CPU"
    )
    print(
        f"workflow overhead: {100 * ratio:.0f} % wall, {100 * ratio_cpu:.0f} % CPU "
        f"(target < 30 %: {'ok' if ratio < 0.3 else 'MISSED'})"
    )


if __name__ == "__main__":
    main()
