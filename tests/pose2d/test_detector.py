"""The hourglass network, checkpoints and weights, and streaming detection."""

from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from flylib import io
from flylib.config import Config
from flylib.errors import FootageError, WeightsError
from flylib.pipeline.inputs import stage_inputs
from flylib.pose2d import (
    HourglassNet,
    decode,
    detect_2d,
    load_detector,
    load_models,
    stream,
    weights,
)
from flylib.pose2d.plan import FlipLR

TINY = dict(num_stacks=2, num_feats=8, inplanes=8)


def _inputs(data: dict):
    """The pose2d stage's inputs under the raw config ``data``."""
    return stage_inputs(Config.from_dict(data), "pose2d")


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny CPU forwards: torch's thread pool only adds spin-wait on a busy 2-core CI box."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _tiny_net(seed=0, **overrides) -> HourglassNet:
    torch.manual_seed(seed)
    net = HourglassNet(**{**TINY, **overrides})
    # non-trivial batch-norm statistics, so a load that skipped them would show
    for module in net.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.2, 0.2)
            module.running_var.uniform_(0.5, 1.5)
    return net.eval()


# --- the network --------------------------------------------------------------


def test_sh8_parameter_names_and_shapes_match_the_published_layout():
    sd = HourglassNet(num_stacks=8, num_classes=19).state_dict()
    shapes = {k: tuple(v.shape) for k, v in sd.items()}
    assert shapes["conv1.weight"] == (64, 3, 7, 7)
    assert shapes["layer1.0.conv1.weight"] == (64, 64, 1, 1)
    assert shapes["layer1.0.conv3.weight"] == (128, 64, 1, 1)
    assert shapes["layer1.0.downsample.0.weight"] == (128, 64, 1, 1)
    # DeepFly2D's layer2 gets the running width: 128 planes, 128 -> 256, projected skip
    assert shapes["layer2.0.conv1.weight"] == (128, 128, 1, 1)
    assert shapes["layer2.0.conv3.weight"] == (256, 128, 1, 1)
    assert shapes["layer2.0.downsample.0.weight"] == (256, 128, 1, 1)
    assert shapes["layer3.0.conv1.weight"] == (128, 256, 1, 1)
    assert "layer3.0.downsample.0.weight" not in shapes  # 256 -> 256: identity skip
    # depth-4 hourglass: levels 0..3, three branches each plus the bottom at level 0
    assert shapes["hg.7.hg.0.3.0.conv2.weight"] == (128, 128, 3, 3)
    assert "hg.0.hg.1.3.0.conv1.weight" not in shapes and "hg.0.hg.4.0.0.conv1.weight" not in shapes
    assert shapes["hg.0.hg.3.2.0.bn1.running_var"] == (256,)
    assert shapes["res.7.0.conv3.weight"] == (256, 128, 1, 1)
    assert shapes["fc.7.0.weight"] == (256, 256, 1, 1) and shapes["fc.7.1.weight"] == (256,)
    assert shapes["score.7.weight"] == (19, 256, 1, 1)
    assert shapes["fc_.6.weight"] == (256, 256, 1, 1) and shapes["score_.6.weight"] == (
        256,
        19,
        1,
        1,
    )
    assert "fc_.7.weight" not in shapes and "score_.7.weight" not in shapes
    assert len(sd) == 2526  # the released file's entry count
    n_values = sum(v.numel() for k, v in sd.items() if not k.endswith("num_batches_tracked"))
    assert n_values == 25_727_256  # parameters + batch-norm running statistics
    n_params = sum(p.numel() for p in HourglassNet(num_stacks=8, num_classes=19).parameters())
    assert n_params == 25_606_168  # pytorch-pose hg8 with 19 outputs (~25.6 M)


def test_forward_gives_every_stack_at_quarter_resolution():
    net = _tiny_net(num_classes=5)
    with torch.inference_mode():
        out = net(torch.randn(2, 3, 64, 128))
    assert len(out) == 2 and all(o.shape == (2, 5, 16, 32) for o in out)
    assert not torch.equal(out[0], out[1])
    torch.testing.assert_close(
        net.heatmaps(torch.zeros(1, 3, 64, 64)), net(torch.zeros(1, 3, 64, 64))[-1]
    )


# --- checkpoints ----------------------------------------------------------------


