"""The :class:`Config` object: construction, typed views, stage parameters, snapshot."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import fields
from pathlib import Path

import yaml

from ..errors import ConfigError
from ..skeleton import Skeleton
from ..stages import REGISTRY
from .canonical import plain
from .constants import DEFAULT_CONFIG_PATH
from .loading import parse_text, problem_report
from .neuromechfly import NeuromechflyParams
from .params import (
    BundleAdjustmentParams,
    IoParams,
    PictorialParams,
    Pose2dParams,
    TriangulationParams,
    build_params,
)
from .postprocessing import KinematicsParams, RefinementParams
from .sources import source_patterns, view_names
from .validation import validate_config


class Config:
    """A loaded, validated flylib run configuration.

    Build one with :meth:`from_file` (``.yaml``/``.yml``/``.toml``), :meth:`from_yaml`,
    :meth:`from_toml`, :meth:`from_dict` or :meth:`default`.

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
            error = ConfigError(problem_report(str(source or "<dict>"), problems))
            error.problems = problems  # type: ignore[attr-defined]
            raise error

    def __repr__(self) -> str:
        return f"Config(source={str(self.source) if self.source else None!r})"

    # -- construction --------------------------------------------------------

    @classmethod
    def from_file(cls, path: str | Path) -> Config:
        """Load a config, choosing YAML or TOML by the suffix (``.yaml``, ``.yml``, ``.toml``).

        Raises
        ------
        ConfigError
            If the file is missing, has another suffix, does not parse or is invalid.
        """
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
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raise ConfigError(f"{path}: config file not found; check the path") from None
        except IsADirectoryError:
            raise ConfigError(f"{path}: is a directory, not a config file") from None
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise ConfigError(f"{path}: not UTF-8 text ({err}); save it as UTF-8") from None
        return cls(parse_text(text, fmt, str(path)), text=text, source=path, format=fmt)

    @classmethod
    def from_dict(cls, data: Mapping) -> Config:
        """Wrap an already-parsed mapping, deep-copied (library use, Snakemake's
        ``config``); no source text."""
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

    # -- typed per-stage views -------------------------------------------------

    @property
    def pose2d(self) -> Pose2dParams:
        """The scalar ``pose2d`` settings."""
        return build_params(Pose2dParams, self.data.get("pose2d") or {})

    @property
    def triangulation(self) -> TriangulationParams:
        """The ``triangulation`` table."""
        return build_params(TriangulationParams, self.data.get("triangulation") or {})

    @property
    def refinement(self) -> RefinementParams:
        """The ``refinement`` table."""
        return build_params(RefinementParams, self.data.get("refinement") or {})

    @property
    def kinematics(self) -> KinematicsParams:
        """The ``kinematics`` table."""
        return KinematicsParams.from_table(self.data.get("kinematics") or {})

    @property
    def neuromechfly(self) -> NeuromechflyParams:
        """The ``neuromechfly`` table."""
        return build_params(NeuromechflyParams, self.data.get("neuromechfly") or {})

    @property
    def pictorial(self) -> PictorialParams:
        """The ``pictorial_structures`` table."""
        return build_params(PictorialParams, self.data.get("pictorial_structures") or {})

    @property
    def bundle_adjustment(self) -> BundleAdjustmentParams:
        """The ``bundle_adjustment`` table; keys it does not name go to ``least_squares``."""
        table = dict(self.data.get("bundle_adjustment") or {})
        own = {f.name for f in fields(BundleAdjustmentParams)}
        leftovers = {k: v for k, v in table.items() if k not in own}
        params = build_params(BundleAdjustmentParams, {k: v for k, v in table.items() if k in own})
        return BundleAdjustmentParams(**{**params.__dict__, "least_squares": leftovers})

    @property
    def io(self) -> IoParams:
        """Frame-reading settings (``io.image.workers``; 0 means let the reader choose)."""
        workers = ((self.data.get("io") or {}).get("image") or {}).get("workers")
        on_corrupt = (self.data.get("io") or {}).get("on_corrupt_frame") or "error"
        return IoParams(image_workers=workers or None, on_corrupt_frame=on_corrupt)

    @property
    def visualization(self) -> dict:
        """The raw ``visualization`` table (parsed by ``flylib.visualization``)."""
        return self.data.get("visualization") or {}

    @property
    def import_spec(self) -> dict | None:
        """The ``pose2d.import`` table (read 2D from another tool), or ``None``."""
        return (self.data.get("pose2d") or {}).get("import")

    # -- pipeline orchestration ---------------------------------------------

    def stage_flags(self) -> dict[str, bool]:
        """``stage -> enabled`` for every stage in :data:`STAGES` (``pipeline.do_<stage>``,
        else :data:`STAGE_DEFAULTS`)."""
        pipeline = self.data.get("pipeline") or {}
        flags: dict[str, bool] = {}
        for stage in REGISTRY:  # run order: a stage's upstream flags are final before it
            if stage.toggled:
                on = bool(pipeline.get(f"do_{stage.name}", stage.default_on))
                if stage.needs_one_of:
                    on &= any(flags.get(up, True) for up in stage.needs_one_of)
                flags[stage.name] = on
        return flags

    # -- structured sections ---------------------------------------------------

    def view_names(self) -> list[str]:
        """The camera (view) names in config order: the V axis of every points array.

        Taken from the ``cameras`` table (``defaults`` excluded); a config whose rig
        comes from a calibration file and names no cameras falls back to the
        ``pose2d.output_points`` views.
        """
        return view_names(self, required=False)

    def camera_table(self) -> tuple[dict, dict]:
        """``cameras.defaults`` and ``name -> spec`` for every real camera."""
        cameras = dict(self.data.get("cameras") or {})
        defaults = cameras.pop("defaults", {}) or {}
        return dict(defaults), cameras

    def source_patterns(self) -> dict[str, str]:
        """Each footage source's glob (``sources[].name -> filename``, else its name), in
        config order; a config listing no sources is a ConfigError."""
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

    # -- snapshot ----------------------------------------------------------------

    def snapshot_text(self) -> str:
        """The text :meth:`save_snapshot` writes: the source text, or a YAML dump for a dict."""
        if self.text is not None:
            return self.text
        return yaml.safe_dump(
            plain(self.data), sort_keys=False, default_flow_style=None, allow_unicode=True
        )

    def save_snapshot(self, outdir: str | Path) -> Path:
        """Write the config that drives this run to ``<outdir>/config.yaml`` (or ``.toml``).

        The source text is copied byte-for-byte, atomically; a config built from a
        dict is written as YAML. A snapshot of the other format left by an earlier
        run is removed so the directory holds exactly one. Returns the snapshot file.
        """
        from ..paths import atomic_path

        fmt = self.format if self.text is not None else "yaml"
        target = Path(outdir) / f"config.{fmt}"
        with atomic_path(target) as tmp:
            tmp.write_bytes(self.snapshot_text().encode("utf-8"))
        stale = target.with_suffix(".toml" if fmt == "yaml" else ".yaml")
        stale.unlink(missing_ok=True)
        return target
