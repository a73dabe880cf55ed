"""envs/flylib.yaml: the workflow's conda environment cannot drift from pyproject.toml."""

from __future__ import annotations

import tomllib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import yaml
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.utils import canonicalize_name
from packaging.version import Version

REPO = Path(__file__).resolve().parents[2]


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def _env() -> tuple[list, list[str]]:
    spec = yaml.safe_load((REPO / "envs" / "flylib.yaml").read_text())
    deps = spec["dependencies"]
    pip = next(d["pip"] for d in deps if isinstance(d, dict))
    return [d for d in deps if isinstance(d, str)], pip


def _pins() -> dict[str, Requirement]:
    _, pip = _env()
    reqs = [Requirement(line) for line in pip if not line.startswith("-")]
    return {canonicalize_name(r.name): r for r in reqs}


def test_env_pins_exactly_pyprojects_dependencies():
    wanted = {canonicalize_name(Requirement(d).name) for d in _pyproject()["dependencies"]}
    assert set(_pins()) == wanted


def test_every_pin_is_exact_and_within_pyprojects_range():
    ranges = {
        canonicalize_name(r.name): r.specifier
        for r in map(Requirement, _pyproject()["dependencies"])
    }
    for name, req in _pins().items():
        (spec,) = req.specifier
        assert spec.operator == "==", f"{name}: {req} is not pinned"
        assert Version(spec.version) in ranges[name], (
            f"{name}: {req} outside pyproject's {ranges[name]}"
        )


def test_pins_are_the_versions_the_tests_run_with():
    for name, req in _pins().items():
        try:
            installed = Version(version(name)).public  # torch's "+cpu" is a build, not a version
        except PackageNotFoundError:
            continue
        assert req.specifier == SpecifierSet(f"=={installed}"), (
            f"envs/flylib.yaml pins {req}, the tests run with {name}=={installed}"
        )


def test_env_installs_flylib_from_the_checkout_and_a_python_pyproject_allows():
    conda, pip = _env()
    assert "-e ${FLYLIB_CHECKOUT}" in pip
    python = next(d for d in conda if d.startswith("python="))
    assert Version(python.split("=", 1)[1]) in SpecifierSet(_pyproject()["requires-python"])
    assert "FLYLIB_CHECKOUT" in (REPO / "workflow" / "rules" / "common.smk").read_text()
    assert not (REPO / "scripts" / "_bootstrap.py").exists()
