"""Workflow benchmarks: a batch's planning time, each job's fixed cost, the submissions.

Every figure is measured for this checkout and, with ``--baseline DIR`` (a checkout of
the last release: ``git worktree add /tmp/rel <commit>``), for that one in the same
run, each with its own ``PYTHONPATH`` and Snakefile, in pairs whose order alternates
(A B, then B A, ...) so that a machine shared with other work loads both alike.

1. DAG time: ``snakemake --dry-run`` of N recordings (``--recordings 100,1000``): the
   demo's recording at 2 frames (7 videos, DeepLabCut CSVs) hard-linked N times and
   listed in a sheet with its 2D imported per recording, as a lab lists a batch (no
   detector weights needed). Wall clock and CPU, the best of ``--repeats`` after a first
   dry run, whose wall clock is printed apart: it reads every video's header, later ones
   find the frame counts in flylib's cache (``flylib.recordings.frame_counts.FrameCountCache``). A
   dry run longer than ``--cap`` seconds is stopped and reported as "> cap".
   Target: <= 20 s for 1,000 recordings.
2. Fixed cost per recording: one such recording of ``--frames`` frames (60: the demo's)
   run through ``snakemake --cores 1``; each job's wall time (its Snakemake benchmark
   file, the median of ``--repeats`` runs) against the stage's compute (the same stage
   function run a second time in one process: no process start, imports or JIT).
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
        [--repeats 3] [--frames 60] [--cap 600] [--skip-planning] [--skip-fixed]
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
import time
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


def bench_planning(checkouts: dict[str, Path], counts: list[int], cap: float, repeats: int):
    """``{n: {checkout: (wall, cpu)}}``: the best dry run of each batch size, and under
    ``"first"`` each checkout's first dry run's wall time (its frame-count cache empty:
    a cache folder of the benchmark's own)."""
    base = _base_config()
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for n in counts:
            config = {**base, "recordings": str(demo_batch(root / "batch", n, base))}
            work = _workdirs(root / f"plan{n}", checkouts, config)
            cache = {"FLYLIB_CACHE": str(root / f"cache{n}")}
            first = {}
            for name, repo in checkouts.items():  # also warms the imports and the file cache
                first[name] = _snakemake(repo, work[name], "--dry-run", cap=cap, env=cache)[0]
            runs: dict[str, list[tuple[float, float]]] = {name: [] for name in checkouts}
            for _, name, repo in _paired(checkouts, repeats):
                wall, cpu, _ = _snakemake(repo, work[name], "--dry-run", cap=cap, env=cache)
                runs[name].append((wall, cpu))
            results[n] = {name: min(r) for name, r in runs.items()} | {"first": first}
    return results


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


def _direct(workdir: Path, out: Path) -> None:
    """The stages of the batch's one recording run twice in this process; the second
    run's seconds (warm: imports done, JIT compiled) to ``out/compute.json``."""
    from flylib.config import Config
    from flylib.pipeline.planning import plan_recordings

    config = Config.from_yaml(workdir / "config.yaml")
    (rec,) = plan_recordings(config)
    _direct_stages(config, rec.path, out / "first", rec.import_spec)
    cpu = time.process_time()
    seconds = _direct_stages(config, rec.path, out / "second", rec.import_spec)
    cpu = time.process_time() - cpu
    (out / "compute.json").write_text(json.dumps({"wall": seconds, "cpu": cpu}))


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


def _print_planning(plan: dict, cap: float) -> None:
    for n, runs in plan.items():
        first = runs.pop("first")
        for name, (wall, cpu) in runs.items():
            if wall == float("inf"):
                print(f"DAG time, {n} recordings, {name}: > {cap:.0f} s (stopped)")
                continue
            target = f" (target <= 20 s: {'ok' if wall <= 20 else 'MISSED'})" if n == 1000 else ""
            print(
                f"DAG time (snakemake -n), {n:>5} recordings, {name:>8}: {wall:6.2f} s wall, "
                f"{cpu:6.2f} s CPU{target}"
            )
        print(
            "  first dry run (video headers read, no frame count cached): "
            + ", ".join(f"{name} {wall:.2f} s" for name, wall in first.items())
        )
        if "baseline" in runs and runs["baseline"][0] != float("inf"):
            print(
                f"  this checkout / baseline: {runs['this'][0] / runs['baseline'][0]:.2f} wall, "
                f"{runs['this'][1] / runs['baseline'][1]:.2f} CPU"
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
        _print_planning(bench_planning(checkouts, counts, args.cap, args.repeats), args.cap)
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
