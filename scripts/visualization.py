#!/usr/bin/env python
"""visualization stage: render the configured videos of one recording."""

from pathlib import Path

from flylib.pipeline.visualization import run_visualization

from _cli import path, run_script, script_main, script_parser


def run(inputs, results, recording, outdir, *, progress=False, speed=None) -> None:
    """Render the videos of ``results`` over ``recording``'s footage into ``outdir``."""
    run_visualization(inputs, results, recording, outdir, progress=progress, speed=speed)


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job."""
    speed = job.params.speed
    return {
        "results": path(job.input.results),
        "recording": path(job.params.recording),
        "outdir": path(job.wildcards.outdir),
        "speed": None if speed is None else float(speed),
    }


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--results", required=True, type=Path, help="results.h5 of the recording")
    parser.add_argument(
        "--recording", required=True, type=Path, help="recording directory (footage)"
    )
    parser.add_argument("--outdir", required=True, type=Path, help="where the videos go")
    parser.add_argument("--progress", action="store_true", help="show a progress bar")
    parser.add_argument(
        "--speed",
        type=float,
        help="play the videos at this multiple of the recording's rate when the config sets none",
    )
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        stage="visualization",
        outdir=lambda a: a["outdir"],
    )


if __name__ == "__main__":
    run_script(main, globals())
