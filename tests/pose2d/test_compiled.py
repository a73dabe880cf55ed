"""The detector compiled ahead of time (AOTInductor) and its on-disk cache, on the CPU:
BatchNorm folding, the cache key, the ``compile: auto`` policy, compile / load / rebuild
of a damaged entry, and the compiled forward against eager."""

from __future__ import annotations

import dataclasses
import logging

import pytest
import torch

from flylib.config import Config
from flylib.pipeline.inputs import stage_inputs
from flylib.pose2d import compiled
from flylib.pose2d.inference import LoadedModel, load_models
from flylib.pose2d.model import Bottleneck, HourglassNet

# DeepFly2D's layout, narrow: the same module tree as sh8 at a tiny cost
TINY = dict(num_stacks=2, num_feats=8, inplanes=8, num_classes=19)
INPUT = (3, 64, 128)
BATCH = 4


def _inputs(data: dict):
    """The pose2d stage's inputs under the raw config ``data``."""
    return stage_inputs(Config.from_dict(data), "pose2d")


def _tiny_net(seed=0) -> HourglassNet:
    torch.manual_seed(seed)
    net = HourglassNet(**TINY)
    # non-trivial batch-norm statistics and affine parameters, so folding has work to do
    for module in net.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.5, 0.5)
            module.running_var.uniform_(0.3, 2.0)
            module.weight.data.uniform_(0.5, 1.5)
            module.bias.data.uniform_(-0.3, 0.3)
    return net.eval()


# --- BatchNorm folding -------------------------------------------------------------


def test_folded_network_gives_the_same_heatmaps_in_float64():
    net = _tiny_net().double()
    folded = compiled.fold_batchnorm(net)
    x = torch.randn(3, *INPUT, dtype=torch.float64)
    with torch.no_grad():
        want, got = net(x), folded(x)
    for a, b in zip(want, got):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-10)
    # what is left: one BatchNorm per bottleneck (its input is a residual sum), no other
    n_blocks = sum(isinstance(m, Bottleneck) for m in net.modules())
    left = sum(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert left == n_blocks
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules()) == 3 * n_blocks + 1 + 2
    # the original is untouched
    assert isinstance(net.bn1, torch.nn.BatchNorm2d)


def test_folding_in_float32_stays_within_float_rounding():
    net = _tiny_net(seed=3)
    x = torch.randn(2, *INPUT)
    with torch.no_grad():
        want, got = net.heatmaps(x), compiled.fold_batchnorm(net).heatmaps(x)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)


# --- the cache key -------------------------------------------------------------------


def test_every_part_of_the_key_names_another_entry():
    cpu = torch.device("cpu")
    net = _tiny_net()
    key = compiled.CompileKey.for_model(net, cpu, "float32", BATCH, INPUT)
    assert key == compiled.CompileKey.for_model(_tiny_net(), cpu, "float32", BATCH, INPUT)
    other_weights = compiled.CompileKey.for_model(_tiny_net(seed=1), cpu, "float32", BATCH, INPUT)
    variants = [
        other_weights,
        dataclasses.replace(key, torch_version="2.99.0"),
        dataclasses.replace(key, device="cuda:NVIDIA H100 80GB HBM3:sm90"),
        dataclasses.replace(key, precision="bfloat16"),
        dataclasses.replace(key, batch_size=BATCH * 2),
        dataclasses.replace(key, input_shape=(3, 128, 256)),
        dataclasses.replace(key, format=compiled.FORMAT + 1),
    ]
    digests = {key.digest()} | {v.digest() for v in variants}
    assert len(digests) == len(variants) + 1
    # one changed batch-norm statistic is other weights
    changed = _tiny_net()
    changed.bn1.running_mean[0] += 1e-3
    assert compiled.weights_digest(changed) != key.weights
    assert key.device.startswith("cpu:") and key.torch_version == torch.__version__


def test_default_cache_is_under_flylib_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path))
    key = compiled.CompileKey.for_model(_tiny_net(), torch.device("cpu"), "float32", 2, INPUT)
    package, meta = compiled.entry_paths(key)
    assert package.parent == tmp_path / "detector" and package.suffix == ".pt2"
    assert meta.with_suffix(".pt2") == package
    assert not compiled.is_cached(key)
    package.parent.mkdir()
    package.write_bytes(b"not a package")
    assert not compiled.is_cached(key)  # no key file: a partial entry
    meta.write_text(dataclasses.replace(key, batch_size=3).as_json())
    assert not compiled.is_cached(key)  # a key file of something else
    meta.write_text(key.as_json())
    assert compiled.is_cached(key)


