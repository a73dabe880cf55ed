#!/usr/bin/env python
"""bundle_adjustment stage: refine the camera rig against the recording's 2D keypoints."""

from pathlib import Path

from _cli import artifact_outdir, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    # The solver (JAX, SciPy) loads before the job's work: loaded inside the fit, the job
    # spent 0.4 s more in the kernel (some 60,000 more mmap/munmap calls from the
    # allocator; benchmarks/workflow.py).
    import flylib.bundle_adjustment.sequence  # noqa: F401
    from flylib.pipeline.bundle_adjustment import run_bundle_adjustment

    parser = script_parser(__doc__)
    parser.add_argument(
        "--pose2d", dest="pose2d_path", required=True, type=Path, help="pose2d artifact (.h5)"
    )
    parser.add_argument(
        "--out",
        dest="out_path",
        required=True,
        type=Path,
        help="bundle-adjustment artifact to write",
    )
    parser.add_argument(
        "--recording",
        dest="recording_dir",
        type=Path,
        help="recording directory (resolves a per-session calibration file)",
    )
    return script_main(
        parser,
        run_bundle_adjustment,
        argv,
        job=job,
        stage="bundle_adjustment",
        outdir=artifact_outdir,
    )


if __name__ == "__main__":
    run_script(main, globals())
