"""Workflow benchmarks: planning time for many recordings, and the workflow's overhead.

1. Dry-run planning of N recordings (default 200, tiny 2-frame videos, 7 cameras):
   wall-clock of ``snakemake --dry-run`` against a 1-recording dry run measured in the
   same session (the fixed start-up cost), and of :func:`flylib.pipeline.planning.plan_recordings`
   alone. Target: < 10 s for 200 recordings.
2. Overhead of running the demo through Snakemake (one process per job) over calling
   the stage functions directly in one process. Target: < 30 %.

    python benchmarks/workflow.py [--recordings 200] [--frames 60] [--skip-overhead]
"""

from __future__ import annotations

import argparse
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
sys.path.insert(0, str(REPO / "tests"))

from workflow_run import snakemake_command


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _snakemake(workdir: Path, *args: str, cpu: list | None = None) -> float:
    """Wall-clock seconds of one snakemake call; its CPU seconds are appended to ``cpu``
    (a figure that a busy machine inflates much less than the wall clock)."""
    cmd = snakemake_command(workdir, *args)
    cpu_before = _children_cpu()
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if cpu is not None:
        cpu.append(_children_cpu() - cpu_before)
    if proc.returncode != 0:
        raise SystemExit(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return elapsed


def _tiny_recordings(root: Path, count: int, sources: list[dict]) -> list[str]:
    from flylib.io import VideoWriter

    template = root / "template"
    template.mkdir(parents=True)
    for s in sources:
        with VideoWriter(template / s["filename"], fps=10) as writer:
            writer.write_frames(np.zeros((2, 16, 16, 3), np.uint8))
    dirs = []
    for i in range(count):
        rec = root / f"rec{i:03d}"
        shutil.copytree(template, rec)
        dirs.append(str(rec))
    return dirs


def bench_planning(n: int) -> dict:
    from flylib.config import Config
    from flylib.pipeline.planning import plan_recordings

    base = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        dirs = _tiny_recordings(root / "data", n, base["sources"])
        results = {}
        for label, recs in (("1 recording", dirs[:1]), (f"{n} recordings", dirs)):
            config = {**base, "recordings": recs}
            (root / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
            _snakemake(root, "--dry-run")  # warm the file cache and the effective config
            cpu: list[float] = []
            results[label] = min(_snakemake(root, "--dry-run", cpu=cpu) for _ in range(2))
            results[f"{label} cpu"] = min(cpu)
        cfg = Config.from_dict({**base, "recordings": dirs})
        start = time.perf_counter()
        plan_recordings(cfg)
        results["plan_recordings alone"] = time.perf_counter() - start
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
    parser.add_argument("--recordings", type=int, default=200)
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
        n = args.recordings
        plan = bench_planning(n)
        one, many = plan["1 recording"], plan[f"{n} recordings"]
        print(
            f"dry run, 1 recording:   {one:6.2f} s wall, {plan['1 recording cpu']:6.2f} s CPU "
            "(Snakemake start-up and parse: the baseline)"
        )
        print(
            f"dry run, {n} recordings: {many:6.2f} s wall, {plan[f'{n} recordings cpu']:6.2f} s CPU "
            f"(target < 10 s: {'ok' if many < 10 else 'MISSED'}); "
            f"{(many - one) / max(n - 1, 1) * 1000:.1f} ms wall per extra recording; "
            f"ratio to baseline {many / one:.2f}"
        )
        print(f"plan_recordings alone ({n} recordings): {plan['plan_recordings alone']:6.2f} s")
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
