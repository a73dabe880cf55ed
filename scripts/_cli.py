"""The entry point shared by the stage scripts.

A script's options are named for its rule's files and params (``--pose2d``: the job's
``input.pose2d``) and store under the keywords of its stage function (``dest=
"pose2d_path"``), so :func:`script_main` calls ``run_<stage>(inputs, **arguments)``:

- run by the rule's ``script:`` directive (``job``, the script's ``snakemake`` object):
  each option's value read by its name from ``snakemake.input/output/params/wildcards``,
  the inputs object rebuilt from the rule's tracked ``params.stage`` and untracked
  ``params.runtime``, the rule's ``threads``, and stderr sent to the job's log;
- by hand (``python scripts/<stage>.py --config config/config.yaml ...``, see
  ``--help``): the options parsed, the inputs object built from ``--config``.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from flylib.errors import FlylibError

# Snakemake's script preamble appends the job's import path to sys.path again: keep each folder
# once, so an import that scans sys.path (JAX's reads every installed package's metadata per
# folder, ~0.2 s each) scans each folder once.
sys.path[:] = dict.fromkeys(sys.path)

# The options every script shares: what runs the stage, not arguments of the stage.
_SHARED = ("help", "config", "threads", "verbose")


class ScriptParser(argparse.ArgumentParser):
    """An argument parser that keeps a script's own options (``options``) by their names in
    the job (``--bundle-adjustment``: ``bundle_adjustment``), the names ``--help`` shows."""

    def __init__(self, **kwargs: Any) -> None:
        self.options: dict[str, argparse.Action] = {}
        super().__init__(**kwargs)

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        action = super().add_argument(*args, **kwargs)
        if action.dest not in _SHARED:
            name = action.option_strings[-1].lstrip("-").replace("-", "_")
            action.metavar = action.metavar or name.upper()
            self.options[name] = action
        return action


def script_parser(description: str) -> ScriptParser:
    """An argument parser with the options every stage script shares."""
    parser = ScriptParser(description=description)
    parser.add_argument(
        "--config",
        type=Path,
        help="config file (.yaml/.toml) of the run, e.g. config/config.yaml "
        "(required when run by hand)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        help="threads the stage may use (default: the CPUs this process may run on)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return parser


def add_results_argument(parser: argparse.ArgumentParser) -> None:
    """``--results``: the recording's ``results.h5``, read by every stage after assembly."""
    parser.add_argument(
        "--results",
        dest="results_path",
        required=True,
        type=Path,
        help="results.h5 of the recording",
    )


def add_rig_stage_arguments(parser: argparse.ArgumentParser) -> None:
    """``--bundle-adjustment``, ``--out`` and ``--recording``: the arguments of every
    stage after bundle adjustment that writes one artifact from the final rig."""
    parser.add_argument(
        "--bundle-adjustment",
        dest="ba_path",
        type=Path,
        help="bundle-adjustment artifact (its rig); default: the config rig",
    )
    parser.add_argument(
        "--out", dest="out_path", required=True, type=Path, help="artifact to write (.h5)"
    )
    parser.add_argument("--recording", dest="recording_dir", type=Path, help="recording directory")


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """``--pose2d``, ``--members`` and ``--name``: a session's recordings (the arguments of
    the session_calibration and session_summary scripts)."""
    parser.add_argument(
        "--pose2d",
        dest="pose2d_paths",
        nargs="+",
        required=True,
        type=Path,
        help="the members' pose2d artifacts (.h5), in --members order",
    )
    parser.add_argument(
        "--members", nargs="+", required=True, type=str, help="the members' recording ids"
    )
    parser.add_argument("--name", required=True, type=str, help="the session's name")


def artifact_outdir(arguments: dict[str, Any]) -> Path:
    """The recording's output directory of a stage writing the artifact ``out_path``
    (``<outdir>/stages/x.h5`` gives ``<outdir>``; any other file its own directory)."""
    parent = Path(arguments["out_path"]).parent
    return parent.parent if parent.name == "stages" else parent


def _log_to(path: str | Path) -> None:
    """Send this process's stderr (Python's and the C libraries') to ``path``."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    sys.stderr.flush()
    os.dup2(fd, 2)
    os.close(fd)


class _Stopped(BaseException):
    """A stop signal (SIGTERM, SIGINT, SIGHUP) arrived: unwind, so temporary files and
    locks are released, then say so in the log."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _stop(signum: int, frame: Any) -> None:
    raise _Stopped(signum)


def _job_value(job: Any, name: str, action: argparse.Action) -> Any:
    """Option ``name``'s value in the job, converted as the option converts its text (a
    file or directory left out, as an empty list or ``""``: ``None``)."""
    for part in (job.input, job.output, job.params, job.wildcards):
        if name in part.keys():
            value = part[name]
            break
    else:
        return action.default
    if action.type is Path:
        return Path(str(value)) if value else None
    if action.type is None:  # a flag
        return bool(value)
    return None if value is None else action.type(value)


