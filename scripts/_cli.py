"""Command-line plumbing shared by the stage scripts.

Every script runs two ways with the same argument parser:

- by hand, ``python scripts/<stage>.py --config config/config.yaml ... [--threads N]``
  (see ``--help``);
- from its Snakemake rule's ``script:`` directive, where the arguments come from the
  job: each named input, output and param whose name is one of the script's options
  (``pose2d`` -> ``--pose2d``; an unnamed single output -> ``--out``; a ``True`` param ->
  the bare flag), ``{outdir}`` -> ``--outdir``, the rule's ``threads`` -> ``--threads``,
  stderr -> the job's log. A stage script given ``stage=`` runs on that stage's inputs
  object (:mod:`flylib.pipeline.inputs`), rebuilt from the rule's tracked
  ``params.stage`` and untracked ``params.runtime``; by hand it is built from
  ``--config``. (A script without ``stage=`` gets the run's
  :class:`~flylib.config.Config`: the rule's ``params.config``, or ``--config``.)
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

# Params that are not script options: the stage's tracked params and untracked runtime
# (they make its inputs object) and the run's config itself (handed over as an object).
_NOT_OPTIONS = ("stage", "runtime", "config")


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


def output_dir(out: str | Path) -> Path:
    """The recording's output directory of an artifact path (``<outdir>/stages/x.h5``
    gives ``<outdir>``; any other file its own directory)."""
    parent = Path(out).parent
    return parent.parent if parent.name == "stages" else parent


def snakemake_argv(job: Any, parser: argparse.ArgumentParser) -> list[str]:
    """The command line equivalent to a Snakemake ``script:`` job (see the module doc)."""
    options = {a.dest: a for a in parser._actions if a.option_strings}
    argv: list[str] = []

    def add(name: str, value: Any) -> None:
        dest = name.replace("-", "_")
        if dest not in options or value is None or value is False or value == "":
            return
        if isinstance(value, list) and not value:  # an optional input left out
            return
        flag = options[dest].option_strings[-1]
        if value is True or options[dest].nargs == 0:
            argv.append(flag)
        else:
            argv.extend([flag, str(value)])

    named = dict(job.output.items())
    if not named and len(job.output) == 1:
        named = {"out": job.output[0]}
    for items in (job.input.items(), named.items(), job.params.items()):
        for name, value in items:
            if name not in _NOT_OPTIONS:
                add(name, value)
    add("outdir", getattr(job.wildcards, "outdir", None))
    add("threads", job.threads)
    return argv


def _log_to(path: str | Path) -> None:
    """Send this process's stderr (Python's and the C libraries') to ``path``."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    sys.stderr.flush()
    os.dup2(fd, 2)
    os.close(fd)


def script_main(
    parser: argparse.ArgumentParser,
    run: Callable[[argparse.Namespace, Any], Any],
    argv: list[str] | None = None,
    *,
    job: Any = None,
    outdir: Callable[[argparse.Namespace], str | Path] | None = None,
    stage: str | type | None = None,
) -> int:
    """Parse the arguments (from ``argv``, or from the Snakemake ``job``), load the
    config, and run a stage under the thread budget; a user-facing error is printed as
    one line on stderr and exits with status 1.

    With ``outdir`` (the output directory the stage writes, from its arguments) the
    stage runs holding that directory's lock (:func:`flylib.locking.outdir_lock`), so
    a second run writing the same directory fails naming the holder.

    With ``stage``, ``run`` gets the stage's inputs object instead of the config: a
    stage name, or the inputs class of a rule outside the params stages (the demo,
    the NWB export), whose ``params.stage`` is that class's params as JSON.
    """
    if job is not None:
        parser.prog = f"{job.rule}.py"
        if job.log:
            _log_to(job.log[0])
        argv = snakemake_argv(job, parser)
    args = parser.parse_args(argv)
    if job is None and args.config is None:
        parser.error("the following arguments are required: --config")
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from flylib.resources import thread_budget

    try:
        config = _stage_config(args, job, stage)
        with thread_budget(args.threads):
            if outdir is None:
                run(args, config)
            else:
                from flylib.locking import outdir_lock

                with outdir_lock(outdir(args), job=Path(parser.prog).stem):
                    run(args, config)
    except FlylibError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


def _stage_config(args: argparse.Namespace, job: Any, stage: str | type | None) -> Any:
    """What a stage runs on: its inputs object when ``stage`` is given (from the job's
    params, or built from ``--config``: on the config rig when a stage that takes
    ``--bundle-adjustment`` is run without it), else the run's config."""
    from flylib.config import Config

    if stage is None:
        return job.params.config if job is not None else Config.from_file(args.config)
    if not isinstance(stage, str):  # an inputs class of a rule that is not a params stage
        if job is not None:
            return stage.from_params(json.loads(job.params.stage), job.params.runtime)
        return stage.from_config(Config.from_file(args.config))
    from flylib.pipeline.inputs import inputs_from_job, stage_inputs

    if job is not None:
        return inputs_from_job(stage, job.params.stage, job.params.runtime)
    config = Config.from_file(args.config)
    if getattr(args, "bundle_adjustment", False) is None:
        # a stage after bundle adjustment run by hand without its artifact: the config rig
        from flylib.pipeline.stage_helpers import run_inputs

        return run_inputs(config, stage)
    return stage_inputs(config, stage)


def run_script(main: Callable[..., int], namespace: dict) -> None:
    """Run a script's ``main``: with the Snakemake job when ``namespace`` (the script's
    globals) holds one, else from ``sys.argv``; exits with its status."""
    job = namespace.get("snakemake")
    sys.exit(main(job=job) if job is not None else main())
