"""Workflow benchmarks: planning time for many recordings, and the workflow's overhead.

1. Dry-run planning of N recordings (default 200; ``--recordings 1000,10000`` for a
   series): the demo's recording at 2 frames (7 videos, DeepLabCut CSVs) hard-linked N
   times and listed in a sheet with its 2D imported per recording, as a lab lists a
   batch (no detector weights needed). Wall-clock and CPU of ``snakemake --dry-run``
   against a 1-recording dry run measured in the same session (the fixed start-up
   cost), the ratio between them and the cost per extra recording (constant when the
   DAG scales linearly), and :func:`flylib.pipeline.planning.plan_recordings` alone.
   A dry run longer than ``--cap`` seconds is stopped and reported as "> cap".
   Target: < 10 s for 200 recordings.
2. Overhead of running the demo through Snakemake (one process per job) over calling
   the stage functions directly in one process. Target: < 30 %.

    python benchmarks/workflow.py [--recordings 200[,1000,...]] [--cap 600] [--frames 60]
                                  [--skip-overhead]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
sys.path.insert(0, str(REPO / "tests"))

from workflow_run import snakemake_command


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _snakemake(
    workdir: Path, *args: str, cpu: list | None = None, cap: float | None = None
) -> float:
    """Wall-clock seconds of one snakemake call; its CPU seconds are appended to ``cpu``
    (a figure that a busy machine inflates much less than the wall clock). A call
    longer than ``cap`` seconds is stopped: ``inf``."""
    cmd = snakemake_command(workdir, *args)
    cpu_before = _children_cpu()
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=cap)
    except subprocess.TimeoutExpired:
        if cpu is not None:
            cpu.append(float("inf"))
        return float("inf")
    elapsed = time.perf_counter() - start
    if cpu is not None:
        cpu.append(_children_cpu() - cpu_before)
    if proc.returncode != 0:
        raise SystemExit(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return elapsed


def _batch(root: Path, count: int, base: dict) -> Path:
    """A sheet of ``count`` recordings, each the demo's 2-frame recording hard-linked
    into a folder of its own with its 2D imported from its DeepLabCut CSVs."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_files, demo_import_spec, make_demo

    config = Config.from_dict(base)
    template = root / "template"
    if not template.is_dir():
        make_demo(config, template, frames=2)
    spec = demo_import_spec(config)
    names = demo_files(config)
    files = ";".join(f"{view}={name}" for view, name in spec["files"].items())
    rows = ["path\timport_format\timport_files"]
    for i in range(count):
        rec = root / "data" / f"rec{i:05d}"
        if not rec.is_dir():
            rec.mkdir(parents=True)
            for name in (*names["footage"], *names["dlc"]):
                os.link(template / name, rec / name)
        rows.append(f"{rec}\t{spec['format']}\t{files}")
    sheet = root / f"recordings_{count}.tsv"
    sheet.write_text("\n".join(rows) + "\n")
    return sheet


def bench_planning(counts: list[int], cap: float) -> dict:
    """Dry-run seconds (wall, CPU) of 1 recording (the baseline) and of each count."""
    from flylib.config import Config
    from flylib.pipeline.planning import plan_recordings

    base = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for n in [1, *counts]:
            config = {**base, "recordings": str(_batch(root, n, base))}
            (root / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
            cpu: list[float] = []
            if n == 1:  # warm the imports and the file cache; best of two
                _snakemake(root, "--dry-run")
                wall = min(_snakemake(root, "--dry-run", cpu=cpu) for _ in range(2))
            else:
                wall = _snakemake(root, "--dry-run", cpu=cpu, cap=cap)
            start = time.perf_counter()
            plan_recordings(Config.from_dict(config))
            results[n] = {"wall": wall, "cpu": min(cpu), "plan": time.perf_counter() - start}
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
    base = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    base["demo"] = {**(base.get("demo") or {}), "frames": frames}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        config_path = root / "config.yaml"
        config_path.write_text(yaml.safe_dump(base, sort_keys=False))
        _snakemake(root, "--cores", "1", "demo")  # the demo recording, made by its rule
        # the direct pipeline runs in a fresh process of its own (this one has written
        # and opened thousands of videos for the planning benchmark)
        cpu_before = _children_cpu()
        start = time.perf_counter()
        subprocess.run([sys.executable, __file__, "--direct", str(root)], check=True)
        direct = time.perf_counter() - start
        direct_cpu = _children_cpu() - cpu_before
        cpu: list[float] = []
        workflow = _snakemake(root, "--cores", "1", cpu=cpu)
    return {
        "direct": direct,
        "workflow": workflow,
        "direct cpu": direct_cpu,
        "workflow cpu": cpu[0],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--recordings", default="200", help="batch sizes, comma-separated (e.g. 1000,10000)"
    )
    parser.add_argument(
        "--cap", type=float, default=600.0, help="stop a dry run after this many seconds"
    )
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--skip-overhead", action="store_true")
    parser.add_argument("--skip-planning", action="store_true")
    parser.add_argument("--direct", type=Path, help=argparse.SUPPRESS)  # internal: one process
    args = parser.parse_args()
    if args.direct:
        from flylib.config import Config

        root = args.direct
        (root / "direct").mkdir()
        config = Config.from_yaml(root / "config.yaml")
        _direct_pipeline(config, root / "demo", root / "direct", root / "demo" / "truth.h5")
        return

    if not args.skip_planning:
        counts = [int(n) for n in args.recordings.split(",")]
        plan = bench_planning(counts, args.cap)
        one = plan[1]
        print(
            f"dry run, 1 recording:   {one['wall']:7.2f} s wall, {one['cpu']:7.2f} s CPU "
            "(Snakemake start-up and parse: the baseline)"
        )
        for n in counts:
            many = plan[n]
            if many["wall"] == float("inf"):
                print(f"dry run, {n} recordings: > {args.cap:.0f} s (stopped)")
                continue
            target = (
                f" (target < 10 s: {'ok' if many['wall'] < 10 else 'MISSED'})" if n <= 200 else ""
            )
            print(
                f"dry run, {n} recordings: {many['wall']:7.2f} s wall, {many['cpu']:7.2f} s CPU"
                f"{target}; ratio to baseline {many['wall'] / one['wall']:.1f} wall, "
                f"{many['cpu'] / one['cpu']:.1f} CPU; per extra recording "
                f"{(many['wall'] - one['wall']) / (n - 1) * 1000:.1f} ms wall, "
                f"{(many['cpu'] - one['cpu']) / (n - 1) * 1000:.1f} ms CPU; "
                f"plan_recordings alone {many['plan']:.2f} s"
            )
    if args.skip_overhead:
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