# --- the policy -------------------------------------------------------------------


CUDA = torch.device("cuda")


def test_auto_compiles_only_when_it_beats_eager_on_its_cost_model():
    frames_900 = 900 * 8
    use, why = compiled.decide_compile("auto", CUDA, batch_size=16, images=frames_900, cached=False)
    assert not use and "eager" in why and "compile: true" in why  # a cold compile does not pay
    use, why = compiled.decide_compile("auto", CUDA, batch_size=16, images=frames_900, cached=True)
    assert use and "cached" in why
    use, _ = compiled.decide_compile("auto", CUDA, batch_size=16, images=100_000, cached=False)
    assert use  # a long recording pays for its own compilation
    use, _ = compiled.decide_compile("auto", CUDA, batch_size=16, images=80, cached=True)
    assert not use  # ten frames: loading the package costs more than they take eager
    for images in range(0, 200_000, 997):
        for cached in (False, True):
            use, _ = compiled.decide_compile(
                "auto", CUDA, batch_size=16, images=images, cached=cached
            )
            overhead = compiled.CACHED_LOAD_S if cached else compiled.COLD_COMPILE_S
            with_compile = overhead + images / compiled.COMPILED_IMAGES_PER_S
            assert use == (with_compile < images / compiled.EAGER_IMAGES_PER_S)


def test_explicit_settings_and_devices():
    cpu, mps = torch.device("cpu"), torch.device("mps")
    assert (
        compiled.decide_compile(False, CUDA, batch_size=64, images=10**7, cached=True)[0] is False
    )
    assert compiled.decide_compile(True, cpu, batch_size=1, images=1, cached=False)[0] is True
    assert (
        compiled.decide_compile("auto", cpu, batch_size=64, images=10**7, cached=True)[0] is False
    )
    assert compiled.decide_compile(True, mps, batch_size=64, images=10**7, cached=False)[0] is False
    assert (
        compiled.decide_compile("auto", CUDA, batch_size=4, images=10**7, cached=True)[0] is False
    )
    use, why = compiled.decide_compile("auto", CUDA, batch_size=16, images=None, cached=False)
    assert not use and "unknown" in why


# --- compile, load, rebuild (AOTInductor on the CPU) --------------------------------


@pytest.fixture(scope="module")
def cold(tmp_path_factory):
    """One cold compilation into a fresh cache (a minute or more on a busy CPU)."""
    root = tmp_path_factory.mktemp("compiled")
    net = _tiny_net(seed=5)
    key = compiled.CompileKey.for_model(net, torch.device("cpu"), "float32", BATCH, INPUT)
    forward, status = compiled.load_or_compile(net, key, torch.device("cpu"), root=root)
    return root, net, key, forward, status


