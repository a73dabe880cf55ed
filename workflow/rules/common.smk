# Shared set-up: validate the config, resolve the recordings, and the helpers the
# rules use. Runs once per Snakemake invocation, before any job starts.

import functools
import json
import os
import sys
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.logging import logger

from flylib.config.layers import ConfigLayers
from flylib.errors import FlylibError
from flylib.pipeline.planning import calibration_inputs as _calibration_files
from flylib.pipeline.preflight import load_run_config
from flylib.kinematics import FILES as KINEMATICS_FILES
from flylib.neuromechfly import FILES as NEUROMECHFLY_FILES
from flylib.results.artifacts import ARTIFACTS, SUMMARY_FILES, candidates_artifact
from flylib.pipeline.inputs import stage_params as _stage_params, stage_runtime as _stage_runtime
from flylib.pipeline.memory import job_mem_mb  # rules: mem_mb from the recording's size
from flylib.sessions import plan_sessions

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
    LAYERS = _config_layers()
    CONFIG, RECORDINGS = load_run_config(LAYERS, check_frames=workflow.is_main_process)
except FlylibError as exc:
    stop_run(str(exc))
FLAGS = CONFIG.stage_flags()
VIDEO_NAMES = [video.name for video in CONFIG.videos] if FLAGS["visualization"] else []

if sum(r.demo for r in RECORDINGS) > 1:
    stop_run("recordings: more than one {demo: true} entry; list the demo once")


BY_OUTDIR = {str(r.outdir): r for r in RECORDINGS}

# Artifacts another working directory's run wrote with other params (issue 13).
if workflow.is_main_process:
    from flylib.pipeline.planning import params_of  # noqa: E402
    from flylib.provenance import foreign_artifacts  # noqa: E402

    for _line in foreign_artifacts(params_of(CONFIG, run_only=True), RECORDINGS):
        logger.warning(_line)


# Which recording a job's `{outdir}` belongs to is looked up, not matched: a wildcard
# constraint listing every outdir is a regex as long as the batch, which Snakemake
# scans for every job and file (planning 10,000 recordings never finished).


def recording(wildcards):
    """The Recording whose output directory is this job's ``{outdir}``."""
    try:
        return BY_OUTDIR[wildcards.outdir]
    except KeyError:
        raise WorkflowError(
            f"{wildcards.outdir} is not the output folder of any recording of this run"
        ) from None


def unplanned(wildcards) -> list[str]:
    """``[]`` for a recording's output folder; for any other folder one input that
    cannot exist. A user's file whose path matches an output pattern (a
    calibration.toml beside the footage, or in another run's outputs) asks for a job in
    a folder this run does not write; that input makes Snakemake drop the job and read
    the file as it is, never make it."""
    if wildcards.outdir in BY_OUTDIR:
        return []
    return [f"{wildcards.outdir} (no recording of this run writes to this folder)"]


def as_is(value):
    """A param that Snakemake takes as it is: it formats a plain string param as a
    wildcard pattern (a `{view}` in a config value would end the run), but not what a
    function returns. The value, and so the repr its re-run check compares, is kept."""
    return lambda wildcards: value


def stage_params(stage: str):
    """The rule's `params.stage`: the stage's tracked params (its inputs object's,
    flylib.pipeline.inputs), as canonical JSON (Snakemake re-runs a job when it changes)."""
    return as_is(json.dumps(_stage_params(CONFIG, stage), sort_keys=True))


def job_runtime(stage: str):
    """The rule's `params.runtime`: the untracked, speed-only part of the stage's inputs.
    A derived param (a function of the job's input), so it re-runs nothing by itself."""

    def runtime(wildcards, input):
        return _runtime_of(stage)

    return runtime


@functools.cache
def _runtime_of(stage: str):
    """The stage's runtime options, once per rule (they depend on the config alone)."""
    return _stage_runtime(CONFIG, stage)


def artifact(stage: str) -> str:
    """The `{outdir}` pattern of a stage artifact (or of the detector's candidates)."""
    name = candidates_artifact(CONFIG.pictorial.k) if stage == "candidates" else ARTIFACTS[stage]
    return f"{{outdir}}/stages/{name}"


