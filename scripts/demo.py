#!/usr/bin/env python
"""Generate the embedded synthetic demo recording (footage, DeepLabCut CSVs, truth.h5)."""

from pathlib import Path

from flylib.pipeline.demo import DemoInputs, run_demo

from _cli import path, run_script, script_main, script_parser


def run(inputs, out) -> None:
    """Write the demo recording into ``out``."""
    run_demo(inputs, out)


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--out", required=True, type=Path, help="demo recording directory to write")
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=lambda job: {"out": path(job.params.out)},
        stage=DemoInputs,
    )


if __name__ == "__main__":
    run_script(main, globals())
