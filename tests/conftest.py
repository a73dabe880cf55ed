"""Shared fixtures: the location of ``../shared/data`` and helpers to skip without it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
# FLYLIB_SHARED_DATA: the sample data elsewhere than ../shared/data (e.g. from a worktree).
SHARED_DATA = Path(os.environ.get("FLYLIB_SHARED_DATA") or REPO_ROOT.parent / "shared" / "data")


def shared_subdir(name: str) -> Path:
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"{path} is absent: real-data tests need ../shared/data beside the repo")
    return path


@pytest.fixture(scope="session")
def df3d_sample_dir() -> Path:
    """``../shared/data/deepfly3d-sample`` (7 cameras, 960x480, 15 frames), or skip."""
    return shared_subdir("deepfly3d-sample")


@pytest.fixture(scope="session")
def deeperfly_example_dir() -> Path:
    """``../shared/data/deeperfly-example`` (7 cameras, 960x480, 64 frames), or skip."""
    return shared_subdir("deeperfly-example")


@pytest.fixture(scope="session")
def df3d_package_example_dir() -> Path:
    """``../shared/data/deepfly3d-package-example`` (DeepFly3D 1.x ``df3d_result.pkl``
    and ``calib.pkl``, 7 cameras, 15 frames), or skip."""
    return shared_subdir("deepfly3d-package-example")


@pytest.fixture(scope="session")
def df3d_pickle(df3d_sample_dir: Path) -> Path:
    """DeepFly3D's own 2D output for the sample recording, or skip."""
    path = df3d_sample_dir / "df3d_result_2d.pkl"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    return path


# Hypothesis profiles (tests/interop/test_fuzz_loaders.py): "flylib" by default keeps the fuzz tests
# under a minute in all; `pytest --hypothesis-profile=long` runs many more examples.
try:
    from hypothesis import HealthCheck, settings
except ImportError:  # hypothesis is in the `test` extra; the fuzz tests skip without it
    pass
else:
    _fuzz = {
        "deadline": None,
        "print_blob": True,
        "suppress_health_check": [HealthCheck.too_slow, HealthCheck.data_too_large],
    }
    # derandomized: the same examples every run, so CI is reproducible (libhdf5 itself can
    # loop forever on some damaged attribute headers, which random runs may reach)
    settings.register_profile("flylib", max_examples=80, derandomize=True, **_fuzz)
    settings.register_profile("long", max_examples=2000, **_fuzz)
    settings.load_profile("flylib")


def checkpoint_layout(path: Path) -> Path:
    """A file with the layout ``torch.save`` writes (a zip archive holding
    ``<name>/data.pkl``), for validation tests that need a checkpoint to exist but never
    load it (:func:`flylib.pose2d.published.container_problem`)."""
    import pickle
    import zipfile

    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr(f"{path.stem}/data.pkl", pickle.dumps({"state_dict": {}}, protocol=2))
    return path