def pose2d_outputs() -> dict[str, str]:
    """The 2D points, plus the candidate peaks while pictorial structures is on."""
    outputs = {"out": artifact("pose2d")}
    if FLAGS["pictorial_structures"]:
        outputs["candidates_out"] = artifact("candidates")
    return outputs


def _absent_2d(rec) -> list[str]:
    """With pose2d off: the 2D artifacts the later stages need that do not exist."""
    if FLAGS["pose2d"]:
        return []
    needed = [ARTIFACTS["pose2d"]]
    if FLAGS["pictorial_structures"]:
        needed.append(candidates_artifact(CONFIG.pictorial.k))
    return [
        str(rec.outdir / "stages" / n) for n in needed if not (rec.outdir / "stages" / n).is_file()
    ]


def _skipped_recordings() -> set[str]:
    """Ids of the recordings left out for missing 2D (each warned about once)."""
    skipped = set()
    for rec in RECORDINGS:
        absent = _absent_2d(rec)
        if absent:
            skipped.add(rec.id)
            logger.warning(
                f"{rec.id}: pipeline.do_pose2d is false and {', '.join(absent)} "
                "missing; skipping this recording (turn pose2d on to create it)"
            )
    return skipped


SKIPPED = _skipped_recordings()

# Session calibration (bundle_adjustment.session: true): the recordings of one rig
# solved together (flylib.sessions). Each member's triangulation, refinement and
# assembly read the session's rig; its own solve still runs, for the session summary.
try:
    SESSIONS = (
        plan_sessions([r for r in RECORDINGS if r.id not in SKIPPED])
        if FLAGS["bundle_adjustment"] and CONFIG.bundle_adjustment.session
        else []
    )
except FlylibError as exc:
    stop_run(str(exc))
if CONFIG.bundle_adjustment.session and not FLAGS["bundle_adjustment"] and workflow.is_main_process:
    logger.warning(
        "bundle_adjustment.session: true does nothing while pipeline.do_bundle_adjustment "
        "is false (every recording uses the config rig); turn bundle adjustment on"
    )
SESSION_OF = {r.id: s for s in SESSIONS for r in s.members}
BY_SESSIONDIR = {str(s.outdir): s for s in SESSIONS}


def session(wildcards):
    """The Session whose folder is this job's ``{sessiondir}``."""
    try:
        return BY_SESSIONDIR[wildcards.sessiondir]
    except KeyError:
        raise WorkflowError(
            f"{wildcards.sessiondir} is not the folder of any session of this run"
        ) from None


def session_unplanned(wildcards) -> list[str]:
    """As :func:`unplanned`, for a session's folder."""
    if wildcards.sessiondir in BY_SESSIONDIR:
        return []
    return [f"{wildcards.sessiondir} (no session of this run writes to this folder)"]


def rig_artifact(wildcards) -> str:
    """The bundle-adjusted rig a recording's later stages read: its session's while
    session calibration is on, else its own bundle-adjustment artifact."""
    own = BY_OUTDIR.get(wildcards.outdir)  # None: a folder no recording writes (unplanned)
    if own is not None and own.id in SESSION_OF:
        return str(SESSION_OF[own.id].artifact)
    return artifact("bundle_adjustment").format(outdir=wildcards.outdir)


def recording_targets(rec) -> list[str]:
    """Every final output of one recording."""
    out = str(rec.outdir)
    targets = [f"{out}/results.h5", *(f"{out}/{name}" for name in SUMMARY_FILES)]
    if FLAGS["visualization"]:
        targets += [f"{out}/{name}.mp4" for name in VIDEO_NAMES]
    if FLAGS["kinematics"]:
        targets += [f"{out}/{name}" for name in KINEMATICS_FILES]
    if FLAGS["neuromechfly"]:
        targets += [f"{out}/{name}" for name in NEUROMECHFLY_FILES]
    return targets


def all_targets() -> list[str]:
    targets = [t for rec in RECORDINGS if rec.id not in SKIPPED for t in recording_targets(rec)]
    return targets + [str(s.summary) for s in SESSIONS]


