"""The NWB export of one recording (rule ``export_nwb``, ``flylib export --nwb``): the
``exports`` and ``nwb`` tables tracked, the footage lookup and config text not."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..interop.views import footage_files
from .inputs import StageInputs
from .visualization import footage_globs

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NwbExportRuntime:
    """Untracked: ``footage`` (linked from the file, itself a rule input) and ``config_text``
    (stored in the file as the config that produced the result)."""

    footage: tuple[tuple[str, str | None], ...] = ()
    config_text: str | None = None


@dataclass(frozen=True)
class NwbExportInputs(StageInputs):
    """The NWB export's inputs. ``nwb`` rebuilt from the rule's JSON holds date-times as
    ISO 8601 text, which the metadata parser reads back as the same date-times."""

    STAGE = "export_nwb"

    exports: Mapping[str, Any]
    nwb: Mapping[str, Any] | None
    runtime: NwbExportRuntime = NwbExportRuntime()

    @classmethod
    def from_config(cls, config) -> NwbExportInputs:
        return cls(
            exports=dict(config.data.get("exports") or {}),
            nwb=config.data.get("nwb"),
            runtime=NwbExportRuntime(footage_globs(config), config.snapshot_text()),
        )

    def rule_params(self) -> str:
        """The rule's ``params.stage``: sorted JSON, YAML's date-times as text."""
        return json.dumps(self.params(), sort_keys=True, default=str)


def session_metadata(
    inputs: NwbExportInputs,
    recording_dir: str | Path | None,
    *,
    demo: bool = False,
    extra: Mapping | None = None,
) -> dict[str, Any]:
    """The recording's checked session metadata from the ``nwb`` table; ConfigError names every
    problem at once."""
    from ..config.nwb_metadata import recording_metadata

    return recording_metadata(inputs.nwb, recording_dir, demo=demo, extra=extra)


def run_export_nwb(
    inputs: NwbExportInputs,
    results_path: str | Path,
    out_path: str | Path,
    *,
    recording_dir: str | Path | None = None,
    demo: bool = False,
    extra_metadata: Mapping | None = None,
    angles_path: str | Path | None = None,
) -> Path:
    """Export a run's ``results.h5`` as NWB, checking the session metadata first (ConfigError
    naming every problem, or no frame rate). ``recording_dir``'s footage is linked;
    ``demo``: the demo's metadata defaults; ``angles_path``: a ``neuromechfly.h5`` to include.
    """
    from ..interop.nwb import export_nwb

    metadata = session_metadata(inputs, recording_dir, demo=demo, extra=extra_metadata)
    footage = (
        footage_files(inputs.runtime.footage, Path(recording_dir))
        if recording_dir is not None
        else {}
    )
    return export_nwb(
        results_path,
        out_path,
        metadata,
        footage=footage,
        recording_dir=recording_dir,
        config_text=inputs.runtime.config_text,
        angles_path=angles_path,
    )


def export_nwb_command(
    results_path: str | Path,
    out_path: str | Path,
    *,
    config_path: str | Path | None = None,
    recording: str | Path | None = None,
    metadata_path: str | Path | None = None,
) -> Path:
    """``flylib export RESULTS_H5 --nwb OUT``: :func:`run_export_nwb` with ``config_path``
    defaulting to the snapshot beside ``results.h5`` (else the default config) and
    ``recording`` to the one it records. ``metadata_path`` overrides the ``nwb`` table and the
    recording's ``nwb.yaml``."""
    from ..config import Config
    from ..config.nwb_metadata import read_sidecar
    from ..results import open_checked, read_meta_from

    results_path = Path(results_path)
    with open_checked(results_path, "pass the results.h5 a run wrote") as f:
        meta = read_meta_from(f)
    if config_path is None:
        snapshots = [results_path.parent / f"config.{ext}" for ext in ("yaml", "toml")]
        config_path = next((p for p in snapshots if p.is_file()), None)
        if config_path is None:
            log.warning(
                "%s: no config snapshot beside it; using flylib's default config "
                "(pass --config for the run's)",
                results_path,
            )
    config = Config.from_file(config_path) if config_path is not None else Config.default()
    if recording is None and meta.get("recording"):
        recording = Path(meta["recording"])
        if not recording.is_dir():
            log.warning(
                "%s names recording %s, which is not a directory here; no video is linked "
                "(pass --recording)",
                results_path,
                recording,
            )
            recording = None
    extra = None
    if metadata_path is not None:
        if not Path(metadata_path).is_file():
            raise ConfigError(f"{metadata_path}: --nwb-metadata file not found")
        extra = read_sidecar(metadata_path)
    return run_export_nwb(
        NwbExportInputs.from_config(config),
        results_path,
        out_path,
        recording_dir=recording,
        extra_metadata=extra,
    )