@pytest.mark.parametrize("prefix", ["module.", "model.", ""])
def test_checkpoint_roundtrip_gives_identical_heatmaps(tmp_path, prefix):
    net = _tiny_net(seed=3)
    path = weights.save_checkpoint(net, tmp_path / "sh2.tar", prefix=prefix)
    raw = torch.load(path, weights_only=True)
    assert set(raw) == {"state_dict"} and all(k.startswith(prefix) for k in raw["state_dict"])
    loaded = load_detector(path, num_classes=19)
    assert loaded.num_stacks == 2 and loaded.config["num_feats"] == 8
    x = torch.randn(2, 3, 64, 128)
    with torch.inference_mode():
        assert torch.equal(net(x)[-1], loaded(x)[-1])


def test_bad_checkpoints_are_clear_weights_errors(tmp_path):
    net = _tiny_net()
    good = weights.save_checkpoint(net, tmp_path / "good.tar")
    with pytest.raises(
        WeightsError, match="outputs 19 channels but the model's n_out_channels is 7"
    ):
        weights.load_hourglass(good, num_classes=7)
    with pytest.raises(WeightsError, match="has 2 stacks, expected 8"):
        weights.load_hourglass(good, num_stacks=8)
    state = {k: v.clone() for k, v in net.state_dict().items()}
    state["res.1.0.conv2.weight"] = torch.zeros(8, 8, 1, 1)
    torch.save({"state_dict": state}, tmp_path / "shape.tar")
    with pytest.raises(
        WeightsError, match=r"shape\.tar: the checkpoint does not fit.*res\.1\.0\.conv2\.weight"
    ):
        weights.load_hourglass(tmp_path / "shape.tar")
    del state["res.1.0.conv2.weight"]
    torch.save({"state_dict": state}, tmp_path / "missing.tar")
    with pytest.raises(WeightsError, match="does not fit"):
        weights.load_hourglass(tmp_path / "missing.tar")
    torch.save({"state_dict": {"encoder.weight": torch.zeros(3)}}, tmp_path / "other.tar")
    with pytest.raises(WeightsError, match="not a stacked-hourglass checkpoint"):
        weights.load_hourglass(tmp_path / "other.tar")
    (tmp_path / "junk.tar").write_bytes(b"junk")
    with pytest.raises(WeightsError, match="cannot read the checkpoint"):
        weights.load_hourglass(tmp_path / "junk.tar")


def test_weights_resolution_cache_download_and_offline(tmp_path, monkeypatch):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    assert (
        weights.cached_checkpoint("deepfly2d", "hourglass")
        == tmp_path / "cache" / "sh8_deepfly.tar"
    )
    with pytest.raises(WeightsError, match="does not exist"):
        weights.resolve_weights(tmp_path / "nope.tar")
    published = weights.save_checkpoint(_tiny_net(), tmp_path / "published.tar")
    digest = weights.sha256sum(published)
    with pytest.raises(WeightsError, match="downloading is off"):
        weights.resolve_weights("", allow_download=False)
    # offline: one clear error that says where to put the file
    with pytest.raises(WeightsError, match=r"put it at .*cache/sh8_deepfly\.tar"):
        weights.resolve_weights("", url="http://127.0.0.1:9/sh8.tar")
    with pytest.raises(WeightsError, match="checksum mismatch"):
        weights.resolve_weights("", url=published.as_uri(), sha256="0" * 64)
    assert not (tmp_path / "cache" / "sh8_deepfly.tar").exists()
    assert list((tmp_path / "cache").iterdir()) == []  # no partial file left behind
    got = weights.resolve_weights("", url=published.as_uri(), sha256=digest)
    assert got == tmp_path / "cache" / "sh8_deepfly.tar" and weights.sha256sum(got) == digest
    # now cached: no network needed
    assert weights.resolve_weights("", url="http://127.0.0.1:9/sh8.tar") == got


# --- detection ------------------------------------------------------------------


@pytest.fixture(scope="module")
def default_data():
    from flylib.config import Config

    return copy.deepcopy(dict(Config.default().data))


def _config(default_data, checkpoint: Path, *, input_size=(64, 128), batch_size=4):
    data = copy.deepcopy(default_data)
    model = data["pose2d"]["models"][0]
    model.update(weights=str(checkpoint), input_size=list(input_size))
    data["pose2d"].update(batch_size=batch_size, decode_buffer=2, device="cpu")
    return data


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    return weights.save_checkpoint(
        _tiny_net(seed=11, num_stacks=1), tmp_path_factory.mktemp("w") / "sh1.tar"
    )


