"""Tracked = read: a stage reads only config its rule tracks (flylib.pipeline.tracked).

Two halves: every path a stage may read is tracked (changing it changes the stage's
params, so Snakemake re-runs the stage), and a stage's artifact is bit-identical
when every config key it may not read changes at once.
"""

from __future__ import annotations

import copy

import h5py
import numpy as np
import pytest

from flylib.config import PARAM_STAGES, Config
from flylib.errors import ConfigError
from flylib.pipeline import stages
from flylib.pipeline.bundle_adjustment import run_bundle_adjustment
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.kinematics import run_kinematics
from flylib.pipeline.neuromechfly import run_neuromechfly
from flylib.pipeline.refinement import run_refinement
from flylib.pipeline.tracked import (
    UNTRACKED,
    StageConfig,
    UntrackedConfigRead,
    stage_reads,
    upstream_reads,
)
from flylib.pipeline.triangulation import run_triangulation

_CHOICES = (
    "dlt",
    "greedy",
    "ransac",
    "soft_l1",
    "huber",
    "cauchy",
    "linear",
    "even",
    "confidence",
    "coverage",
    "lm",
    "scipy",
    "float16",
    "bfloat16",
    "missing",
    "error",
    "free",
    "fixed",
    "white",
    "gray",
)


def _candidates(value):
    """Other values for a leaf, most likely valid first."""
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, int):
        return [value + 1, value - 1, value + 3]
    if isinstance(value, float):
        return [value * 2 + 1, value / 2]
    if isinstance(value, str):
        return [c for c in _CHOICES if c != value] + [value + "_x", "#123456"]
    if isinstance(value, list):
        return [value[:-1], value + value[-1:]] if value else [[1], ["x"]]
    if value is None:
        return [1, 2.5, True, "x", ["x"]]
    return []


def _leaves(data, prefix=()):
    """``(path tuple, value)`` of every leaf (lists are leaves) of a config mapping."""
    items = enumerate(data) if isinstance(data, list) else data.items()
    for key, value in items:
        if (isinstance(value, dict) and value) or (
            isinstance(value, list) and value and all(isinstance(v, dict) for v in value)
        ):
            yield from _leaves(value, (*prefix, key))
        else:
            yield (*prefix, key), value


def _set(data, path, value):
    out = copy.deepcopy(data)
    node = out
    for key in path[:-1]:
        node = node[key] if isinstance(node, list) else node.setdefault(key, {})
    node[path[-1]] = value
    return out


def _under(path: tuple, declared: str) -> bool:
    parts = tuple(declared.partition(":")[0].split("."))
    return path[: len(parts)] == parts


def _params(data, stage):
    """``stage``'s params of ``data``, without validating the whole config (a change to
    one key need not make a consistent config to show whether the params carry it)."""
    config = object.__new__(Config)
    config.data, config.text, config.source, config.format = data, None, None, "yaml"
    try:
        return config.stage_params(stage)
    except (ConfigError, ValueError, TypeError, KeyError, AttributeError):
        return None


def _variants():
    """``(name, data)``: the default config, with bundle adjustment on and off."""
    data = Config.default().data
    off = copy.deepcopy(data)
    off["pipeline"]["do_bundle_adjustment"] = False
    return [("ba_on", data), ("ba_off", off)]


def _renamed_keys(data, path):
    """The config with the mapping at ``path`` holding one key renamed."""
    node = data
    for key in path:
        node = node[key]
    first = next(k for k in node if k != "defaults")
    renamed = {("renamed" if k == first else k): v for k, v in node.items()}
    return _set(data, path, renamed)


@pytest.mark.parametrize("variant", ["ba_on", "ba_off"])
@pytest.mark.parametrize("stage", PARAM_STAGES)
@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_every_path_a_stage_reads_is_tracked(stage, variant):
    data = dict(_variants())[variant]
    config = Config.from_dict(data)
    upstream = upstream_reads(stage)
    untracked_why = UNTRACKED.get(stage, {})
    for declared in stage_reads(config, stage):
        if declared in untracked_why:
            continue
        owner = upstream.get(declared, stage)
        base = config.stage_params(owner)
        path = tuple(declared.partition(":")[0].split("."))
        if declared.endswith(":names"):
            try:
                changed = _params(_renamed_keys(data, path), owner)
            except (KeyError, StopIteration):
                continue  # not in this config (e.g. no output_points)
            assert changed != base, f"{stage}: renaming a key of {declared} leaves {owner}'s params"
            continue
        leaves = [(p, v) for p, v in _leaves(data) if _under(p, declared)] or [(path, None)]
        for leaf, value in leaves:
            if any(_under(leaf, u) for u in untracked_why):
                continue
            results = [_params(_set(data, leaf, c), owner) for c in _candidates(value)]
            results = [r for r in results if r is not None]
            assert results, f"{stage}: no valid change of {'.'.join(leaf)} to try"
            assert any(r != base for r in results), (
                f"{stage} reads {'.'.join(leaf)} (declared {declared}) but {owner}'s params do not track it"
            )


def test_a_stage_cannot_read_an_untracked_key():
    view = StageConfig.for_stage(Config.default(), "triangulation")
    with pytest.raises(UntrackedConfigRead, match=r"'triangulation' read config key 'refinement'"):
        view.data.get("refinement")
    assert view.triangulation.method == "ransac"
    with pytest.raises(
        UntrackedConfigRead, match="max_drops"
    ):  # greedy's knob, untracked under ransac
        view.data["triangulation"]["max_drops"]
    assert view.triangulation.ransac_threshold == Config.default().triangulation.ransac_threshold
    with pytest.raises(UntrackedConfigRead):
        StageConfig.for_stage(view, "assemble")