def script_main(
    parser: ScriptParser,
    run: Callable[..., Any],
    argv: list[str] | None = None,
    *,
    job: Any = None,
    stage: str | type,
    outdir: Callable[[dict[str, Any]], str | Path | None] = lambda given: given.get("outdir"),
    job_extra: Callable[[Any], dict[str, Any]] = lambda job: {},
    hand_extra: Callable[[argparse.Namespace], dict[str, Any]] = lambda args: {},
) -> int:
    """Run a stage script: ``run(inputs, **arguments)`` under the thread budget; a
    user-facing error is printed as one line on stderr and exits with status 1.

    Parameters
    ----------
    parser
        The script's options (by hand: parsed from ``argv``).
    run
        The stage function, or the script's wrapper around it.
    argv, job
        The command line by hand (``None``: ``sys.argv``), or the Snakemake ``script:``
        job (``snakemake``; ``argv`` unused).
    stage
        A stage name, or the inputs class of a rule outside the params stages (the
        demo, the NWB export), whose ``params.stage`` is that class's params as JSON.
    outdir
        The output directory the stage writes, from its arguments (default: its
        ``outdir`` argument, if it takes one): the stage then runs holding that directory's lock (:func:`flylib.locking.outdir_lock`), so a
        second run writing the same directory fails naming the holder.
    job_extra, hand_extra
        ``run``'s arguments that are no option, from the job and by hand.
    """
    options = parser.options
    if job is not None:
        if job.log:
            _log_to(job.log[0])
        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(signum, _stop)
        name, threads, verbose = job.rule, job.threads, False

        def prepare() -> tuple[Any, dict[str, Any]]:
            from flylib.provenance import refuse_stale_inputs

            if "expects" in job.params.keys():  # an input of other settings is never read
                refuse_stale_inputs(job.input, job.params.expects)
            inputs = _job_inputs(job, stage)
            given = {a.dest: _job_value(job, n, a) for n, a in options.items()}
            return inputs, given | job_extra(job)

    else:
        args = parser.parse_args(argv)
        if args.config is None:
            parser.error("the following arguments are required: --config")
        name, threads, verbose = Path(parser.prog).stem, args.threads, args.verbose

        def prepare() -> tuple[Any, dict[str, Any]]:
            inputs = _hand_inputs(args, stage, options.get("bundle_adjustment"))
            given = {a.dest: getattr(args, a.dest) for a in options.values()}
            return inputs, given | hand_extra(args)

    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from flylib.resources import thread_budget

    try:
        inputs, given = prepare()
        if not gc.isenabled():  # run_script's imports done: their objects out of its way
            gc.freeze()
            gc.enable()
        directory = outdir(given)
        with thread_budget(threads):
            if directory is None:
                run(inputs, **given)
            else:
                from flylib.locking import outdir_lock

                with outdir_lock(directory, job=name):
                    run(inputs, **given)
    except Exception as exc:
        stop = _stop_within(exc)
        if stop is not None:
            return _stopped(stop)
        if not isinstance(exc, (FlylibError, argparse.ArgumentTypeError)):  # a job's value
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except _Stopped as stop:
        return _stopped(stop)
    if job is not None:
        from flylib.run_summary import JOB_FINISHED

        print(JOB_FINISHED, file=sys.stderr, flush=True)
    return 0


def _stop_within(exc: BaseException) -> _Stopped | None:
    """The stop that ``exc`` was raised from, if any: a stop signal's exception raised
    while C code ran (h5py's lock) comes back as ``SystemError: ... returned a result
    with an exception set``, which a stage may turn into its own error in turn."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, _Stopped):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _stopped(stop: _Stopped) -> int:
    """Say in the job's log which signal stopped it; the job's exit status."""
    from flylib.run_summary import JOB_STOPPED

    print(f"{JOB_STOPPED}{signal.Signals(stop.signum).name}", file=sys.stderr, flush=True)
    return 128 + stop.signum


def _job_inputs(job: Any, stage: str | type) -> Any:
    """A job's inputs object: its rule's ``params.stage`` parsed once, with its untracked
    ``params.runtime`` (``stage``: a stage's name, or the inputs class of a rule-only step)."""
    if isinstance(stage, str):
        from flylib.pipeline.inputs import inputs_class

        stage = inputs_class(stage)
    return stage.from_params(json.loads(job.params.stage), job.params.runtime)


def _hand_inputs(args: argparse.Namespace, stage: str | type, rig: argparse.Action | None) -> Any:
    """The inputs object by hand, built from ``--config``: for a stage with a
    ``--bundle-adjustment`` option (``rig``) left out, on the config rig."""
    from flylib.config import Config

    config = Config.from_file(args.config)
    if not isinstance(stage, str):
        return stage.from_config(config)
    if rig is not None:
        from flylib.pipeline.stage_helpers import run_inputs

        return run_inputs(config, stage, getattr(args, rig.dest))
    from flylib.pipeline.inputs import stage_inputs

    return stage_inputs(config, stage)


def run_script(main: Callable[..., int], namespace: dict) -> None:
    """Run a script's ``main``: with the Snakemake job when ``namespace`` (the script's
    globals) holds one, else from ``sys.argv``; exits with its status."""
    job = namespace.get("snakemake")
    gc.disable()  # a job's imports make ~250,000 objects and no garbage: collecting them is waste
    sys.exit(main(job=job) if job is not None else main())
