"""What a run plans from its config before any stage: the recordings it covers, the params
each stage's artifact should carry, the config rig and its files, and the workflow's
:class:`RunPlan`. The modules below take these as typed values; this is where a
:class:`~flylib.config.Config` is read for them.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ..config import Config
from ..errors import ConfigError
from ..provenance import foreign_artifacts, params_hash
from ..recordings import Recording, plan_listing
from ..results.artifacts import ARTIFACTS, candidates_artifact
from ..sessions import Session, plan_sessions
from ..stages import registry
from ..visualization.specs import video_specs
from .demo import demo_import_spec
from .inputs import RigSpec, stage_params, stage_runtime

__all__ = [
    "RECORDING_GROUP",
    "RunPlan",
    "calibration_inputs",
    "config_rig",
    "params_of",
    "plan_recordings",
]


def plan_recordings(
    config: Config, *, check_frames: bool = True, config_dir: Path | None = None
) -> list[Recording]:
    """The recordings a workflow run covers: :func:`flylib.recordings.plan_listing` of the
    config's ``recordings``, ``sources``, ``recursive``, ``outdir`` and ``pose2d.import``.
    ``check_frames``: compare frame counts across sources; ``config_dir``: the folder of the
    config file that set ``recordings`` (for messages)."""
    data = config.data
    return plan_listing(
        data.get("recordings"),
        data.get("sources"),
        recursive=bool(data.get("recursive", False)),
        outdir=data.get("outdir"),
        default_import=(data.get("pose2d") or {}).get("import"),
        demo_import=lambda: demo_import_spec(config),
        check_frames=check_frames,
        config_dir=config_dir,
    )


def params_of(config: Config, *, run_only: bool = False) -> Callable[[str], dict | None]:
    """``stage -> the params its rule tracks under config`` (each computed once; also
    ``session_calibration``). ``run_only``: ``None`` for a stage the run does not write
    (:meth:`~flylib.config.Config.stage_flags`)."""
    flags = config.stage_flags() if run_only else {}

    @functools.cache
    def lookup(stage: str) -> dict | None:
        if stage == "session_calibration":  # a session's rig (flylib.sessions)
            if not flags.get("bundle_adjustment", True):
                return None
            from .session_calibration import SessionCalibrationInputs

            return SessionCalibrationInputs.from_config(config).canonical_params()
        if not flags.get(stage, True):
            return None
        return stage_params(config, stage)

    return lookup


def config_rig(
    config: Config,
    image_sizes: Mapping[str, tuple[int, int]] | None = None,
    recording_dir: str | Path | None = None,
):
    """The rig the config describes (:meth:`RigSpec.camera_group`, the one rig builder)."""
    return RigSpec.from_config(config).camera_group(image_sizes, recording_dir)


def calibration_inputs(config: Config, recording_dir: str | Path | None = None) -> list[Path]:
    """The files the config's ``calibration`` table reads for one recording."""
    from ..interop.anipose import calibration_inputs as calibration_files

    rig = RigSpec.from_config(config)
    return calibration_files(
        rig.calibration, Path(recording_dir) if recording_dir else None, config_dir=rig.config_dir
    )


#: The cluster job group of a recording's CPU jobs (profiles/slurm), submitted as one job;
#: the detector is its own (GPU) job, imported 2D joins its recording's group.
RECORDING_GROUP = "recording"


