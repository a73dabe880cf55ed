"""Stage lists, known keys and option tuples shared by the config submodules."""

from __future__ import annotations

from ..paths import DEFAULT_CONFIG_PATH  # noqa: F401  (re-exported: flylib.config.DEFAULT_CONFIG_PATH)
from ..stages import derived, registry

#: The pipeline stages, in run order; each is toggled by ``pipeline.do_<stage>``.
STAGES: tuple[str, ...] = derived(lambda: [s.name for s in registry() if s.toggled])
#: Whether each stage runs when its ``pipeline.do_<stage>`` key is absent.
STAGE_DEFAULTS: dict[str, bool] = derived(
    lambda: {s.name: bool(s.default_on) for s in registry() if s.toggled}, mapping=True
)
#: The workflow rules whose params a stage's inputs object states (:mod:`flylib.pipeline.inputs`).
PARAM_STAGES: tuple[str, ...] = derived(lambda: [s.name for s in registry()])

TOP_LEVEL_KEYS: tuple[str, ...] = derived(
    lambda: (
        *("sources", "io", "skeleton", "cameras", "pipeline"),
        *STAGES,  # each stage's own table
        *("calibration", "recordings", "recursive", "outdir", "demo", "exports", "nwb"),
        "corrections",
    )
)
#: Keys of the ``exports`` table: extra per-recording outputs the workflow writes.
EXPORT_KEYS: tuple[str, ...] = ("nwb",)
TRIANGULATION_METHODS = ("ransac", "greedy", "dlt")
FRAME_SAMPLINGS = ("even", "confidence", "coverage", "diversity")
BA_SOLVERS = ("lm", "scipy")
BA_DISTORTION_MODES = ("auto", "free", "fixed")
# a tethered fly's thorax-coxa joints do not move (names missing from a skeleton are ignored)
TETHERED_RIGID_POINTS = tuple(f"{leg}_thorax_coxa" for leg in ("lf", "lm", "lh", "rf", "rm", "rh"))
PRECISIONS = ("float32", "float16", "bfloat16")
#: Sub-pixel refinements of a heatmap peak (``pose2d.models[].subpixel``, :mod:`flylib.pose2d.decode`).
SUBPIXEL_METHODS = ("weighted", "argmax", "taylor", "parabola")
POSE2D_PLAN_KEYS = ("preprocessors", "models", "pathways", "output_points", "weights", "import")
# least_squares arguments the bundle adjuster owns itself (the problem definition).
LEAST_SQUARES_RESERVED = (
    "fun",
    "x0",
    "jac",
    "bounds",
    "args",
    "kwargs",
    "jac_sparsity",
    "callback",
)
# least_squares arguments that change only speed or logging, never the result.
LEAST_SQUARES_PERF = ("verbose", "workers")
