#!/usr/bin/env python
"""export_nwb: one recording's results.h5 as an NWB file (ndx-pose), with the session
metadata of the config's nwb table and the recording's nwb.yaml."""

from pathlib import Path

from flylib.pipeline.export_nwb import NwbExportInputs, run_export_nwb

from _cli import path, run_script, script_main, script_parser


def run(inputs, results, recording, output, *, angles=None, demo=False) -> None:
    """Export ``results`` (and the joint ``angles``) as the NWB file ``output``."""
    run_export_nwb(inputs, results, output, recording_dir=recording, demo=demo, angles_path=angles)


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job (``input.angles``: none, or one file)."""
    return {
        "results": path(job.input.results),
        "recording": path(job.params.recording),
        "output": path(job.output.output),
        "angles": path(job.input.angles),
        "demo": bool(job.params.demo),
    }


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--results", required=True, type=Path, help="results.h5 of the recording")
    parser.add_argument(
        "--recording",
        required=True,
        type=Path,
        help="recording directory (footage linked from the NWB file, nwb.yaml)",
    )
    parser.add_argument("--output", required=True, type=Path, help="destination .nwb file")
    parser.add_argument(
        "--angles",
        type=Path,
        default=None,
        help="neuromechfly.h5 of the recording: its joint angles go in the NWB file too",
    )
    parser.add_argument(
        "--demo",
        action="store_true",
        help="the recording is the embedded demo (its synthetic session metadata applies)",
    )
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        stage=NwbExportInputs,
        outdir=lambda a: a["output"].parent,
    )


if __name__ == "__main__":
    run_script(main, globals())
