"""Untracked = unused: a stage's artifact is bit-identical when every config key its
params do not hold changes at once.

A stage reads only its inputs object (:mod:`flylib.pipeline.inputs`), which a job
rebuilds from the params its rule tracks plus the untracked, speed-only runtime
(``tests/pipeline/test_inputs.py``). Here the other half: change every key of the config
that leaves the stage's params unchanged (where the config stays valid) and run the
stage again on the same upstream artifacts; every dataset must come out the same.
"""

from __future__ import annotations

import copy

import h5py
import numpy as np
import pytest

from flylib.config import Config
from flylib.errors import ConfigError
from flylib.pipeline.assemble import run_assemble
from flylib.pipeline.bundle_adjustment import run_bundle_adjustment
from flylib.pipeline.inputs import stage_inputs, stage_params
from flylib.pipeline.kinematics import run_kinematics
from flylib.pipeline.neuromechfly import run_neuromechfly
from flylib.pipeline.pose2d import run_pose2d
from flylib.pipeline.refinement import run_refinement
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


def _holder(data, path):
    """The mapping or list that holds the leaf at ``path`` (under its last key)."""
    for key in path[:-1]:
        data = data[key]
    return data


# -- artifacts: every untracked key changed at once ------------------------------------


def _perturb_untracked(data, stage):
    """``data`` with every leaf changed whose change leaves ``stage``'s params as they
    are (where the config stays valid), and how many leaves changed."""
    base = stage_params(Config.from_dict(data), stage)
    out, changed = copy.deepcopy(data), 0
    for leaf, value in list(_leaves(data)):
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
        # each candidate tried in place (Config.from_dict validates a deep copy of it, so no
        # trial needs a copy of its own) and put back unless it is kept
        holder, key = _holder(out, leaf), leaf[-1]
        kept = holder[key]
        for candidate in _candidates(value):
            holder[key] = candidate
            try:
                params = stage_params(Config.from_dict(out), stage)
            except ConfigError:
                continue
            if params != base:
                continue  # tracked: a change re-runs the stage
            kept, changed = candidate, changed + 1
            break
        holder[key] = kept
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
    from flylib.pipeline.demo import demo_import_spec, make_demo

    root = tmp_path_factory.mktemp("tracked")
    data = Config.default().data
    data["bundle_adjustment"]["max_nfev"] = 5
    config = Config.from_dict(data)
    rec, out = root / "rec", root / "base"
    make_demo(config, rec, frames=4, seed=0)
    spec = demo_import_spec(config)
    (out / "stages").mkdir(parents=True)
    p2d = run_pose2d(
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
    run_assemble(stage_inputs(config, "assemble"), files, out, recording_dir=rec)
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
    perturbed, changed = _perturb_untracked(data, stage)
    assert changed > 10
    # only the stage under test sees the changed config; its inputs are the base run's
    other, out = Config.from_dict(perturbed), tmp_path
    upstream = {k: base[k] for k in ("pose2d", "bundle_adjustment", "triangulation", "refinement")}
    run = {
        "pose2d": lambda: run_pose2d(
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
            run_assemble(stage_inputs(other, "assemble"), upstream, out, recording_dir=rec),
            out / "results.h5",
        )[1],
    }[stage]
    _same(base[stage], run())
