# Shared set-up: validate the config, resolve the recordings, and the helpers the
# rules use. Runs once per Snakemake invocation, before any job starts.

import json
import os
import sys
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.logging import logger

from flylib.config.layers import ConfigLayers
from flylib.errors import FlylibError
from flylib.neuromechfly import FILES as NEUROMECHFLY_FILES
from flylib.results.artifacts import ARTIFACTS
from flylib.pipeline.memory import job_mem_mb  # rules: mem_mb from the recording's size
from flylib.pipeline.planning import RECORDING_GROUP, RunPlan
from flylib.pipeline.preflight import load_run_config

# envs/flylib.yaml installs flylib from this checkout: pip expands the variable when
# --sdm conda creates the environment, which happens in this process, before any job.
os.environ.update(FLYLIB_CHECKOUT=str(Path(workflow.basedir).resolve()))

# The config: the same files Snakemake merged (configfile: and --configfile, then
# --config overrides), re-read by flylib's parser so that 1e-8 is a number, a key
# given twice is an error, and every problem names the user's own file and key.


def _user_path(path) -> str:
    text = os.path.relpath(os.path.abspath(path))
    return text if not text.startswith("..") else str(os.path.abspath(path))


def _config_layers() -> ConfigLayers:
    settings = workflow.config_settings
    cli = [Path(f).absolute() for f in settings.configfiles]
    directive = (
        []
        if settings.replace_workflow_config
        else [f for f in workflow.configfiles if Path(f).absolute() not in cli]
    )
    files = [_user_path(f) for f in [*directive, *cli]]
    return ConfigLayers.from_files(files, overrides=dict(settings.config or {}))


# Validate before the DAG is built, with flylib's validator (the one source of truth;
# there is no separate JSON schema): every key on its own, then what needs the whole
# config or the planned recordings (the rig, import specs, detection plan and
# weights, videos, footage for the detector), so nothing that can be known now
# surfaces later inside a job. Nothing is written or created for an invalid config.
# A cluster job re-parses the config: the footage frame counts were checked already.


def stop_run(message: str) -> None:
    """End the run before the DAG with ``message`` alone on stderr: a WorkflowError
    raised here would come wrapped in Snakemake's file, line and traceback lines."""
    print(message, file=sys.stderr, flush=True)
    sys.exit(1)


try:
    PLAN = RunPlan(
        *load_run_config(_config_layers(), check_frames=workflow.is_main_process),
        main_process=workflow.is_main_process,
    )
except FlylibError as exc:
    stop_run(str(exc))
for _line in PLAN.warnings:
    logger.warning(_line)

# What the rule files use, bound from the plan (flylib.pipeline.planning.RunPlan).
CONFIG, RECORDINGS, FLAGS = PLAN.config, PLAN.recordings, PLAN.flags
SKIPPED, SESSIONS, VIDEO_NAMES = PLAN.skipped, PLAN.sessions, PLAN.video_names
all_targets = PLAN.targets
artifact = PLAN.artifact
unplanned = PLAN.unplanned
rig_artifact = PLAN.rig_artifact
calibration_inputs = PLAN.calibration_inputs
reconstruction_inputs = PLAN.reconstruction_inputs
refinement_inputs = PLAN.refinement_inputs
pose2d_outputs = PLAN.pose2d_outputs
pose2d_import = PLAN.pose2d_import
# pose2d's resources: the detector on a GPU, on its own; imported 2D in its recording's
# group (on a cluster each recording's CPU chain is one submission, see profiles/slurm)
pose2d_gpus = PLAN.pose2d_gpus
pose2d_mem_mb = PLAN.pose2d_mem_mb
pose2d_runtime = PLAN.pose2d_runtime
pose2d_group = PLAN.pose2d_group


def recording(wildcards):
    """The Recording whose output directory is this job's ``{outdir}``."""
    try:
        return PLAN.recording(wildcards)
    except FlylibError as exc:
        raise WorkflowError(str(exc)) from None


def session(wildcards):
    """The Session whose folder is this job's ``{sessiondir}``."""
    try:
        return PLAN.session(wildcards)
    except FlylibError as exc:
        raise WorkflowError(str(exc)) from None


def as_is(value):
    """A param that Snakemake takes as it is: it formats a plain string param as a
    wildcard pattern (a `{view}` in a config value would end the run), but not what a
    function returns. The value, and so the repr its re-run check compares, is kept."""
    return lambda wildcards: value


def job_params(stage: str, recording_path: bool = True) -> dict:
    """A stage rule's shared params: `stage`, its tracked params as canonical JSON
    (Snakemake re-runs a job when they change); `runtime`, the untracked, speed-only
    part, and `expects`, the params hashes its input artifacts must record (the job
    refuses others), derived params (functions of the job's input) that re-run nothing
    by themselves; and (unless told not to) `recording`, the job's recording folder."""
    return {
        "stage": as_is(PLAN.stage_json(stage)),
        "runtime": lambda wildcards, input: PLAN.runtime(stage),
        "expects": lambda wildcards, input: PLAN.expects(wildcards),
        **({"recording": lambda w: str(recording(w).path)} if recording_path else {}),
    }


# -- one run per output directory ------------------------------------------------------
# Snakemake deletes a job's old outputs before the job starts, so a job's own lock
# (scripts/_cli.py) comes too late: a second run from another directory would already
# have removed the first run's files. The run claims every output directory once its
# DAG is built and before any job is scheduled or any output removed (onstart: real
# runs only, so -n, --list, --summary and the jobs' own re-parses claim nothing), and
# releases them at exit. Its jobs inherit the claim's run id and pass it; a claim left
# by a killed run (same host, pid gone) is taken over by the next run. Once claimed,
# the temporary files of writers killed mid-write there are removed.


onstart:
    import atexit
    from flylib.locking import claim_outdirs, release_outdirs
    from flylib.paths import remove_stale_temps

    try:
        _claimed = claim_outdirs(str(r.outdir) for r in PLAN.planned)
    except FlylibError as exc:
        raise WorkflowError(str(exc)) from None
    atexit.register(release_outdirs, _claimed)
    # the folders are the run's now: their planned outputs are flylib's (re-runs replace them)
    from flylib.pipeline.user_files import record_planned

    record_planned(CONFIG, _claimed)
    for _outdir in _claimed:
        for _temp in remove_stale_temps(_outdir, recursive=True):
            logger.info(f"removed {_temp}, left by a writer that was killed")