@pytest.mark.slow
def test_cold_compile_matches_eager_and_leaves_one_complete_entry(cold):
    root, net, key, forward, status = cold
    assert status == "cold"
    assert sorted(p.name for p in root.iterdir()) == sorted(
        p.name for p in compiled.entry_paths(key, root)
    )  # no temporary file left behind
    assert compiled.is_cached(key, root)
    x = torch.randn(BATCH, *INPUT)
    with torch.inference_mode():
        torch.testing.assert_close(forward(x), net.heatmaps(x), rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_a_second_load_comes_from_the_cache(cold):
    root, net, key, _, _ = cold
    forward, status = compiled.load_or_compile(net, key, torch.device("cpu"), root=root)
    assert status == "cached"
    x = torch.randn(BATCH, *INPUT)
    with torch.inference_mode():
        torch.testing.assert_close(forward(x), net.heatmaps(x), rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_a_damaged_package_is_rebuilt_with_a_warning(cold, tmp_path, caplog, monkeypatch):
    root, net, key, _, _ = cold
    package, meta = compiled.entry_paths(key, tmp_path)
    package.write_bytes(b"PK\x03\x04 truncated by a crash")
    meta.write_text(key.as_json())
    good = compiled.entry_paths(key, root)[0].read_bytes()
    built = []

    def compile_package(net_, key_, device, path):  # the cold test covers a real compile
        built.append(path)
        with compiled.atomic_path(path) as tmp:
            tmp.write_bytes(good)

    monkeypatch.setattr(compiled, "compile_package", compile_package)
    with caplog.at_level(logging.WARNING, logger="flylib.pose2d.compiled"):
        forward, status = compiled.load_or_compile(net, key, torch.device("cpu"), root=tmp_path)
    assert status == "rebuilt"
    assert any(str(package) in r.getMessage() and "again" in r.getMessage() for r in caplog.records)
    x = torch.randn(BATCH, *INPUT)
    with torch.inference_mode():
        torch.testing.assert_close(forward(x), net.heatmaps(x), rtol=1e-4, atol=1e-4)
    assert compiled.is_cached(key, tmp_path) and built == [package]
    # a package without its key file (a crash between the two writes) is rebuilt too
    meta.unlink()
    assert compiled.load_or_compile(net, key, torch.device("cpu"), root=tmp_path)[1] == "rebuilt"
    assert len(built) == 2


@pytest.mark.slow
def test_load_models_uses_the_cached_package_and_pads_a_short_batch(cold, tmp_path, caplog):
    import copy

    from flylib.config import Config
    from flylib.pose2d import weights

    root, net, key, _, _ = cold
    checkpoint = weights.save_checkpoint(net, tmp_path / "sh2.tar")
    data = copy.deepcopy(dict(Config.default().data))
    data["pose2d"]["models"][0].update(weights=str(checkpoint), input_size=list(INPUT[1:]))
    data["pose2d"].update(batch_size=BATCH, device="cpu", compile=True)
    plan = _inputs(data).detection_plan()
    with caplog.at_level(logging.INFO, logger="flylib.pose2d.inference"):
        models = load_models(plan, _inputs(data).detector_params(), frames=6, cache_root=root)
    model = next(iter(models.values()))
    assert isinstance(model, LoadedModel) and model.compiled
    assert model.compile_status == "cached" and model.compile_key() == key
    assert any("pose2d.compile is true" in r.getMessage() for r in caplog.records)
    x = torch.randn(BATCH + 2, *INPUT)  # one full batch and one padded to BATCH
    with torch.inference_mode():
        torch.testing.assert_close(model.heatmaps(x), net.heatmaps(x), rtol=1e-4, atol=1e-4)
    # auto on the CPU stays eager, and says so
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="flylib.pose2d.inference"):
        eager = load_models(
            plan,
            dataclasses.replace(_inputs(data).detector_params(), compile="auto"),
            frames=10**6,
            cache_root=root,
        )
    assert not next(iter(eager.values())).compiled
    assert any("auto: eager on cpu" in r.getMessage() for r in caplog.records)


def test_the_policy_sees_the_recordings_frame_count(tmp_path):
    import copy

    import numpy as np

    from flylib import io
    from flylib.config import Config
    from flylib.pose2d.stream import frame_count

    data = copy.deepcopy(dict(Config.default().data))
    plan = _inputs(data).detection_plan()
    first = plan.active_sources()[0]
    video = tmp_path / "camera_0.mp4"
    with io.VideoWriter(video, fps=100) as writer:
        for t in range(7):
            writer.write_frame(np.full((48, 64, 3), 10 * t, np.uint8))
    assert frame_count(plan, {first: [video]}) == 7
    assert frame_count(plan, {}) is None  # the detection itself names missing footage
    assert frame_count(plan, {first: [tmp_path / "nothing.mp4"]}) is None


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


@needs_cuda
@pytest.mark.slow
@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_on_a_gpu_the_graphed_package_matches_eager_autocast(tmp_path, precision):
    import copy

    from flylib.config import Config

    data = copy.deepcopy(dict(Config.default().data))
    data["pose2d"]["models"][0].update(input_size=list(INPUT[1:]))
    spec = _inputs(data).detection_plan().models["deepfly2d"]
    cuda = torch.device("cuda")
    eager = LoadedModel(spec, _tiny_net(seed=7), cuda, precision=precision, batch_size=BATCH)
    model = LoadedModel(
        spec,
        _tiny_net(seed=7),
        cuda,
        precision=precision,
        batch_size=BATCH,
        compiled=True,
        cache_root=tmp_path / "cache",
    )
    assert model.compile_status == "cold"
    assert isinstance(model._forward, compiled.CudaGraphForward)
    x = torch.randn(BATCH + 1, *INPUT, device=cuda)
    tol = 1e-3 if precision == "float32" else 5e-2
    for _ in range(2):  # replays reuse the graph's buffers: results must not alias
        torch.testing.assert_close(model.heatmaps(x), eager.heatmaps(x), rtol=tol, atol=tol)
