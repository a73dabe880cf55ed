"""The run configuration: loading (YAML or TOML), validation, typed per-stage views.

A :class:`Config` wraps the parsed mapping (:attr:`Config.data`) and, when read from a file, its
exact text (:attr:`Config.text`) so the run can snapshot it byte-for-byte. Every constructor
validates: all problems are raised together as one :class:`~flylib.errors.ConfigError`, one line
per problem, each naming its key path.

What each workflow stage reads of a config, and so what re-runs it, is its inputs object's params
(:mod:`flylib.pipeline.inputs`): the config stops at the pipeline layer; below it, algorithms take
arrays and the typed ``*Params`` views.

Modules: :mod:`.constants` (stage lists, known keys, :data:`DEFAULT_CONFIG_PATH`), :mod:`.checks`
(value checks), :mod:`.params` (the ``*Params`` dataclasses, :data:`~.params.PARAM_TABLES`),
:mod:`.loading` (YAML/TOML parsing), :mod:`.validation` (:func:`validate_config`),
:mod:`.canonical` (canonical forms) and :mod:`.core` (:class:`Config`).
"""

# ``X as X``: importable from here as before the split, though not in ``__all__``.
from .checks import Check as Check
from .constants import (
    DEFAULT_CONFIG_PATH,
    FRAME_SAMPLINGS as FRAME_SAMPLINGS,
    LEAST_SQUARES_RESERVED as LEAST_SQUARES_RESERVED,
    PARAM_STAGES,
    PRECISIONS as PRECISIONS,
    STAGE_DEFAULTS,
    STAGES,
    TOP_LEVEL_KEYS as TOP_LEVEL_KEYS,
    TRIANGULATION_METHODS as TRIANGULATION_METHODS,
)
from .core import Config
from .params import (
    LEAST_SQUARES_OPTIONS as LEAST_SQUARES_OPTIONS,
    BundleAdjustmentParams,
    IoParams,
    PictorialParams,
    Pose2dParams,
    TriangulationParams,
)
from .validation import validate_config as validate_config

__all__ = [
    "BundleAdjustmentParams",
    "Config",
    "DEFAULT_CONFIG_PATH",
    "IoParams",
    "PARAM_STAGES",
    "PictorialParams",
    "Pose2dParams",
    "STAGES",
    "STAGE_DEFAULTS",
    "TriangulationParams",
]
