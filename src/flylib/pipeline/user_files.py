"""Inputs are never outputs: a run's planned files checked against the user's, before any job.

Every file a recording's jobs would write (:func:`planned_outputs`) is compared with every
file the run reads (footage, imported 2D, calibration, config files, recording sheets,
corrections, ``nwb.yaml``) and with the files already in the output folder. A planned output
that is an input, or an existing file flylib did not write, stops the run with one line
naming the file, both roles and the fix.

flylib's own files: those listed in an output folder's :data:`flylib.paths.OUTPUTS_MANIFEST`
(written once a run claims the folder, :func:`record_planned`); any HDF5 file carrying
flylib's ``meta`` attribute; and all of a folder without a manifest but with flylib's stage
artifacts (written before the manifest existed).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ..paths import (
    OUTPUTS_MANIFEST,
    real_paths,
    record_outputs,
    recorded_outputs,
    written_by_flylib,
)

__all__ = ["NWB_FILE", "output_problems", "planned_outputs", "record_planned"]

#: The NWB export's file name in a recording's output folder.
NWB_FILE = "results.nwb"
_FIX = "set outdir to another folder, e.g. '{recording}/flylib_outputs'"


def planned_outputs(config: Any, flags: Mapping[str, bool]) -> dict[str, str]:
    """``name`` (relative to the outdir) ``-> what writes it`` (e.g. ``"assemble's
    calibration.toml"``) of every file a recording's jobs write under ``flags``."""
    from ..results.artifacts import candidates_artifact
    from ..stages import registry

    out: dict[str, str] = {}
    for stage in registry():  # each stage's artifact and outputs (assemble's results.h5, ...)
        if flags.get(stage.name, True):
            owner = stage.name + ("'" if stage.name.endswith("s") else "'s")
            names = [f"stages/{stage.artifact}"] if stage.artifact else []
            out |= {name: f"{owner} {name}" for name in [*names, *stage.outputs]}
    if flags.get("pose2d", True) and flags.get("pictorial_structures", False):
        name = candidates_artifact(config.pictorial_structures.k)
        out[f"stages/{name}"] = f"pose2d's stages/{name}"
    out["config.yaml"] = "assemble's config.yaml"
    # the snapshot of the other format, which assemble removes (Config.save_snapshot)
    out["config.toml"] = "assemble (it deletes an earlier run's config.toml snapshot)"
    if flags.get("visualization", True):
        from ..visualization.specs import video_specs

        for video in video_specs(config):
            out[f"{video.name}.mp4"] = f"visualization's {video.name}.mp4"
    if (config.data.get("exports") or {}).get("nwb"):
        out[NWB_FILE] = f"export_nwb's {NWB_FILE}"
    return out


def _run_inputs(config: Any, rec: Any, config_files: Iterable[str]) -> dict[str, str]:
    """``path -> role`` of the files one recording's run reads."""
    from ..config.nwb_metadata import sidecar_inputs
    from ..corrections import corrections_path
    from ..errors import FlylibError
    from .planning import calibration_inputs

    inputs = {str(f): f"recording {rec.id}'s footage" for f in rec.footage}
    for f in config_files:
        inputs[str(f)] = "a config file of the run"
    sheet = rec.extra.get("sheet")
    if sheet:
        inputs[str(sheet)] = "the recordings sheet"
    try:
        for f in calibration_inputs(config, rec.path):
            inputs[str(f)] = "the run's calibration file (calibration.file)"
    except FlylibError:
        pass  # reported by the rig's own check
    if rec.import_spec is not None and not rec.demo:
        files = rec.import_files
        if files is None:  # not found by the run's preflight yet
            from .pose2d import import_inputs, import_target

            try:
                files = import_inputs(import_target(config), rec.import_spec, rec.path)
            except FlylibError:
                files = []  # reported by the import's own check
        for f in files:
            inputs[str(f)] = "an imported 2D file (pose2d.import)"
    for f in sidecar_inputs(rec):
        inputs[f] = "the recording's nwb.yaml"
    try:
        path, _ = corrections_path(config.data.get("corrections"), rec.outdir, rec.path, rec.id)
        inputs[str(path)] = "the recording's corrections (corrections)"
    except FlylibError:
        pass
    return inputs


def _adopted(outdir: Path) -> bool:
    """A folder written by a flylib from before the manifest: its stage artifacts."""
    stages = outdir / "stages"
    try:
        return any(written_by_flylib(p, hdf5=True) for p in stages.glob("*.h5"))
    except OSError:
        return False


def output_problems(
    config: Any, recordings: Iterable[Any], config_files: Iterable[str] = ()
) -> list[str]:
    """One ``outdir: ...`` line per planned output that is an input of the run or an existing
    file flylib did not write (only names and stats are read)."""
    planned = planned_outputs(config, config.stage_flags())
    real = real_paths()
    config_files = [real(f) for f in config_files]
    problems: list[str] = []
    for rec in recordings:
        outdir = Path(os.path.realpath(rec.outdir))
        inputs = {real(p): role for p, role in _run_inputs(config, rec, config_files).items()}
        for name, writer in planned.items():
            role = inputs.get(str(outdir / name))
            if role is not None:
                problems.append(
                    f"outdir: {rec.outdir / name} is {role} and would be "
                    f"{'deleted' if 'deletes' in writer else 'overwritten'} by {writer}; {_FIX}"
                )
        if rec.demo or not outdir.is_dir():
            continue
        known = recorded_outputs(outdir)
        if known is None and _adopted(outdir):
            continue
        for name, writer in planned.items():
            path = outdir / name
            if str(path) in inputs or name in (known or ()) or not os.path.lexists(path):
                continue
            if name.endswith(".h5") and written_by_flylib(path, hdf5=True):
                continue
            problems.append(
                f"outdir: {rec.outdir / name} exists and was not written by flylib (not in "
                f"{OUTPUTS_MANIFEST}) and would be "
                f"{'deleted' if 'deletes' in writer else 'overwritten'} by {writer}; move it "
                f"away or {_FIX}"
            )
    return problems


def record_planned(config: Any, outdirs: Iterable[str | Path]) -> None:
    """Record the planned outputs in each claimed output folder's manifest (the next run
    replaces them as flylib's)."""
    names = list(planned_outputs(config, config.stage_flags()))
    for outdir in outdirs:
        Path(outdir).mkdir(parents=True, exist_ok=True)
        record_outputs(outdir, names)
