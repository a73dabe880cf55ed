"""``flylib doctor``: the installation in one screen, and what in it blocks a run.

Each check gives one line: ``ok``, ``note`` (works, worth knowing: e.g. no GPU, no SLURM) or
``FAIL`` (a run cannot work until it is fixed); ``flylib doctor`` exits 1 on a ``FAIL``."""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from .paths import cache_dir

OK, NOTE, FAIL = "ok", "note", "FAIL"

#: What a workflow run imports (distribution name, import name): one missing is a FAIL.
REQUIRED = (
    ("numpy", "numpy"),
    ("scipy", "scipy"),
    ("torch", "torch"),
    ("jax", "jax"),
    ("h5py", "h5py"),
    ("av", "av"),
    ("opencv-python-headless", "cv2"),
    ("pandas", "pandas"),
    ("snakemake", "snakemake"),
    ("pyyaml", "yaml"),
    ("matplotlib", "matplotlib"),
)
#: Used by one command each (NWB export, the review GUI): one missing is a note.
OPTIONAL = (
    ("pynwb", "pynwb", "flylib export --nwb"),
    ("ndx-pose", "ndx_pose", "flylib export --nwb"),
    ("fastapi", "fastapi", "flylib gui"),
    ("uvicorn", "uvicorn", "flylib gui"),
)


@dataclass(frozen=True)
class Check:
    """One line of the report: ``status`` is ``ok``, ``note`` or ``FAIL``."""

    status: str
    what: str
    detail: str


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def _importable(module: str) -> str | None:
    """Why ``module`` does not import (one line), or ``None`` when it does."""
    try:
        importlib.import_module(module)
    except Exception as exc:  # a broken install fails in any way; report, never raise
        return " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
    return None


def check_packages() -> list[Check]:
    """Python and the packages a run needs (versions; FAIL for a missing or broken one)."""
    lines = [Check(OK, "python", f"{sys.version.split()[0]} ({sys.executable})")]
    flylib_version = _version("flylib") or "not installed (run from a source tree)"
    lines.append(Check(OK, "flylib", flylib_version))
    found, missing = [], []
    for dist, module in REQUIRED:
        version = _version(dist)
        why = _importable(module) if version else "not installed"
        if why:
            missing.append(f"{dist} ({why})")
        else:
            found.append(f"{dist} {version}")
    lines.append(Check(OK, "packages", ", ".join(found)))
    if missing:
        lines.append(
            Check(
                FAIL,
                "packages",
                f"missing or broken: {'; '.join(missing)}; re-run `bash install.sh`",
            )
        )
    for dist, module, used_by in OPTIONAL:
        version = _version(dist)
        if not version or _importable(module):
            lines.append(Check(NOTE, dist, f"not installed: {used_by} will not work"))
    snakemake = Path(sys.executable).with_name("snakemake")
    if not snakemake.exists() and shutil.which("snakemake") is None:
        lines.append(Check(FAIL, "snakemake", "no snakemake command beside this Python or on PATH"))
    return lines


def check_torch() -> list[Check]:
    """Where the detector runs: a CUDA GPU, Apple's GPU, or the CPU."""
    import torch

    if torch.cuda.is_available():
        names = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
        return [Check(OK, "torch device", f"CUDA {torch.version.cuda}: {names}")]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        return [Check(OK, "torch device", "Apple GPU (MPS)")]
    build = "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}"
    return [
        Check(
            NOTE,
            "torch device",
            f"CPU ({build}): the detector runs, slowly; imported 2D needs no GPU",
        )
    ]


def check_weights(config_files: Sequence[Path] = ()) -> list[Check]:
    """The detector checkpoint of every model the detection plan uses: present, or where to
    put it. Missing weights block only runs that detect (not the demo, not imports)."""
    from .config import Config, validate_config
    from .config.constants import DEFAULT_CONFIG_PATH
    from .config.layers import ConfigLayers
    from .errors import ConfigError
    from .pipeline.pose2d import Pose2dInputs
    from .pose2d.published import cached_checkpoint, checkpoint_problem

    layers = ConfigLayers.from_files([DEFAULT_CONFIG_PATH, *config_files])
    problems = validate_config(layers.data)
    if problems:
        raise ConfigError(layers.report(problems))
    config = Config(layers.data)
    plan = Pose2dInputs.from_config(config).detection_plan()
    own = (config.data.get("pose2d") or {}).get("weights") or {}
    lines = []
    for name in dict.fromkeys(p.model for p in plan.active_pathways()):
        spec = plan.models[name]
        key = f"pose2d.weights.{name}" if name in own else f"pose2d.models.{name}.weights"
        where = Path(spec.weights).expanduser() if spec.weights else None
        where = where or cached_checkpoint(spec.name, spec.model_class, spec.url)
        if where.is_file():
            lines.append(Check(OK, f"weights {name}", str(where)))
            continue
        problem = checkpoint_problem(spec, key, timeout=2.0)
        if problem is None:
            lines.append(Check(OK, f"weights {name}", f"downloads on first use to {where}"))
        else:
            lines.append(
                Check(NOTE, f"weights {name}", f"needed only to run the detector: {problem}")
            )
    return lines


