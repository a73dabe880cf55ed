#!/usr/bin/env python
"""pose2d stage: 2D keypoints of one recording (detector, or another tool's files)."""

import argparse
from pathlib import Path

from flylib.config.loading import parse_json
from flylib.errors import ConfigError
from flylib.pipeline.pose2d import run_pose2d

from _cli import output_dir, path, run_script, script_main, script_parser


def _import_spec(text: str):
    """The --import-spec JSON, nesting bounded (a ConfigError line, not a traceback)."""
    try:
        return parse_json(text, "--import-spec")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def run(inputs, recording, out, *, import_spec=None, candidates_out=None, progress=False) -> None:
    """The 2D keypoints of ``recording`` into ``out`` (and the candidate peaks into
    ``candidates_out``)."""
    run_pose2d(
        inputs,
        recording,
        out,
        import_spec=import_spec,
        progress=progress,
        candidates_path=candidates_out,
    )


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job (``params.import_spec``: the
    recording's own import spec as JSON, ``null`` for the config's)."""
    return {
        "recording": path(job.params.recording),
        "out": path(job.output.out),
        "import_spec": parse_json(job.params.import_spec, "--import-spec"),
        "candidates_out": path(job.output.get("candidates_out")),
    }


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--recording", required=True, type=Path, help="recording directory")
    parser.add_argument("--out", required=True, type=Path, help="pose2d artifact to write (.h5)")
    parser.add_argument(
        "--import-spec",
        type=_import_spec,
        default=None,
        help="JSON pose2d.import spec for this recording (default: the config's)",
    )
    parser.add_argument(
        "--candidates-out",
        type=Path,
        default=None,
        help="also write the detector's top-K peaks here (for pictorial structures)",
    )
    parser.add_argument("--progress", action="store_true", help="show a progress bar")
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        stage="pose2d",
        outdir=lambda a: output_dir(a["out"]),
    )


if __name__ == "__main__":
    run_script(main, globals())
