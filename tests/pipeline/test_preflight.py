"""The run's preflight (:func:`flylib.pipeline.preflight.load_run_config`)."""

from __future__ import annotations

import yaml

from flylib.config import Config
from flylib.config.layers import ConfigLayers
from flylib.paths import DEFAULT_CONFIG_PATH
from flylib.pipeline.demo import demo_import_spec, make_demo
from flylib.pipeline.preflight import load_run_config


def test_the_planned_recordings_keep_the_import_files_preflight_found(tmp_path, monkeypatch):
    """The workflow's pose2d inputs are the files preflight found, kept on each Recording
    (issue 38: finding them a second time made a 1,000-recording dry run slower)."""
    import flylib.interop.importer as importer

    base = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    config = Config.from_dict(base)
    make_demo(config, tmp_path / "rec", frames=2)
    spec = demo_import_spec(config)
    files = ";".join(f"{view}={name}" for view, name in spec["files"].items())
    sheet = tmp_path / "recordings.tsv"
    sheet.write_text(
        f"path\timport_format\timport_files\n{tmp_path / 'rec'}\t{spec['format']}\t{files}\n"
    )
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**base, "recordings": str(sheet)}))
    found = []
    real = importer.import_files
    monkeypatch.setattr(importer, "import_files", lambda *a: found.append(a) or real(*a))

    _, recordings = load_run_config(ConfigLayers.from_files([str(tmp_path / "config.yaml")]))

    (rec,) = recordings
    assert rec.import_files == tuple(sorted({tmp_path / "rec" / n for n in spec["files"].values()}))
    assert len(found) == 1  # each recording's files looked up once
