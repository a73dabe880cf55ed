#!/usr/bin/env python
"""pictorial_structures stage: recover joints from the detector's candidate peaks."""

from pathlib import Path

from _cli import add_rig_stage_arguments, artifact_outdir, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.pictorial_structures import run_pictorial_structures

    parser = script_parser(__doc__)
    parser.add_argument(
        "--pose2d", dest="pose2d_path", required=True, type=Path, help="pose2d artifact"
    )
    parser.add_argument(
        "--candidates",
        dest="candidates_path",
        type=Path,
        help="the detector's top-K peaks (default: those inside the pose2d artifact)",
    )
    add_rig_stage_arguments(parser)
    return script_main(
        parser,
        run_pictorial_structures,
        argv,
        job=job,
        stage="pictorial_structures",
        outdir=artifact_outdir,
    )


if __name__ == "__main__":
    run_script(main, globals())