def _folder_size(path: Path) -> tuple[int, int]:
    files = size = 0
    for root, _, names in os.walk(path):
        for name in names:
            try:
                size += os.stat(os.path.join(root, name)).st_size
                files += 1
            except OSError:
                continue
    return files, size


def check_caches() -> list[Check]:
    """The per-user cache (weights, compiled detectors, JAX kernels): writable, and how full."""
    root = cache_dir()
    try:
        root.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=root, prefix=".doctor-"):
            pass
    except OSError as exc:
        return [
            Check(
                FAIL,
                "cache",
                f"{root} is not writable ({exc.strerror or exc}); set FLYLIB_CACHE to a "
                "writable folder",
            )
        ]
    lines = [Check(OK, "cache", f"{root} (writable; FLYLIB_CACHE moves it)")]
    for sub, what in (("detector", "compiled detectors"), ("jax", "JAX kernels")):
        files, size = _folder_size(root / sub)
        detail = (
            f"{files} files, {size / 2**20:.1f} MiB" if files else "empty (filled by the first run)"
        )
        lines.append(Check(OK, f"cache {sub}", f"{what}: {detail}"))
    return lines


def check_cluster() -> list[Check]:
    """SLURM: the Snakemake executor plugin and ``sbatch`` (only for ``--profile profiles/slurm``)."""
    plugin = _version("snakemake-executor-plugin-slurm")
    sbatch = shutil.which("sbatch")
    if plugin and sbatch:
        return [Check(OK, "slurm", f"executor plugin {plugin}, sbatch at {sbatch}")]
    missing = [what for what, have in (("executor plugin", plugin), ("sbatch", sbatch)) if not have]
    return [Check(NOTE, "slurm", f"no {' and no '.join(missing)}: runs stay on this machine")]


def check_browser() -> list[Check]:
    """Chromium and its driver: the GUI's browser tests (``flylib gui`` needs any browser)."""
    driver = shutil.which("chromedriver")
    browser = next(
        (b for b in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if b),
        None,
    )
    if driver and browser:
        return [Check(OK, "chromium", f"{browser}, driver {driver}")]
    return [
        Check(
            NOTE,
            "chromium",
            "not found: the GUI's browser tests skip (`bash install.sh --test-system-packages` "
            "installs it); flylib gui works with any browser",
        )
    ]


def run_checks(config_files: Sequence[Path] = ()) -> list[Check]:
    """Every check, in the order printed. A check that itself fails is one FAIL line."""
    checks: list[Callable[[], list[Check]]] = [
        check_packages,
        check_torch,
        lambda: check_weights(config_files),
        check_caches,
        check_cluster,
        check_browser,
    ]
    lines: list[Check] = []
    for check in checks:
        try:
            lines += check()
        except Exception as exc:  # a broken install must still get its report
            name = getattr(check, "__name__", "check").replace("check_", "")
            lines.append(Check(FAIL, name, " ".join(f"{type(exc).__name__}: {exc}".split())))
    return lines


def format_report(lines: Sequence[Check]) -> str:
    """The report as printed: one aligned line per check, then the verdict."""
    width = max(len(c.what) for c in lines)
    body = [f"{c.status:<4}  {c.what:<{width}}  {c.detail}" for c in lines]
    failed = [c.what for c in lines if c.status == FAIL]
    verdict = (
        f"flylib doctor: {len(failed)} problem(s) block a run: {', '.join(failed)}"
        if failed
        else "flylib doctor: ready to run (notes above are not problems)"
    )
    return "\n".join([*body, verdict])