def _sources(root: Path, data, kind: str) -> dict[str, list[Path]]:
    out = {}
    for s in data["sources"]:
        if kind == "video":
            out[s["name"]] = [root / s["filename"]]
        else:
            out[s["name"]] = io.list_image_files(root / s["filename"].replace(".mp4", "_img_*.jpg"))
    return out


@pytest.mark.parametrize("kind", ["video", "images"])
def test_detect_2d_on_the_deepfly3d_sample(df3d_sample_dir, default_data, tiny_checkpoint, kind):
    data = _config(default_data, tiny_checkpoint)
    plan = _inputs(data).detection_plan()
    models = load_models(plan, _inputs(data).detector_params())
    pts, conf, cands = detect_2d(
        _inputs(data).detector_params(), plan, models, sources=_sources(df3d_sample_dir, data, kind)
    )
    assert pts.shape == (7, 15, 38, 2) and conf.shape == (7, 15, 38) and cands is None
    filled = plan.filled_mask()
    assert np.array_equal(np.isnan(conf), np.broadcast_to(~filled[:, None, :], conf.shape))
    assert np.array_equal(np.isnan(pts).any(-1), np.isnan(conf))
    assert np.array_equal(np.isnan(pts).all(-1), np.isnan(conf))
    xs, ys = (
        pts[..., 0][filled[:, None, :].repeat(15, 1)],
        pts[..., 1][filled[:, None, :].repeat(15, 1)],
    )
    # DeepFly2D's convention: normalized [0, 1] times the frame size
    assert xs.min() >= 0 and xs.max() <= 960 and ys.min() >= 0 and ys.max() <= 480


def test_mirrored_pathway_lands_in_the_raw_frame(
    df3d_sample_dir, default_data, tiny_checkpoint, tmp_path
):
    """Detecting on camera_4 through the flip preprocessor equals detecting, without
    one, on a mirrored copy of the footage and mirroring the points back
    (x -> W - x: DeepFly2D's normalized x -> 1 - x)."""
    frames = io.open_reader(df3d_sample_dir / "camera_4.mp4")[:6]
    import cv2

    for i, frame in enumerate(frames):  # lossless copies: the two runs see the same pixels
        cv2.imwrite(str(tmp_path / f"raw_{i}.png"), frame[..., ::-1])
        cv2.imwrite(str(tmp_path / f"mirror_{i}.png"), frame[:, ::-1, ::-1])
    data = _config(default_data, tiny_checkpoint)
    data["pose2d"]["pathways"] = [
        {"name": "lf_flip", "source": "vid_lf", "preprocessor": "flip", "model": "deepfly2d"},
        {"name": "lf_plain", "source": "vid_lm", "model": "deepfly2d"},
    ]
    points = data["skeleton"]["point_names"][:19]
    data["pose2d"]["output_points"] = {
        "lf": {p: {"pathway": "lf_flip", "out_channel": c} for c, p in enumerate(points)},
        "lm": {p: {"pathway": "lf_plain", "out_channel": c} for c, p in enumerate(points)},
    }
    plan = _inputs(data).detection_plan()
    sources = {
        "vid_lf": io.list_image_files(tmp_path / "raw_*.png"),
        "vid_lm": io.list_image_files(tmp_path / "mirror_*.png"),
    }
    pts, conf, _ = detect_2d(
        _inputs(data).detector_params(),
        plan,
        load_models(plan, _inputs(data).detector_params()),
        sources=sources,
    )
    lf, lm = plan.view_names.index("lf"), plan.view_names.index("lm")
    via_flip, on_mirror = pts[lf, :, :19], pts[lm, :, :19]
    np.testing.assert_allclose(via_flip[..., 0], 960.0 - on_mirror[..., 0], atol=1e-3)
    np.testing.assert_allclose(via_flip[..., 1], on_mirror[..., 1], atol=1e-3)
    np.testing.assert_allclose(conf[lf, :, :19], conf[lm, :, :19], rtol=1e-5)
    assert FlipLR() in plan.pathways[0].ops


