"""The entry point shared by the stage scripts.

A script's ``run(inputs, **arguments)`` calls its stage function with the stage's
inputs object (:mod:`flylib.pipeline.inputs`) and the files and options it takes, by
name. :func:`script_main` gets both two ways:

- from the rule's ``script:`` directive (``job``, the script's ``snakemake`` object):
  the inputs object rebuilt from the rule's tracked ``params.stage`` and untracked
  ``params.runtime``, the arguments read from ``snakemake.input/output/params/
  wildcards`` by the script's ``job_arguments``, the rule's ``threads``, and stderr
  sent to the job's log;
- by hand, ``python scripts/<stage>.py --config config/config.yaml ... [--threads N]``
  (see ``--help``): the inputs object built from ``--config`` and the arguments from
  the script's options, each option's name that of a ``run`` argument.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from flylib.errors import FlylibError

# The options every script shares: what runs the stage, not arguments of ``run``.
_SHARED = ("config", "threads", "verbose")


def script_parser(description: str) -> argparse.ArgumentParser:
    """An argument parser with the options every stage script shares."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="config file (.yaml/.toml) of the run, e.g. config/config.yaml "
        "(required when run by hand)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="threads the stage may use (default: the CPUs this process may run on)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return parser


def add_rig_stage_arguments(parser: argparse.ArgumentParser) -> None:
    """``--bundle-adjustment``, ``--out`` and ``--recording``: the arguments of every
    stage after bundle adjustment that writes one artifact from the final rig."""
    parser.add_argument(
        "--bundle-adjustment",
        type=Path,
        default=None,
        help="bundle-adjustment artifact (its rig); default: the config rig",
    )
    parser.add_argument("--out", required=True, type=Path, help="artifact to write (.h5)")
    parser.add_argument("--recording", type=Path, default=None, help="recording directory")


def rig_stage_job_arguments(job: Any) -> dict[str, Path | None]:
    """The :func:`add_rig_stage_arguments` arguments of a Snakemake job."""
    return {
        "bundle_adjustment": path(job.input.get("bundle_adjustment")),
        "out": path(job.output[0]),
        "recording": path(job.params.recording),
    }


def path(value: Any) -> Path | None:
    """A job's file or directory as the by-hand option gives it: a ``Path``, or
    ``None`` for an optional one left out (absent, an empty list, ``""``)."""
    return Path(str(value)) if value else None


def output_dir(out: str | Path) -> Path:
    """The recording's output directory of an artifact path (``<outdir>/stages/x.h5``
    gives ``<outdir>``; any other file its own directory)."""
    parent = Path(out).parent
    return parent.parent if parent.name == "stages" else parent


def _log_to(path: str | Path) -> None:
    """Send this process's stderr (Python's and the C libraries') to ``path``."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    sys.stderr.flush()
    os.dup2(fd, 2)
    os.close(fd)


def script_main(
    parser: argparse.ArgumentParser,
    run: Callable[..., Any],
    argv: list[str] | None = None,
    *,
    job: Any = None,
    job_arguments: Callable[[Any], dict[str, Any]],
    stage: str | type,
    outdir: Callable[[dict[str, Any]], str | Path] | None = None,
    hand_arguments: Callable[[argparse.Namespace], dict[str, Any]] | None = None,
) -> int:
    """Run a stage script: ``run(inputs, **arguments)`` under the thread budget; a
    user-facing error is printed as one line on stderr and exits with status 1.

    Parameters
    ----------
    parser
        The script's options (by hand: parsed from ``argv``).
    run
        The script's entry point.
    argv
        The command line by hand (``None``: ``sys.argv``); unused with ``job``.
    job
        The Snakemake ``script:`` job (``snakemake``), or ``None`` by hand.
    job_arguments
        ``run``'s arguments read from the job.
    stage
        A stage name, or the inputs class of a rule outside the params stages (the
        demo, the NWB export), whose ``params.stage`` is that class's params as JSON.
    outdir
        The output directory the stage writes, from its arguments: the stage then
        runs holding that directory's lock (:func:`flylib.locking.outdir_lock`), so a
        second run writing the same directory fails naming the holder.
    hand_arguments
        ``run``'s arguments by hand (default: the options other than the shared ones).
    """
    if job is not None:
        if job.log:
            _log_to(job.log[0])
        name, threads, verbose = job.rule, job.threads, False

        def inputs() -> Any:
            return _job_inputs(job, stage)

        def arguments() -> dict[str, Any]:
            return job_arguments(job)

    else:
        args = parser.parse_args(argv)
        if args.config is None:
            parser.error("the following arguments are required: --config")
        name, threads, verbose = Path(parser.prog).stem, args.threads, args.verbose

        def inputs() -> Any:
            return _hand_inputs(args, stage)

        def arguments() -> dict[str, Any]:
            if hand_arguments is not None:
                return hand_arguments(args)
            return {k: v for k, v in vars(args).items() if k not in _SHARED}

    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from flylib.resources import thread_budget

    try:
        stage_inputs = inputs()
        with thread_budget(threads):
            given = arguments()
            if outdir is None:
                run(stage_inputs, **given)
            else:
                from flylib.locking import outdir_lock

                with outdir_lock(outdir(given), job=name):
                    run(stage_inputs, **given)
    except FlylibError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


def _job_inputs(job: Any, stage: str | type) -> Any:
    """A job's inputs object, from its rule's ``params.stage`` and ``params.runtime``."""
    if not isinstance(stage, str):  # an inputs class of a rule that is not a params stage
        return stage.from_params(json.loads(job.params.stage), job.params.runtime)
    from flylib.pipeline.inputs import inputs_from_job

    return inputs_from_job(stage, job.params.stage, job.params.runtime)


def _hand_inputs(args: argparse.Namespace, stage: str | type) -> Any:
    """The inputs object by hand, built from ``--config``: on the config rig when a
    stage that takes ``--bundle-adjustment`` is run without it."""
    from flylib.config import Config

    config = Config.from_file(args.config)
    if not isinstance(stage, str):
        return stage.from_config(config)
    if getattr(args, "bundle_adjustment", False) is None:
        # a stage after bundle adjustment run by hand without its artifact: the config rig
        from flylib.pipeline.stage_helpers import run_inputs

        return run_inputs(config, stage)
    from flylib.pipeline.inputs import stage_inputs

    return stage_inputs(config, stage)


def run_script(main: Callable[..., int], namespace: dict) -> None:
    """Run a script's ``main``: with the Snakemake job when ``namespace`` (the script's
    globals) holds one, else from ``sys.argv``; exits with its status."""
    job = namespace.get("snakemake")
    sys.exit(main(job=job) if job is not None else main())