# -- artifacts: every untracked key changed at once ------------------------------------


def _perturb_untracked(data, config, stage):
    """``data`` with every leaf ``stage`` may not read changed (where the config stays
    valid), and how many leaves changed."""
    declared = stage_reads(config, stage)
    out, changed = copy.deepcopy(data), 0
    for leaf, value in list(_leaves(data)):
        if any(_under(leaf, d) for d in declared if not d.endswith(":names")):
            continue
        if leaf[0] in (
            "recordings",
            "outdir",
            "recursive",
            "demo",
            "exports",
            "nwb",
            "corrections",
        ):
            continue  # which recordings and extra outputs: not an input of a stage function
        if leaf[0] == "pipeline":
            continue  # the stage flags shape the DAG (which artifacts a stage is given)
        if leaf[0] == "cameras" and any(d.startswith("cameras:names") for d in declared):
            continue  # the camera names are tracked; their geometry is checked below
        for candidate in _candidates(value):
            trial = _set(out, leaf, candidate)
            try:
                Config.from_dict(trial)
            except ConfigError:
                continue
            out, changed = trial, changed + 1
            break
    return out, changed


def _datasets(path):
    out = {}
    with h5py.File(path) as f:
        f.visititems(
            lambda name, obj: (
                out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None
            )
        )
    return out


def _same(a, b):
    da, db = _datasets(a), _datasets(b)
    assert da.keys() == db.keys()
    for name in da:
        x, y = np.asarray(da[name]), np.asarray(db[name])
        same = (
            np.array_equal(x, y, equal_nan=True) if x.dtype.kind in "fc" else np.array_equal(x, y)
        )
        assert same, f"{a.name}: {name} differs"


@pytest.fixture(scope="module")
def base_run(tmp_path_factory):
    """A tiny demo recording and every stage's artifact from the default config."""
    from flylib.demo import demo_import_spec
    from flylib.pipeline.demo import make_demo

    root = tmp_path_factory.mktemp("tracked")
    data = Config.default().data
    data["bundle_adjustment"]["max_nfev"] = 5
    config = Config.from_dict(data)
    rec, out = root / "rec", root / "base"
    make_demo(config, rec, frames=4, seed=0)
    spec = demo_import_spec(config)
    (out / "stages").mkdir(parents=True)
    p2d = stages.run_pose2d(
        stage_inputs(config, "pose2d"), rec, out / "stages" / "pose2d.h5", import_spec=spec
    )
    ba = run_bundle_adjustment(
        stage_inputs(config, "bundle_adjustment"),
        p2d,
        out / "stages" / "bundle_adjustment.h5",
        recording_dir=rec,
    )
    tri = run_triangulation(
        stage_inputs(config, "triangulation"),
        p2d,
        out / "stages" / "triangulation.h5",
        ba_path=ba,
        recording_dir=rec,
    )
    ref = run_refinement(
        stage_inputs(config, "refinement"),
        p2d,
        tri,
        out / "stages" / "refinement.h5",
        ba_path=ba,
        recording_dir=rec,
    )
    files = {"pose2d": p2d, "bundle_adjustment": ba, "triangulation": tri, "refinement": ref}
    stages.run_assemble(stage_inputs(config, "assemble"), files, out, recording_dir=rec)
    run_kinematics(stage_inputs(config, "kinematics"), out / "results.h5", out)
    run_neuromechfly(stage_inputs(config, "neuromechfly"), out / "results.h5", out)
    artifacts = {
        **files,
        "assemble": out / "results.h5",
        "kinematics": out / "kinematics.h5",
        "neuromechfly": out / "neuromechfly.h5",
    }
    return data, rec, spec, artifacts


@pytest.mark.slow
@pytest.mark.parametrize(
    "stage",
    ["pose2d", "bundle_adjustment", "triangulation", "assemble"],
)
def test_artifact_is_bit_identical_when_every_untracked_key_changes(base_run, stage, tmp_path):
    data, rec, spec, base = base_run
    perturbed, changed = _perturb_untracked(data, Config.from_dict(data), stage)
    assert changed > 10
    # only the stage under test sees the changed config; its inputs are the base run's
    other, out = Config.from_dict(perturbed), tmp_path
    upstream = {k: base[k] for k in ("pose2d", "bundle_adjustment", "triangulation", "refinement")}
    run = {
        "pose2d": lambda: stages.run_pose2d(
            stage_inputs(other, "pose2d"), rec, out / "pose2d.h5", import_spec=spec
        ),
        "bundle_adjustment": lambda: run_bundle_adjustment(
            stage_inputs(other, "bundle_adjustment"),
            base["pose2d"],
            out / "ba.h5",
            recording_dir=rec,
        ),
        "triangulation": lambda: run_triangulation(
            stage_inputs(other, "triangulation"),
            base["pose2d"],
            out / "tri.h5",
            ba_path=base["bundle_adjustment"],
            recording_dir=rec,
        ),
        "assemble": lambda: (
            stages.run_assemble(stage_inputs(other, "assemble"), upstream, out, recording_dir=rec),
            out / "results.h5",
        )[1],
    }[stage]
    _same(base[stage], run())