def test_candidates_agree_with_the_argmax_and_pictorial(default_data, tiny_checkpoint, tmp_path):
    from flylib.pictorial import Candidates, peak_candidates

    rng = np.random.default_rng(1)
    frames = rng.integers(0, 255, size=(5, 96, 160, 3), dtype=np.uint8)
    with io.VideoWriter(tmp_path / "cam.mp4", fps=10) as writer:
        writer.write_frames(frames)
    data = _config(default_data, tiny_checkpoint, batch_size=2)
    plan = _inputs(data).detection_plan()
    sources = {s: [tmp_path / "cam.mp4"] for s in plan.sources}
    pts, conf, cands = detect_2d(
        _inputs(data).detector_params(),
        plan,
        load_models(plan, _inputs(data).detector_params()),
        sources=sources,
        want_candidates=True,
        k=3,
    )
    assert isinstance(cands, Candidates) and cands.xy.shape == (7, 5, 38, 3, 2)
    seen = conf > 0.05  # pictorial's peak threshold
    assert seen.sum() > 100
    # the strongest local maximum is the global maximum: candidate 0 is the arg-max
    np.testing.assert_allclose(cands.xy[..., 0, :][seen], pts[seen], atol=1e-6)
    np.testing.assert_allclose(cands.score[..., 0][seen], conf[seen], rtol=1e-6)
    unseen = np.isnan(conf)
    assert np.all(cands.score[unseen] == 0) and np.isnan(cands.xy[unseen]).all()
    # the on-device peak finder matches pictorial's NumPy one on Gaussian blobs, for
    # each refinement both implement (weighted: the detector's default)
    hm = np.stack(
        [
            0.9 * decode.gaussian_heatmap((16, 32), (5.3, 4.6), 1.4)
            + 0.6 * decode.gaussian_heatmap((16, 32), (21.8, 10.2), 1.4),
            0.7 * decode.gaussian_heatmap((16, 32), (12.4, 7.7), 1.1) - 0.2,  # negatives: clipped
        ]
    )
    for method in ("weighted", "taylor", "argmax"):
        ours_xy, ours_score = decode.topk_peaks(
            torch.from_numpy(hm)[None], k=3, radius=2, threshold=0.05, method=method
        )
        ref_xy, ref_score = peak_candidates(hm, k=3, radius=2, threshold=0.05, method=method)
        np.testing.assert_allclose(ours_xy[0].numpy(), ref_xy, atol=1e-6, err_msg=method)
        np.testing.assert_allclose(np.nan_to_num(ours_score[0].numpy()), ref_score, atol=1e-12)


def test_detect_recording_returns_pose2d_data_and_never_runs_untrained(
    default_data, tiny_checkpoint, tmp_path, monkeypatch
):
    from flylib.pose2d import detect_recording
    from flylib.results import Pose2dData

    with io.VideoWriter(tmp_path / "cam.mp4", fps=10) as writer:
        writer.write_frames(np.full((3, 64, 96, 3), 90, np.uint8))
    data = _config(default_data, tiny_checkpoint)
    sources = {s["name"]: [tmp_path / "cam.mp4"] for s in data["sources"]}
    result = detect_recording(
        _inputs(data).detection_plan(), sources, _inputs(data).detector_params(), progress=False
    )
    assert isinstance(result, Pose2dData)
    assert result.view_names == ["rh", "rm", "rf", "f", "lf", "lm", "lh"]
    assert result.image_sizes == {v: (64, 96) for v in result.view_names}
    assert result.pts2d.shape == (7, 3, 38, 2)
    # no weights anywhere and no network: a WeightsError, not an untrained network
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "empty-cache"))
    data["pose2d"]["models"][0].update(weights="", url="http://127.0.0.1:9/sh8.tar")
    with pytest.raises(WeightsError, match="put it at"):
        detect_recording(
            _inputs(data).detection_plan(), sources, _inputs(data).detector_params(), progress=False
        )


def test_sources_of_different_length_are_a_footage_error(default_data, tiny_checkpoint, tmp_path):
    for name, n in (("long", 6), ("short", 4)):
        with io.VideoWriter(tmp_path / f"{name}.mp4", fps=10) as writer:
            writer.write_frames(np.zeros((n, 64, 64, 3), np.uint8))
    data = _config(default_data, tiny_checkpoint, batch_size=4)
    plan = _inputs(data).detection_plan()
    sources = {s: [tmp_path / ("short.mp4" if s == "vid_lh" else "long.mp4")] for s in plan.sources}
    with pytest.raises(FootageError, match=r"sources differ in length"):
        detect_2d(
            _inputs(data).detector_params(),
            plan,
            load_models(plan, _inputs(data).detector_params()),
            sources=sources,
        )
    with pytest.raises(FootageError, match="no footage for source"):
        detect_2d(
            _inputs(data).detector_params(),
            plan,
            load_models(plan, _inputs(data).detector_params()),
            sources={"vid_rh": [tmp_path / "long.mp4"]},
        )