# -- per-rule input and argument helpers ---------------------------------------


def pose2d_import(wildcards) -> str:
    """The recording's own import spec as JSON ("null": the config's pose2d.import)."""
    return json.dumps(recording(wildcards).import_spec, sort_keys=True)


# -- cluster job groups --------------------------------------------------------------
# On a cluster (profiles/slurm) each recording's CPU chain is one submission: every
# per-recording rule is in the group "recording", and Snakemake submits each connected
# part of a group (one recording's jobs) as one job whose resources it derives from its
# members (the sum over jobs that run side by side, the most over jobs in a row, runtimes
# added up). The detector is its own (GPU) job; imported 2D joins its recording's
# group. Local runs ignore groups. `--group-components recording=N` puts N recordings in
# one submission; `--groups` renames or splits them.

#: The group of a recording's CPU jobs.
RECORDING_GROUP = "recording"


def pose2d_mem_mb(wildcards) -> int:
    """The detector's memory; reading imported 2D needs far less (and sets its group's)."""
    return 8000 if pose2d_gpus(wildcards) else 2000


def pose2d_runtime(wildcards) -> int:
    """Minutes: the detector's, or reading imported 2D's."""
    return 120 if pose2d_gpus(wildcards) else 15


def pose2d_group(wildcards) -> str | None:
    """Imported 2D (no GPU) runs in its recording's group; the detector on its own."""
    return RECORDING_GROUP if pose2d_gpus(wildcards) == 0 else None


def pose2d_gpus(wildcards) -> int:
    """A GPU only when the detector runs (imported 2D needs none)."""
    rec = recording(wildcards)
    return 0 if (rec.import_spec or CONFIG.import_spec) else 1


def calibration_inputs(wildcards) -> list[str]:
    """The calibration file(s) the config rig is read from ([] for an orbit rig), so a
    rule that builds the config rig re-runs when the file changes."""
    return unplanned(wildcards) or list(_recording_calibration(recording(wildcards).path))


@functools.cache
def _recording_calibration(path: Path) -> tuple[str, ...]:
    return tuple(str(p) for p in _calibration_files(CONFIG, path))


def reconstruction_inputs(stage: str):
    """Inputs of a geometry rule: pose2d, plus the bundle-adjusted rig while that stage
    is on (else the calibration file the config rig comes from, if any), plus
    (triangulation) pictorial-structures 2D while that stage is on."""

    def inputs(wildcards) -> dict:
        def own(name: str) -> str:
            return artifact(name).format(outdir=wildcards.outdir)

        files = {"pose2d": own("pose2d")}
        if stage == "pictorial_structures":
            files["candidates"] = own("candidates")
        if FLAGS["bundle_adjustment"]:
            files["bundle_adjustment"] = rig_artifact(wildcards)
        if stage == "triangulation" and FLAGS["pictorial_structures"]:
            files["pictorial_structures"] = own("pictorial_structures")
        if not FLAGS["bundle_adjustment"]:
            files["calibration"] = calibration_inputs(wildcards)
        return files

    return inputs


def refinement_inputs(wildcards) -> dict:
    """Inputs of refinement: pose2d (2D, confidences), the triangulation (start, inlier
    views), and the rig as triangulation reads it."""
    files = reconstruction_inputs("refinement")(wildcards)
    files["triangulation"] = artifact("triangulation").format(outdir=wildcards.outdir)
    return files


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
        _claimed = claim_outdirs(str(r.outdir) for r in RECORDINGS if r.id not in SKIPPED)
    except FlylibError as exc:
        raise WorkflowError(str(exc)) from None
    atexit.register(release_outdirs, _claimed)
    # the folders are the run's now: their planned outputs are flylib's (re-runs replace them)
    from flylib.pipeline.user_files import record_planned

    record_planned(CONFIG, _claimed)
    for _outdir in _claimed:
        for _temp in remove_stale_temps(_outdir, recursive=True):
            logger.info(f"removed {_temp}, left by a writer that was killed")
