"""The :class:`Config` object: construction, typed views, stage parameters, snapshot."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError
from ..skeleton import Skeleton
from ..stages import registry
from .canonical import plain
from .constants import DEFAULT_CONFIG_PATH
from .loading import parse_text, problem_error, read_config_text
from .params import PARAM_TABLES, build_params
from .sources import source_patterns, view_names
from .validation import validate_config


class Config:
    """A loaded, validated flylib run configuration (:meth:`from_file`, :meth:`from_dict`,
    :meth:`default`, ...).

    Attributes
    ----------
    data
        The parsed mapping.
    text
        The exact source text when read from a file (``None`` for a dict): what
        :meth:`save_snapshot` writes back byte-for-byte.
    source
        The file it was read from, or ``None``.
    format
        ``"yaml"`` or ``"toml"``: the snapshot's format.
    """

    def __init__(
        self,
        data: Mapping,
        *,
        text: str | None = None,
        source: Path | None = None,
        format: str = "yaml",
    ) -> None:
        self.data: dict = dict(data)
        self.text = text
        self.source = source
        self.format = format
        problems = validate_config(self.data)
        if problems:
            raise problem_error(str(source or "<dict>"), problems)

    def __repr__(self) -> str:
        return f"Config(source={str(self.source) if self.source else None!r})"

    @classmethod
    def from_file(cls, path: str | Path) -> Config:
        """Load a ``.yaml``, ``.yml`` or ``.toml`` config; a ConfigError if the file is missing,
        has another suffix, does not parse or is invalid."""
        suffix = Path(path).suffix.lower()
        if suffix in (".yaml", ".yml"):
            return cls.from_yaml(path)
        if suffix == ".toml":
            return cls.from_toml(path)
        raise ConfigError(
            f"{path}: unknown config format {suffix!r}; use a .yaml, .yml or .toml file"
        )

    @classmethod
    def from_yaml(cls, path: str | Path) -> Config:
        """Load a YAML config file (keeping its text for the snapshot)."""
        return cls._from_path(Path(path), "yaml")

    @classmethod
    def from_toml(cls, path: str | Path) -> Config:
        """Load a TOML config file (keeping its text for the snapshot)."""
        return cls._from_path(Path(path), "toml")

    @classmethod
    def _from_path(cls, path: Path, fmt: str) -> Config:
        text = read_config_text(path, str(path))
        return cls(parse_text(text, fmt, str(path)), text=text, source=path, format=fmt)

    @classmethod
    def from_dict(cls, data: Mapping) -> Config:
        """Wrap an already-parsed mapping, deep-copied (Snakemake's ``config``); no source text."""
        return cls(copy.deepcopy(dict(data)))

    @classmethod
    def default(cls) -> Config:
        """The packaged default config (:data:`DEFAULT_CONFIG_PATH`): the 7-camera fly rig."""
        return cls.from_yaml(DEFAULT_CONFIG_PATH)

    @classmethod
    def of_outputs(cls, outdir: str | Path) -> Config:
        """The config a run used: the snapshot ``config.yaml`` (or ``.toml``) every run
        leaves in its output directory ``outdir``, else :meth:`default`."""
        snapshots = (Path(outdir) / "config.yaml", Path(outdir) / "config.toml")
        snapshot = next((p for p in snapshots if p.is_file()), None)
        return cls.from_file(snapshot) if snapshot else cls.default()

    def params(self, table: str) -> Any:
        """The typed view of ``table`` (a key of :data:`~flylib.config.params.PARAM_TABLES`):
        its class's ``from_table`` when it has one, else :func:`~.params.build_params`."""
        cls = PARAM_TABLES[table]
        values = self.data.get(table) or {}
        from_table = getattr(cls, "from_table", None)
        return from_table(values) if from_table else build_params(cls, values)

    def __getattr__(self, name: str) -> Any:
        """A params table by its name, :meth:`params` (``config.triangulation``: a
        :class:`~.params.TriangulationParams`); every stage's from its record."""
        if not name.startswith("_") and name in PARAM_TABLES:
            return self.params(name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def visualization(self) -> dict:
        """The raw ``visualization`` table (parsed by ``flylib.visualization``)."""
        return self.data.get("visualization") or {}

    @property
    def import_spec(self) -> dict | None:
        """The ``pose2d.import`` table (read 2D from another tool), or ``None``."""
        return (self.data.get("pose2d") or {}).get("import")

    def stage_flags(self) -> dict[str, bool]:
        """``stage -> enabled`` for every toggled stage (``pipeline.do_<stage>``, else its default)."""
        pipeline = self.data.get("pipeline") or {}
        flags: dict[str, bool] = {}
        for stage in registry():  # run order: a stage's upstream flags are final before it
            if stage.toggled:
                on = bool(pipeline.get(f"do_{stage.name}", stage.default_on))
                if stage.needs_one_of:
                    on &= any(flags.get(up, True) for up in stage.needs_one_of)
                flags[stage.name] = on
        return flags

    def view_names(self) -> list[str]:
        """The camera (view) names in config order: the V axis of every points array.

        The ``cameras`` table (``defaults`` excluded), else (a rig from a calibration file)
        the ``pose2d.output_points`` views.
        """
        return view_names(self, required=False)

    def camera_table(self) -> tuple[dict, dict]:
        """``cameras.defaults`` and ``name -> spec`` for every real camera."""
        cameras = dict(self.data.get("cameras") or {})
        defaults = cameras.pop("defaults", {}) or {}
        return dict(defaults), cameras

    def source_patterns(self) -> dict[str, str]:
        """``sources[].name -> filename`` (else the name), in config order; none is a ConfigError."""
        return source_patterns(self)

    def skeleton_table(self) -> dict:
        """The ``skeleton`` table; a ConfigError when the config has none."""
        if "skeleton" not in self.data:
            raise ConfigError(
                f"{self.source or 'config'}: no 'skeleton' table; add one or use Skeleton.fly()"
            )
        return self.data["skeleton"]

    def skeleton(self) -> Skeleton:
        """The configured skeleton, or the default fly skeleton when there is no ``skeleton`` table."""
        return Skeleton.from_config(self) if self.data.get("skeleton") else Skeleton.fly()

    def snapshot_text(self) -> str:
        """The text :meth:`save_snapshot` writes: the source text, or a YAML dump for a dict."""
        if self.text is not None:
            return self.text
        return yaml.safe_dump(
            plain(self.data), sort_keys=False, default_flow_style=None, allow_unicode=True
        )

    def save_snapshot(self, outdir: str | Path) -> Path:
        """Write ``<outdir>/config.yaml`` (or ``.toml``): the source text byte-for-byte,
        atomically (a dict config as YAML); removes a snapshot of the other format, so the
        directory holds exactly one. Returns the snapshot file."""
        from ..paths import atomic_path

        fmt = self.format if self.text is not None else "yaml"
        target = Path(outdir) / f"config.{fmt}"
        with atomic_path(target) as tmp:
            tmp.write_bytes(self.snapshot_text().encode("utf-8"))
        stale = target.with_suffix(".toml" if fmt == "yaml" else ".yaml")
        stale.unlink(missing_ok=True)
        return target