def test_prefetch_queue_stays_bounded(tmp_path):
    files = []
    import cv2

    for i in range(40):
        files.append(tmp_path / f"f{i}.png")
        cv2.imwrite(str(files[-1]), np.full((8, 8, 3), i, np.uint8))
    prefetcher = stream.BlockPrefetcher("s", files, block_size=3, depth=2, workers=1, threaded=True)
    prefetcher.start()
    time.sleep(0.3)  # a slow consumer: the decoder must stop at the queue bound
    assert prefetcher.blocks.qsize() <= 2 and prefetcher.is_alive()
    blocks = []
    while (block := prefetcher.get()) is not stream.END_OF_STREAM:
        blocks.append(block)
    prefetcher.join(timeout=5)
    values = torch.cat(blocks)[:, 0, 0, 0].tolist()
    assert values == list(range(40)) and max(len(b) for b in blocks) == 3


def test_gpu_side_yuv_conversion_matches_the_decoder(df3d_sample_dir, tmp_path):
    from flylib.pose2d.inference import yuv420p_to_rgb

    rng = np.random.default_rng(5)
    smooth = (
        torch.nn.functional.interpolate(
            torch.from_numpy(rng.uniform(20, 235, size=(4, 3, 6, 8))),
            size=(48, 64),
            mode="bilinear",
        )
        .permute(0, 2, 3, 1)
        .numpy()
        .astype(np.uint8)
    )
    with io.VideoWriter(tmp_path / "colour.mp4", fps=10, crf=0) as writer:
        writer.write_frames(smooth)
    # grey fly footage: within a grey level; colour: FFmpeg's fixed-point chroma path differs slightly
    for path, tol, mean_tol in (
        (df3d_sample_dir / "camera_1.mp4", 1, 0.5),
        (tmp_path / "colour.mp4", 4, 1.5),
    ):
        reader = io.VideoReader(path)
        assert reader.pixel_format() == "yuv420p" and reader.color_tags() == ("bt601", "limited")
        planes = np.stack(list(reader.stream_frames(stop=3, format="yuv420p")))
        rgb = yuv420p_to_rgb(torch.from_numpy(planes)).numpy().astype(int)
        diff = np.abs(rgb - reader[:3].astype(int))
        assert diff.max() <= tol and diff.mean() < mean_tol


def test_yuv_streaming_path_gives_the_same_detections(default_data, tiny_checkpoint, tmp_path):
    frames = np.repeat(np.linspace(30, 220, 96 * 128).reshape(1, 96, 128, 1), 3, axis=-1)
    frames = (frames + np.arange(4)[:, None, None, None] * 5).astype(np.uint8)
    with io.VideoWriter(tmp_path / "cam.mp4", fps=10, crf=0) as writer:
        writer.write_frames(frames)
    data = _config(default_data, tiny_checkpoint, batch_size=3)
    plan = _inputs(data).detection_plan()
    models = load_models(plan, _inputs(data).detector_params())
    sources = {s: [tmp_path / "cam.mp4"] for s in plan.sources}
    timings: dict[str, float] = {}
    start = time.perf_counter()
    rgb = stream.run_detection(plan, models, sources, batch_size=3, raw_yuv=False, timings=timings)
    wall = time.perf_counter() - start
    yuv = stream.run_detection(plan, models, sources, batch_size=3, raw_yuv=True)
    # the loop's time accounts: on the CPU the forwards run inside "launch"
    assert set(timings) == {"wait_decode", "launch", "wait_device", "scatter"}
    assert min(timings.values()) >= 0 and sum(timings.values()) <= wall
    assert (
        timings["launch"] > timings["scatter"] and timings["wait_device"] < 1e-3
    )  # no GPU to wait on
    assert yuv.frame_sizes == rgb.frame_sizes == {s: (96, 128) for s in plan.sources}
    np.testing.assert_allclose(yuv.conf, rgb.conf, rtol=0.05, atol=1e-3)
    close = np.linalg.norm(yuv.pts2d - rgb.pts2d, axis=-1) < 1.0
    assert close[~np.isnan(rgb.conf)].mean() > 0.95
