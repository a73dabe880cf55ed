"""Which config produced an artifact: params hashes recorded in every flylib HDF5 file.

Each stage artifact's ``meta`` records ``params_sha256``, the hash of the params that stage's
result depends on (:func:`flylib.pipeline.inputs.stage_params`: exactly what the workflow
rule tracks as its ``params``), and ``upstream_params_sha256``, the hashes recorded in the
artifacts it was built from. ``results.h5`` keeps each stage group's meta and adds the
assemble stage's own. From these :func:`provenance_report` tells

* a *stale* stage: made with params other than what a config gives now;
* a *mixed* file: a stage built from an upstream artifact other than the one assembled
  beside it (e.g. triangulation from an older pose2d);
* a results file assembled from other artifacts than those in ``stages/``.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "ProvenanceRow",
    "file_sha256",
    "foreign_artifacts",
    "params_hash",
    "provenance_report",
    "refuse_stale_inputs",
    "stage_provenance",
    "stale_artifacts",
]

#: meta key of an artifact's own params hash.
PARAMS_KEY = "params_sha256"
#: meta key of ``{upstream stage: params hash}`` the artifact was built from.
UPSTREAM_KEY = "upstream_params_sha256"
#: meta key of ``{"host", "cwd", "outdir"?}``: where the artifact's writer ran (a Snakemake
#: job's working directory is its run's) and the output directory it wrote (when it held
#: that directory's lock), which tells a copy.
WRITER_KEY = "writer"
#: meta key of the artifact's own random id (two artifacts with equal params differ).
ARTIFACT_ID_KEY = "artifact_id"
#: meta key of ``{upstream stage: artifact id}`` the artifact was built from.
UPSTREAM_IDS_KEY = "upstream_artifact_ids"


def params_hash(params: Mapping[str, Any]) -> str:
    """A short, stable hash of JSON-serialisable params (canonical JSON, SHA-256, 16 lowercase
    hex digits)."""
    text = json.dumps(params, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def stage_provenance(
    params: Mapping[str, Any], stage: str, upstream: Mapping[str, str | Path | None] | None = None
) -> dict:
    """The provenance entries of a stage artifact's ``meta``: ``{"params_sha256": ...,
    "artifact_id": ..., "writer": {...}, "upstream_params_sha256": {stage: hash},
    "upstream_artifact_ids": {stage: id}}``.

    ``params`` are the stage's tracked params (:func:`flylib.pipeline.inputs.stage_params`),
    ``stage`` a :data:`flylib.config.PARAM_STAGES` name, ``upstream`` maps each upstream
    stage to the artifact path the stage read (``None`` entries skipped).
    """
    from .locking import held_outdir
    from .results import read_meta

    if not isinstance(params, Mapping):
        raise TypeError(
            f"stage_provenance(params, {stage!r}, ...) takes the stage's params mapping "
            f"(flylib.pipeline.inputs.stage_params(config, {stage!r})), not a "
            f"{type(params).__name__}"
        )
    writer = {"host": socket.gethostname(), "cwd": os.getcwd()}
    if held_outdir() is not None:
        writer["outdir"] = str(held_outdir())
    out: dict[str, Any] = {
        PARAMS_KEY: params_hash(params),
        ARTIFACT_ID_KEY: uuid.uuid4().hex[:16],
        WRITER_KEY: writer,
    }
    hashes, ids = {}, {}
    for name, path in (upstream or {}).items():
        if path:
            meta = read_meta(path)
            hashes[name] = meta.get(PARAMS_KEY)
            if meta.get(ARTIFACT_ID_KEY):
                ids[name] = meta[ARTIFACT_ID_KEY]
    if hashes:
        out[UPSTREAM_KEY] = hashes
    if ids:
        out[UPSTREAM_IDS_KEY] = ids
    return out


@dataclass
class ProvenanceRow:
    """One stage of a results file (``assemble`` for the file itself): the params hash it
    ``recorded`` (``None``: an older flylib), the one the compared config gives
    (``expected``; ``None`` without a config), one line per inconsistency (``problems``),
    and ``status``: ``ok``, ``stale`` (params differ from the config's, or a corrections
    sidecar beside the file was not applied), ``mixed`` (built from other upstream
    artifacts) or ``unknown`` (no hash recorded)."""

    stage: str
    recorded: str | None
    expected: str | None
    problems: list[str]
    status: str


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes, 16 hex digits (e.g. the corrections sidecar applied)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def _group_metas(path: Path) -> tuple[dict, dict[str, dict], dict | None]:
    """The root meta, each stage group's meta, and the corrections the triangulation group
    records having applied (``None``: none)."""
    from .results import STAGE_GROUPS, open_checked, read_meta_from

    with open_checked(path, "pass a results.h5 a run wrote") as f:
        root = read_meta_from(f)
        groups = {stage: read_meta_from(f[stage]) for stage in STAGE_GROUPS if stage in f}
        applied = f["triangulation"].attrs.get("corrections") if "triangulation" in f else None
    if isinstance(applied, bytes):
        applied = applied.decode()
    try:
        applied = json.loads(applied) if isinstance(applied, str) else None
    except ValueError:
        applied = None
    return root, groups, applied if isinstance(applied, dict) else None


def _corrections_problem(results: Path, applied: dict | None) -> str | None:
    """A line when the corrections sidecar beside ``results`` is not what its triangulation
    applied (never applied, or edited since)."""
    sidecar = results.parent / "corrections.h5"
    if not sidecar.is_file():
        return None
    if applied is None:
        return (
            f"{sidecar}: manual corrections that the triangulation in {results.name} did not "
            "apply; re-run the workflow to apply them"
        )
    if applied.get("sha256") and applied["sha256"] != file_sha256(sidecar):
        return (
            f"{sidecar}: changed since the triangulation in {results.name} applied it "
            f"({applied.get('count')} corrections then); re-run the workflow to apply it"
        )
    return None


def snapshot_beside(results: str | Path) -> Path | None:
    """The config snapshot the workflow writes beside ``results.h5``, if there is one."""
    results = Path(results)
    for name in ("config.yaml", "config.toml"):
        candidate = results.parent / name
        if candidate.is_file():
            return candidate
    return None


#: ``stage -> the params a config gives it`` (``None``: nothing to compare with).
ParamsOf = Callable[[str], "Mapping[str, Any] | None"]


def provenance_report(
    results: str | Path, params_of: ParamsOf | None = None, stages_dir: str | Path | None = None
) -> list[ProvenanceRow]:
    """Check a ``results.h5``'s recorded params hashes for a stale or mixed state: one row
    per stage in the file, then ``assemble``.

    ``params_of`` (:func:`flylib.pipeline.planning.params_of`) gives the params of the
    config to compare with, asked for each stage in the file and ``assemble``
    (``session_calibration`` for a session's rig); ``None`` checks only consistency.
    ``stages_dir`` (default: ``stages/`` beside the file, when it exists) is where the file
    was assembled from: each artifact there must carry the hash the file holds.
    """
    from .results import ARTIFACTS, read_meta

    results = Path(results)
    root, groups, applied = _group_metas(results)
    recorded = {stage: meta.get(PARAMS_KEY) for stage, meta in groups.items()}
    recorded_ids = {stage: meta.get(ARTIFACT_ID_KEY) for stage, meta in groups.items()}
    if stages_dir is None and (results.parent / "stages").is_dir():
        stages_dir = results.parent / "stages"
    rows = []
    for stage, meta in [*groups.items(), ("assemble", root)]:
        own = meta.get(PARAMS_KEY)
        problems: list[str] = []
        status = "unknown" if own is None else "ok"
        # a session's rig: its params are the session solve's, and stages/ holds the
        # recording's own solve
        session_rig = stage == "bundle_adjustment" and bool(meta.get("session"))
        asked = "session_calibration" if session_rig else stage
        params = params_of(asked) if params_of is not None else None
        expected = params_hash(params) if params is not None else None
        if expected is not None and own is not None and own != expected:
            status = "stale"
            problems.append(
                f"{results}: {stage} is stale: made with params {own}, but the config "
                f"gives {expected}; re-run the workflow with that config"
            )
        for upstream, built_from in (meta.get(UPSTREAM_KEY) or {}).items():
            present = recorded.get(upstream)
            if upstream in recorded and built_from != present:
                status = "mixed" if status != "stale" else status
                problems.append(
                    f"{results}: {stage} was built from {upstream} params {built_from}, but "
                    f"the {upstream} in this file has {present}; the file mixes runs: re-run the workflow"
                )
        for upstream, built_from in (meta.get(UPSTREAM_IDS_KEY) or {}).items():
            present = recorded_ids.get(upstream)
            if (
                present
                and built_from != present
                and recorded.get(upstream) == (meta.get(UPSTREAM_KEY) or {}).get(upstream)
            ):
                status = "mixed" if status != "stale" else status
                problems.append(
                    f"{results}: {stage} was built from another {upstream} artifact ({built_from}) "
                    f"than the one in this file ({present}), with equal params; the file mixes "
                    "runs or recordings: re-run the workflow"
                )
        if stages_dir is not None and stage != "assemble" and not session_rig:
            artifact = Path(stages_dir) / ARTIFACTS[stage]
            if artifact.is_file():
                disk_meta = read_meta(artifact)
                on_disk = disk_meta.get(PARAMS_KEY)
                disk_id, own_id = disk_meta.get(ARTIFACT_ID_KEY), meta.get(ARTIFACT_ID_KEY)
                if on_disk == own and disk_id and own_id and disk_id != own_id:
                    status = "mixed" if status != "stale" else status
                    problems.append(
                        f"{artifact}: another {stage} artifact ({disk_id}) than the one "
                        f"{results.name} holds ({own_id}), with equal params; results.h5 is not "
                        "assembled from these artifacts: re-run the workflow"
                    )
                if on_disk != own:
                    status = "mixed" if status != "stale" else status
                    problems.append(
                        f"{artifact}: params {on_disk}, but {results.name} holds {stage} with "
                        f"{own}; results.h5 is not assembled from these artifacts: re-run the workflow"
                    )
        if stage == "triangulation":
            unapplied = _corrections_problem(results, applied)
            if unapplied is not None:
                status = "stale" if status == "ok" else status
                problems.append(unapplied)
        rows.append(ProvenanceRow(stage, own, expected, problems, status))
    return rows


def _other_settings(path, stage: str, recorded, expected: str, against: str) -> str | None:
    """A line's start when ``path`` of ``stage`` records a params hash other than ``expected``
    (``None`` too when it records none: an older flylib)."""
    if recorded in (None, expected):
        return None
    return (
        f"{path}: made with other {stage} settings (params {recorded}) than {against} ({expected})"
    )


def refuse_stale_inputs(inputs: Mapping[str, Any], expected: Mapping[str, str]) -> None:
    """A ResultsError naming the first of a workflow job's ``inputs`` whose params hash is not
    ``expected`` (input name -> hash; ``results``: assemble's), e.g. written late by a killed
    run's job; it is set aside first, so that the next run makes it again."""
    from .errors import ResultsError
    from .results import read_meta

    for name, hash_ in expected.items():
        path = Path(str(inputs[name])) if name in inputs.keys() and inputs[name] else None
        recorded = read_meta(path).get(PARAMS_KEY) if path and path.is_file() else None
        stage = "assemble" if name == "results" else name
        line = _other_settings(path, stage, recorded, hash_, "this run's config")
        if line is not None:
            aside = path.with_name(f"{path.stem}.stale-{recorded}{path.suffix}")
            os.replace(path, aside)
            raise ResultsError(
                f"{line}, e.g. by a job of an earlier run that finished late; set aside as "
                f"{aside.name}: re-run the workflow to make it again"
            )


def stale_artifacts(results: str | Path, params_of: ParamsOf, against: str) -> list[str]:
    """One line per stage group of ``results`` and stage artifact in ``stages/`` beside it made
    with other params than ``params_of`` gives (``against``: that config's name)."""
    from .results import ARTIFACTS, read_meta

    results = Path(results)
    _, groups, _ = _group_metas(results)
    lines = []
    for stage, name in ARTIFACTS.items():
        session = bool(groups.get(stage, {}).get("session"))  # a session's rig, not stages/
        params = params_of("session_calibration" if session else stage)
        artifact = results.parent / "stages" / name
        found = [(f"{results}: its {stage} group", groups.get(stage), results.name)]
        if not session and artifact.is_file():
            found.append((artifact, read_meta(artifact), "it"))
        for where, meta, fix in found if params is not None else []:
            line = _other_settings(
                where, stage, (meta or {}).get(PARAMS_KEY), params_hash(params), against
            )
            if line:
                lines.append(f"{line}; delete {fix} and re-run the workflow to make it again")
    return lines


def foreign_artifacts(
    params_of: ParamsOf, recordings, *, cwd: str | Path | None = None
) -> list[str]:
    """Artifacts another working directory's run wrote with other params, one line each
    naming it and the fix.

    Snakemake tracks params per working directory: a run from another directory that wrote
    the same output directory with another config leaves artifacts this run's Snakemake
    takes as up to date. Flagged: those whose recorded writer's working directory differs
    from ``cwd`` (default: the current one) and whose params hash differs from what
    ``params_of`` gives (:func:`flylib.pipeline.planning.params_of` with ``run_only=True``;
    ``None`` for a stage the run does not write), and copies from another output directory.
    An artifact too damaged to tell gets a line too. ``recordings`` have an ``outdir``.
    """
    from .errors import ResultsError
    from .results import ARTIFACTS, read_meta

    here = str(Path(cwd or os.getcwd()).resolve())
    runs = [stage for stage in ARTIFACTS if params_of(stage) is not None]
    lines = []
    for rec in recordings:
        outdir = Path(rec.outdir)
        files = {stage: outdir / "stages" / ARTIFACTS[stage] for stage in runs}
        files["assemble"] = outdir / "results.h5"
        for stage, path in files.items():
            if not path.is_file():
                continue
            try:
                meta = read_meta(path)
            except ResultsError as err:  # the stage that reads it fails on it: say so now
                lines.append(f"{err} (only {rec.id} is affected)")
                continue
            writer = meta.get(WRITER_KEY) or {}
            recorded = meta.get(PARAMS_KEY)
            if not writer.get("cwd") or recorded is None:
                continue
            expected = params_hash(params_of(stage))
            written_in = writer.get("outdir")
            if written_in and Path(written_in) != outdir.resolve() and recorded != expected:
                lines.append(
                    f"{path}: copied from {written_in} (made there with other {stage} params, "
                    f"{recorded}; this config gives {expected}); Snakemake has no record of the "
                    f"copy and takes it as up to date: delete it or re-run with --forcerun {stage}"
                )
                continue
            if str(Path(writer["cwd"]).resolve()) == here:
                continue
            if recorded != expected:
                lines.append(
                    f"{path}: written by a run from {writer['cwd']} on {writer.get('host')} with other "
                    f"{stage} params ({recorded}, this config gives {expected}); this run's Snakemake "
                    f"does not know it and may take it as up to date: delete it or re-run with "
                    f"--forcerun {stage}"
                )
    return lines