class RunPlan:
    """A workflow run as planned before its DAG: the recordings (and which are skipped), the
    stage flags, the sessions, and every input, param and resource the rules look up
    (workflow/rules/common.smk binds them). A rule's ``wildcards`` is anything with ``outdir``
    (``sessiondir`` for a session's rule). ConfigError for two demos or a session folder that
    is a recording's output folder."""

    def __init__(self, config: Config, recordings: list[Recording], *, main_process: bool = True):
        self.config = config
        self.recordings = recordings
        self.flags = config.stage_flags()
        self.video_names = (
            [v.name for v in video_specs(config)] if self.flags["visualization"] else []
        )
        if sum(r.demo for r in recordings) > 1:
            raise ConfigError("recordings: more than one {demo: true} entry; list the demo once")
        # a lookup, not a wildcard constraint: a regex listing every outdir is as long as
        # the batch, which Snakemake scans for every job and file (10,000 never planned)
        self.by_outdir = {str(r.outdir): r for r in recordings}
        self.warnings: list[str] = []
        self.params_of = params_of(config, run_only=True)
        if main_process:  # artifacts another working directory wrote with other params
            self.warnings += foreign_artifacts(self.params_of, recordings)
        self.skipped: set[str] = set()
        for rec in recordings:
            absent = self._absent_2d(rec)
            if absent:
                self.skipped.add(rec.id)
                self.warnings.append(
                    f"{rec.id}: pipeline.do_pose2d is false and {', '.join(absent)} "
                    "missing; skipping this recording (turn pose2d on to create it)"
                )
        session = config.bundle_adjustment.session
        self.sessions: list[Session] = (
            plan_sessions(self.planned) if self.flags["bundle_adjustment"] and session else []
        )
        if session and not self.flags["bundle_adjustment"] and main_process:
            self.warnings.append(
                "bundle_adjustment.session: true does nothing while "
                "pipeline.do_bundle_adjustment is false (every recording uses the config "
                "rig); turn bundle adjustment on"
            )
        self.session_of = {r.id: s for s in self.sessions for r in s.members}
        self.by_sessiondir = {str(s.outdir): s for s in self.sessions}
        self._runtime: dict[str, Any] = {}
        self._expects: dict[str, str] | None = None
        self._calibration: dict[Path, tuple[str, ...]] = {}

    @property
    def planned(self) -> list[Recording]:
        return [r for r in self.recordings if r.id not in self.skipped]

    def _absent_2d(self, rec: Recording) -> list[str]:
        """With pose2d off: the 2D artifacts the later stages need that do not exist."""
        if self.flags["pose2d"]:
            return []
        needed = [ARTIFACTS["pose2d"]]
        if self.flags["pictorial_structures"]:
            needed.append(candidates_artifact(self.config.pictorial_structures.k))
        stages = rec.outdir / "stages"
        return [str(stages / n) for n in needed if not (stages / n).is_file()]

    def recording(self, wildcards) -> Recording:
        try:
            return self.by_outdir[wildcards.outdir]
        except KeyError:
            raise ConfigError(
                f"{wildcards.outdir} is not the output folder of any recording of this run"
            ) from None

    def unplanned(self, wildcards) -> list[str]:
        """``[]`` for a recording's output folder, else one input that cannot exist: a user's
        file matching an output pattern (a calibration.toml beside the footage) asks for a job
        in a folder this run does not write; that input makes Snakemake drop the job and read
        the file as it is."""
        if wildcards.outdir in self.by_outdir:
            return []
        return [f"{wildcards.outdir} (no recording of this run writes to this folder)"]

    def session(self, wildcards) -> Session:
        try:
            return self.by_sessiondir[wildcards.sessiondir]
        except KeyError:
            raise ConfigError(
                f"{wildcards.sessiondir} is not the folder of any session of this run"
            ) from None

    def session_unplanned(self, wildcards) -> list[str]:
        """As :meth:`unplanned`, for a session's folder."""
        if wildcards.sessiondir in self.by_sessiondir:
            return []
        return [f"{wildcards.sessiondir} (no session of this run writes to this folder)"]

    def session_inputs(self, rule: str) -> Callable[[Any], dict]:
        """Inputs of a session's rule: each member's 2D, and the config rig's files (the solve)
        or the session's rig and each member's own (the summary)."""

        def inputs(wildcards) -> dict:
            unplanned = self.session_unplanned(wildcards)
            if unplanned:
                return {"unplanned": unplanned}
            session = self.session(wildcards)
            members = [str(r.outdir) for r in session.members]
            files = {"pose2d_files": [self.artifact("pose2d").format(outdir=o) for o in members]}
            if rule == "session_calibration":
                files["rig_files"] = list(self.recording_calibration(session.members[0].path))
            else:
                files["session"] = str(session.artifact)
                ba = self.artifact("bundle_adjustment")
                files["trial_files"] = [ba.format(outdir=o) for o in members]
            return files

        return inputs

    def stage_json(self, stage: str) -> str:
        """The stage's tracked params as canonical JSON: its rule's ``params.stage``."""
        return json.dumps(stage_params(self.config, stage), sort_keys=True)

    def runtime(self, stage: str) -> Any:
        """The untracked, speed-only part of the stage's inputs (once per stage)."""
        if stage not in self._runtime:
            self._runtime[stage] = stage_runtime(self.config, stage)
        return self._runtime[stage]

    def expects(self, wildcards) -> dict[str, str]:
        """Input name -> the params hash its artifact must record in this run (for
        :func:`flylib.provenance.refuse_stale_inputs`); a session member's rig: the session's."""
        if self._expects is None:
            self._expects = {
                name: params_hash(params)
                for name, stage in [*((s, s) for s in ARTIFACTS), ("results", "assemble")]
                if (params := self.params_of(stage)) is not None
            }
        own = self.by_outdir.get(getattr(wildcards, "outdir", None))
        if own is not None and own.id in self.session_of:
            session = params_hash(self.params_of("session_calibration"))
            return {**self._expects, "bundle_adjustment": session}
        return self._expects

    def pose2d_import(self, wildcards) -> str:
        """The recording's own import spec as JSON ("null": the config's pose2d.import)."""
        return json.dumps(self.recording(wildcards).import_spec, sort_keys=True)

    def artifact(self, stage: str) -> str:
        """The `{outdir}` pattern of a stage artifact (or of the detector's candidates)."""
        name = (
            candidates_artifact(self.config.pictorial_structures.k)
            if stage == "candidates"
            else None
        )
        return f"{{outdir}}/stages/{name or ARTIFACTS[stage]}"

    def pose2d_outputs(self) -> dict[str, str]:
        """The 2D points, plus the candidate peaks while pictorial structures is on."""
        outputs = {"out": self.artifact("pose2d")}
        if self.flags["pictorial_structures"]:
            outputs["candidates_out"] = self.artifact("candidates")
        return outputs

    def rig_artifact(self, wildcards) -> str:
        """The bundle-adjusted rig a recording's later stages read: its session's, else its own."""
        own = self.by_outdir.get(wildcards.outdir)  # None: a folder no recording writes
        if own is not None and own.id in self.session_of:
            return str(self.session_of[own.id].artifact)
        return self.artifact("bundle_adjustment").format(outdir=wildcards.outdir)

    def recording_calibration(self, path: Path) -> tuple[str, ...]:
        """The calibration file(s) the config rig of the recording at ``path`` reads (cached)."""
        if path not in self._calibration:
            self._calibration[path] = tuple(str(p) for p in calibration_inputs(self.config, path))
        return self._calibration[path]

    def calibration_inputs(self, wildcards) -> list[str]:
        """:meth:`recording_calibration` of this job's recording (re-runs on its change)."""
        return self.unplanned(wildcards) or list(
            self.recording_calibration(self.recording(wildcards).path)
        )

    def reconstruction_inputs(self, stage: str) -> Callable[[Any], dict]:
        """Inputs of a geometry rule: pose2d, the bundle-adjusted rig (else the config rig's
        calibration file, if any) and, for triangulation, PS's 2D while PS is on."""

        def inputs(wildcards) -> dict:
            def own(name: str) -> str:
                return self.artifact(name).format(outdir=wildcards.outdir)

            files: dict[str, Any] = {"pose2d": own("pose2d")}
            if stage == "pictorial_structures":
                files["candidates"] = own("candidates")
            if self.flags["bundle_adjustment"]:
                files["bundle_adjustment"] = self.rig_artifact(wildcards)
            if stage == "triangulation" and self.flags["pictorial_structures"]:
                files["pictorial_structures"] = own("pictorial_structures")
            if not self.flags["bundle_adjustment"]:
                files["calibration"] = self.calibration_inputs(wildcards)
            return files

        return inputs

    def refinement_inputs(self, wildcards) -> dict:
        """Inputs of refinement: as a geometry rule's, plus the triangulation."""
        files = self.reconstruction_inputs("refinement")(wildcards)
        files["triangulation"] = self.artifact("triangulation").format(outdir=wildcards.outdir)
        return files

    def targets(self) -> list[str]:
        """Every final output of the run: each planned recording's, each session's summary."""
        names = [n for s in registry() if self.flags.get(s.name, True) for n in s.outputs]
        names += [f"{name}.mp4" for name in self.video_names]  # none with visualization off
        targets = [f"{rec.outdir}/{name}" for rec in self.planned for name in names]
        return targets + [str(s.summary) for s in self.sessions]

    def pose2d_gpus(self, wildcards) -> int:
        """A GPU only when the detector runs (imported 2D needs none)."""
        rec = self.recording(wildcards)
        return 0 if (rec.import_spec or self.config.import_spec) else 1

    def pose2d_mem_mb(self, wildcards) -> int:
        """The detector's memory; reading imported 2D needs far less (and sets its group's)."""
        return 8000 if self.pose2d_gpus(wildcards) else 2000

    def pose2d_runtime(self, wildcards) -> int:
        """Minutes: the detector's, or reading imported 2D's."""
        return 120 if self.pose2d_gpus(wildcards) else 15

    def pose2d_group(self, wildcards) -> str | None:
        """Imported 2D runs in its recording's group; the detector, and a session member's 2D
        (read by the session's solve, outside the group), on their own."""
        own = self.by_outdir.get(wildcards.outdir)
        if self.pose2d_gpus(wildcards) or (own is not None and own.id in self.session_of):
            return None
        return RECORDING_GROUP
