"""flylib's detector against DeepFly2D's published side, not against flylib's own output.

- The network: ``state_dict()`` has exactly the entries of the released ``sh8``
  checkpoint (``../shared/spec/deepfly2d-sh8-state-dict.tsv``, derived from DeepFly2D's
  model code), and a checkpoint synthesized from that manifest in the released layout
  (``{"state_dict": {"module.<key>": tensor}}`` in a ``.tar``) loads strictly and runs.
  ``sh4``/``sh2`` expectations are derived from the same manifest by the stacking rule.
- The decoding: hand-made heatmaps with known peaks decode with DeepFly2D's
  cell-to-pixel convention (``../shared/spec/deepfly2d-heatmap-decoding.md``) on every
  pathway kind of the default plan, and agree with flylib's DeepFly3D importer on
  DeepFly3D's own 2D output.
"""

from __future__ import annotations

import copy
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch

import flylib
from flylib import io
from flylib.config import Config
from flylib.errors import ConfigError
from flylib.interop.df3d import read_df3d_points2d
from flylib.pipeline.inputs import stage_inputs
from flylib.pose2d import DetectionPlan, HourglassNet, decode, load_models, stream
from flylib.pose2d.inference import LoadedModel
from flylib.pose2d.plan import FlipLR

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
MANIFEST = SHARED / "spec" / "deepfly2d-sh8-state-dict.tsv"
RAW_SIZE, HM_SIZE = (480, 960), (64, 128)  # the rig's frames; heatmaps of a 256x512 input

# per-stack module lists: the i-th hourglass and its head, and the i-th merge back
# into the features (one fewer: the last stack has none)
_STACK_KEY = re.compile(r"^(hg|res|fc|score)\.(\d+)\.")
_MERGE_KEY = re.compile(r"^(fc_|score_)\.(\d+)\.")


def _inputs(data: dict):
    """The pose2d stage's inputs under the raw config ``data``."""
    return stage_inputs(Config.from_dict(data), "pose2d")


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Single CPU forwards: torch's thread pool only adds spin-wait on a busy 2-core box."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


# --- the published state-dict layout ---------------------------------------------


def _read_manifest(path: Path) -> dict[str, tuple[tuple[int, ...], str]]:
    """``module.<key> -> (shape, dtype)`` from the tab-separated manifest, in file order."""
    out = {}
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        key, shape, dtype = line.split("\t")
        out[key] = (
            ((), dtype) if shape == "scalar" else (tuple(int(s) for s in shape.split("x")), dtype)
        )
    return out


@pytest.fixture(scope="module")
def sh8_manifest() -> dict[str, tuple[tuple[int, ...], str]]:
    if not MANIFEST.is_file():
        pytest.skip(
            f"{MANIFEST} is absent: the published-layout tests need ../shared/spec beside the repo"
        )
    return _read_manifest(MANIFEST)


def _strip(manifest: dict) -> dict:
    assert all(k.startswith("module.") for k in manifest)
    return {k[len("module.") :]: v for k, v in manifest.items()}


def _stacks(manifest: dict, n: int) -> dict:
    """The ``n``-stack layout by DeepFly2D's stacking rule: stacks ``>= n`` removed
    (their hourglass, residual, fc and score), and the merges ``fc_``/``score_`` of
    stacks ``>= n - 1`` (the new last stack merges nothing back)."""
    out = {}
    for key, value in manifest.items():
        bare = key.removeprefix("module.")
        if (m := _STACK_KEY.match(bare)) and int(m.group(2)) >= n:
            continue
        if (m := _MERGE_KEY.match(bare)) and int(m.group(2)) >= n - 1:
            continue
        out[key] = value
    return out


def _layout(state_dict: dict[str, torch.Tensor]) -> dict[str, tuple[tuple[int, ...], str]]:
    return {k: (tuple(v.shape), str(v.dtype).removeprefix("torch.")) for k, v in state_dict.items()}


def test_the_manifest_is_the_released_sh8_layout(sh8_manifest):
    assert len(sh8_manifest) == 2526
    stripped = _strip(sh8_manifest)
    # the stem as DeepFly2D builds it (what flylib's earlier network got wrong)
    assert stripped["layer2.0.conv1.weight"] == ((128, 128, 1, 1), "float32")
    assert stripped["layer2.0.downsample.0.weight"] == ((256, 128, 1, 1), "float32")
    assert "layer3.0.downsample.0.weight" not in stripped
    stacks = {int(m.group(2)) for k in stripped if (m := _STACK_KEY.match(k))}
    assert stacks == set(range(8))


def test_default_detector_state_dict_is_exactly_the_released_layout(sh8_manifest):
    ours = _layout(HourglassNet().state_dict())  # the default detector: sh8, 19 classes
    expected = _strip(sh8_manifest)
    assert set(ours) == set(expected), (
        sorted(set(expected) - set(ours))[:5],
        sorted(set(ours) - set(expected))[:5],
    )
    wrong = {k: (ours[k], expected[k]) for k in expected if ours[k] != expected[k]}
    assert not wrong, list(wrong.items())[:5]
    assert len(ours) == 2526


@pytest.mark.parametrize("n", [4, 2, 1])
def test_fewer_stacks_follow_the_same_rule(sh8_manifest, n):
    expected = _strip(_stacks(sh8_manifest, n))
    assert _layout(HourglassNet(num_stacks=n).state_dict()) == expected
    # each stack beyond the first adds the same entries: its hourglass, head and merge
    per_stack = (len(sh8_manifest) - len(_stacks(sh8_manifest, 1))) // 7
    assert len(expected) == len(_stacks(sh8_manifest, 1)) + (n - 1) * per_stack


def _synthesize(manifest: dict, path: Path, seed: int = 0) -> dict[str, torch.Tensor]:
    """A checkpoint in the released layout: random tensors of the manifest's shapes and
    dtypes, saved as ``{"state_dict": {...}}`` with ``torch.save`` (keys as listed)."""
    gen = torch.Generator().manual_seed(seed)
    state = {}
    for key, (shape, dtype) in manifest.items():
        if dtype == "int64":
            state[key] = torch.randint(1, 10_000, shape, generator=gen, dtype=torch.int64)
        elif key.endswith("running_var"):
            state[key] = 0.5 + torch.rand(shape, generator=gen)
        else:
            assert dtype == "float32", (key, dtype)
            state[key] = 0.05 * torch.randn(shape, generator=gen)
    torch.save({"state_dict": state}, path)
    return state


def _assert_loaded(net: HourglassNet, state: dict[str, torch.Tensor]) -> None:
    loaded = net.state_dict()
    for key, value in state.items():
        assert torch.equal(loaded[key.removeprefix("module.")].cpu(), value), key


@pytest.fixture(scope="module")
def sh8_checkpoint(sh8_manifest, tmp_path_factory) -> tuple[Path, dict[str, torch.Tensor]]:
    path = tmp_path_factory.mktemp("released") / "sh8_deepfly.tar"
    return path, _synthesize(sh8_manifest, path)


def test_a_released_layout_sh8_checkpoint_loads_strictly_and_runs(sh8_checkpoint):
    path, state = sh8_checkpoint
    net = flylib.load_detector(path, num_classes=19)  # the user's path; strict inside
    assert net.config == {
        "num_stacks": 8,
        "num_blocks": 1,
        "num_classes": 19,
        "inplanes": 64,
        "num_feats": 128,
        "init_stride": 2,
        "depth": 4,
    }
    _assert_loaded(net, state)
    with torch.inference_mode():
        heatmaps = net.heatmaps(
            torch.randn(1, 3, 256, 512, generator=torch.Generator().manual_seed(1))
        )
    assert heatmaps.shape == (1, 19, 64, 128) and torch.isfinite(heatmaps).all()
    assert heatmaps.std() > 0


def test_the_released_file_in_the_cache_serves_the_default_config(
    sh8_checkpoint, tmp_path, monkeypatch
):
    """What a user does: put the published file in the cache and run the default plan."""
    path, state = sh8_checkpoint
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path))
    (tmp_path / "sh8_deepfly.tar").symlink_to(path)
    data = copy.deepcopy(dict(Config.default().data))
    data["pose2d"]["device"] = "cpu"
    plan = _inputs(data).detection_plan()
    model = load_models(plan, _inputs(data).detector_params(), allow_download=False)["deepfly2d"]
    _assert_loaded(model.net, state)
    assert model.heatmap_size == HM_SIZE
    frames = torch.randint(
        0, 255, (1, *RAW_SIZE, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(3)
    )
    assert model.preprocess(frames, (FlipLR(),)).shape == (1, 3, 256, 512)


@pytest.mark.parametrize("n,prefix", [(4, "module."), (2, "model.")])
def test_fewer_stack_checkpoints_in_the_released_layout_load_strictly(
    sh8_manifest, tmp_path, n, prefix
):
    manifest = {prefix + k.removeprefix("module."): v for k, v in _stacks(sh8_manifest, n).items()}
    path = tmp_path / f"sh{n}.tar"
    state = _synthesize(manifest, path, seed=n)
    net = flylib.load_detector(path)
    assert net.num_stacks == n
    _assert_loaded(net, {k.removeprefix(prefix): v for k, v in state.items()})
    with torch.inference_mode():
        out = net(torch.randn(1, 3, 64, 128, generator=torch.Generator().manual_seed(4)))
    assert len(out) == n and all(o.shape == (1, 19, 16, 32) for o in out)


def test_a_checkpoint_of_the_earlier_non_deepfly2d_stem_is_refused_with_the_reason(tmp_path):
    """flylib's network before issue 11 built layer2 on the stem width (64 planes,
    128 -> 128) and put the projection on layer3; such files cannot hold DeepFly2D weights."""
    from flylib.errors import WeightsError
    from flylib.pose2d.weights import save_checkpoint

    net = HourglassNet(num_stacks=1, num_feats=8, inplanes=8)
    net.inplanes = 16  # after layer1, rebuild the rest of the stem the old way
    net.layer2, net.layer3 = net._make_residual(8, 1), net._make_residual(8, 1)
    path = save_checkpoint(net, tmp_path / "old_stem.tar")
    with pytest.raises(
        WeightsError, match=r"old_stem\.tar: the checkpoint does not fit.*earlier, non-DeepFly2D"
    ):
        flylib.load_detector(path)


# --- decoding: DeepFly2D's cell-to-pixel convention -------------------------------


@pytest.fixture(scope="module")
def default_plan() -> DetectionPlan:
    return stage_inputs(Config.default(), "pose2d").detection_plan()


def _expected_raw(cell_xy, flipped: bool) -> np.ndarray:
    """The spec's raw pixel of heatmap cell ``(x, y) = (c, r)``: ``(c / W_hm W, r / H_hm H)``,
    the normalized column mirrored (``1 - c / W_hm``) on a flipped pathway."""
    u = np.asarray(cell_xy, float)[..., 0] / HM_SIZE[1]
    v = np.asarray(cell_xy, float)[..., 1] / HM_SIZE[0]
    u = 1.0 - u if flipped else u
    return np.stack([u * RAW_SIZE[1], v * RAW_SIZE[0]], axis=-1)


def _pathway_kinds(plan: DetectionPlan) -> dict[str, list]:
    kinds: dict[str, list] = {}
    for pathway in plan.active_pathways():
        kinds.setdefault(
            "flip" if pathway.ops == (FlipLR(),) else "plain" if not pathway.ops else "other", []
        ).append(pathway)
    return kinds


def test_the_default_plan_has_plain_and_mirrored_pathways_only(default_plan):
    kinds = _pathway_kinds(default_plan)
    assert set(kinds) == {"plain", "flip"} and len(kinds["plain"]) == 4 and len(kinds["flip"]) == 4


CELLS = [
    (2, 2),
    (37, 11),
    (64, 32),
    (125, 61),
    (100, 5),
]  # (c, r), at least 2 cells from the border


@pytest.mark.parametrize("method", ["weighted", "argmax", "taylor", "parabola"])
def test_a_blob_on_a_cell_decodes_to_the_cell_on_every_pathway(default_plan, method):
    heatmaps = np.stack([0.8 * decode.gaussian_heatmap(HM_SIZE, c, sigma=1.0) for c in CELLS])[None]
    xy, conf = decode.decode_argmax(torch.from_numpy(heatmaps), method)
    np.testing.assert_allclose(xy[0].numpy(), CELLS, atol=1e-5)
    np.testing.assert_allclose(conf[0].numpy(), 0.8, rtol=1e-6)  # the raw peak value
    spec = default_plan.models["deepfly2d"]
    for pathway in default_plan.active_pathways():
        raw = pathway.heatmap_to_raw(xy[0].double().numpy(), RAW_SIZE, spec, HM_SIZE)
        np.testing.assert_allclose(
            raw, _expected_raw(CELLS, flipped=bool(pathway.ops)), atol=1e-3, err_msg=pathway.name
        )


def test_cell_to_pixel_is_exact_on_every_pathway(default_plan):
    spec = default_plan.models["deepfly2d"]
    cells = np.array([[0.0, 0.0], [127.0, 63.0], [12.25, 40.5], [128.0, 64.0]])
    for pathway in default_plan.active_pathways():
        flipped = bool(pathway.ops)
        raw = pathway.heatmap_to_raw(cells, RAW_SIZE, spec, HM_SIZE)
        np.testing.assert_allclose(raw, _expected_raw(cells, flipped), atol=1e-9)
        # 7.5 raw px per cell on a 960x480 frame; the corner cell is x = 0 (x = 960 mirrored)
        assert raw[0].tolist() == ([960.0, 0.0] if flipped else [0.0, 0.0])
        np.testing.assert_allclose(
            pathway.raw_to_heatmap(raw, RAW_SIZE, spec, HM_SIZE), cells, atol=1e-9
        )


@pytest.mark.parametrize("method", ["weighted", "taylor", "parabola"])
def test_a_blob_between_cells_decodes_between_them(default_plan, method):
    spec = default_plan.models["deepfly2d"]
    c, r = 40, 20
    for centre, axis in (((c + 0.5, r), 0), ((c, r + 0.5), 1), ((c + 0.5, r + 0.5), None)):
        hm = torch.from_numpy(decode.gaussian_heatmap(HM_SIZE, centre, sigma=1.2))[None, None]
        xy, _ = decode.decode_argmax(hm, method)
        got = xy[0, 0].double().numpy()
        for pathway in default_plan.active_pathways():
            raw = pathway.heatmap_to_raw(got, RAW_SIZE, spec, HM_SIZE)
            lo = _expected_raw((c, r), bool(pathway.ops))
            hi = _expected_raw((c + 1, r + 1), bool(pathway.ops))
            for a in (0, 1):
                if axis is None or a == axis:  # strictly between the two cells' pixels
                    assert min(lo[a], hi[a]) + 0.5 < raw[a] < max(lo[a], hi[a]) - 0.5, (
                        pathway.name,
                        centre,
                        raw,
                    )
                else:
                    assert raw[a] == pytest.approx(lo[a], abs=1e-3)
    # the symmetric refinements put an exactly half-way blob exactly half-way
    if method != "weighted":
        np.testing.assert_allclose(got, [c + 0.5, r + 0.5], atol=1e-4)


def _seed_weighted(hm: np.ndarray) -> np.ndarray:
    """The seed's refinement written out in NumPy: the arg-max cell plus the
    intensity-weighted centroid offset of its 5x5 window (negatives clipped, cells
    outside the heatmap ignored); ``(x, y)`` in cells."""
    h, w = hm.shape
    r, c = np.unravel_index(np.argmax(hm), hm.shape)
    rows, cols = np.mgrid[r - 2 : r + 3, c - 2 : c + 3]
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    weight = np.where(inside, np.clip(hm[rows.clip(0, h - 1), cols.clip(0, w - 1)], 0, None), 0.0)
    return np.array([(weight * cols).sum(), (weight * rows).sum()]) / weight.sum()


def test_the_default_refinement_is_the_seed_weighted_centroid():
    assert decode.DEFAULT_SUBPIXEL == "weighted"
    rng = np.random.default_rng(0)
    hm = rng.normal(0.0, 0.1, size=(4, 16, 24))
    for i, (r, c) in enumerate(
        [(7, 9), (0, 1), (15, 23)]
    ):  # inside, top border, bottom-right corner
        hm[i, r, c] = 2.0
    hm[3] = (
        0.7 * decode.gaussian_heatmap((16, 24), (10.3, 6.6), 1.3) ** 0.5
    )  # a wide, skewed window
    xy, conf = decode.decode_argmax(torch.from_numpy(hm)[None])  # the default
    for i in range(len(hm)):
        np.testing.assert_allclose(xy[0, i].numpy(), _seed_weighted(hm[i]), atol=1e-5)
        assert conf[0, i].item() == pytest.approx(hm[i].max())


def test_an_unknown_subpixel_method_is_a_config_error(default_plan):
    data = copy.deepcopy(dict(Config.default().data))
    assert default_plan.models["deepfly2d"].subpixel == "weighted"
    data["pose2d"]["models"][0]["subpixel"] = "quadratic"
    with pytest.raises(
        ConfigError, match=r"pose2d\.models\[0\]\.subpixel: unknown sub-pixel method 'quadratic'"
    ):
        DetectionPlan.from_tables(
            data["sources"], data["pose2d"], default_plan.view_names, default_plan.point_names
        )
    with pytest.raises(ConfigError, match=r"pose2d\.models\.deepfly2d\.subpixel"):
        Config.from_dict(data)
    data["pose2d"]["models"][0]["subpixel"] = "taylor"
    assert _inputs(data).detection_plan().models["deepfly2d"].subpixel == "taylor"


class _FixedHeatmaps(torch.nn.Module):
    """A stand-in network that returns the same hand-made heatmaps for any input."""

    def __init__(self, heatmaps: torch.Tensor):
        super().__init__()
        self.register_buffer("hm", heatmaps)

    def forward(self, x):
        return [self.hm.expand(x.shape[0], *self.hm.shape[1:])]

    def heatmaps(self, x):
        """The last stack's heatmaps, as :class:`HourglassNet` gives inference."""
        return self.forward(x)[-1]

    @staticmethod
    def output_stride() -> int:
        return 4


def test_detection_on_the_default_plan_puts_known_peaks_at_the_spec_pixels(default_plan, tmp_path):
    """Frames -> every pathway of the default plan -> (view, point): each channel's
    peak, refined by the default (the seed's weighted centroid), lands at the spec's
    raw pixel, mirrored on the flipped pathways."""
    rng = np.random.default_rng(4)
    centres = np.stack(
        [rng.uniform(3, HM_SIZE[1] - 3, 19), rng.uniform(3, HM_SIZE[0] - 3, 19)], axis=-1
    )
    heatmaps = np.stack([0.9 * decode.gaussian_heatmap(HM_SIZE, c, sigma=1.5) for c in centres])
    cells = np.stack([_seed_weighted(hm) for hm in heatmaps])
    assert np.abs(cells - centres).max() > 0.02  # the window's pull: not just any refinement
    with io.VideoWriter(tmp_path / "cam.mp4", fps=10) as writer:
        writer.write_frames(np.full((3, *RAW_SIZE, 3), 80, np.uint8))
    spec = default_plan.models["deepfly2d"]
    model = LoadedModel(
        spec, _FixedHeatmaps(torch.from_numpy(heatmaps[None]).float()), torch.device("cpu")
    )
    sources = {s: [tmp_path / "cam.mp4"] for s in default_plan.sources}
    out = stream.run_detection(
        default_plan, {"deepfly2d": model}, sources, batch_size=2, decode_buffer=1
    )
    assert out.pts2d.shape == (7, 3, 38, 2)
    for pathway in default_plan.active_pathways():
        expected = _expected_raw(cells[pathway.channels], flipped=bool(pathway.ops))
        for t in range(3):
            got = out.pts2d[pathway.views, t, pathway.points]
            np.testing.assert_allclose(got, expected, atol=2e-3, err_msg=pathway.name)
            np.testing.assert_allclose(
                out.conf[pathway.views, t, pathway.points],
                heatmaps[pathway.channels].max(axis=(1, 2)),
                rtol=1e-6,
            )


# --- agreement with flylib's DeepFly3D importer -----------------------------------


def _df3d_view_pathways(plan: DetectionPlan) -> dict[int, object]:
    """DeepFly3D camera row -> the default pathway filling that view's r*/l* points
    (rows 0-2 plain, rows 4-6 mirrored; row 3, the front camera, has no DeepFly3D 2D)."""
    out = {}
    for i, view in enumerate(plan.view_names):
        if view == "f":
            continue
        (pathway,) = {p.name: p for p in plan.active_pathways() if i in p.views}.values()
        out[i] = pathway
    return out


def test_detector_and_df3d_importer_agree_on_normalized_points(default_plan, tmp_path):
    """The same DeepFly2D normalized point read by the importer (as DeepFly3D stores it:
    mirrored cameras hold 1 - x) and decoded by the detector gives the same pixel."""
    cells = np.array([[5.0, 3.0], [64.0, 32.0], [121.0, 60.0], [17.4, 44.8]])  # (c, r)
    points2d = np.zeros((7, 1, 38, 2))
    pathways = _df3d_view_pathways(default_plan)
    for i, pathway in pathways.items():
        flipped = pathway.ops == (FlipLR(),)
        col = cells[:, 0] / HM_SIZE[1]
        points2d[i, 0, : len(cells)] = np.stack(
            [cells[:, 1] / HM_SIZE[0], 1 - col if flipped else col], -1
        )
    path = tmp_path / "df3d_result.pkl"
    with path.open("wb") as fh:
        pickle.dump({"points2d": points2d}, fh)
    imported = read_df3d_points2d(path, [RAW_SIZE] * 7)
    spec = default_plan.models["deepfly2d"]
    assert {p.ops for p in pathways.values()} == {(), (FlipLR(),)}
    for i, pathway in pathways.items():
        detector = pathway.heatmap_to_raw(cells, RAW_SIZE, spec, HM_SIZE)
        np.testing.assert_allclose(
            imported.xy[i, 0, : len(cells)], detector, atol=1e-9, err_msg=pathway.name
        )


def test_deepfly3d_real_2d_lies_on_the_detector_grid(df3d_pickle, default_plan):
    """DeepFly3D's own 2D for the sample recording: each detected point is a whole
    heatmap cell under the detector's convention, and the detector maps that cell to
    exactly the pixel flylib's importer reads (no half-cell shift on either path)."""
    with df3d_pickle.open("rb") as fh:
        norm = np.asarray(pickle.load(fh)["points2d"], float)
    imported = read_df3d_points2d(df3d_pickle, [RAW_SIZE] * norm.shape[0])
    spec = default_plan.models["deepfly2d"]
    checked = 0
    for i, pathway in _df3d_view_pathways(default_plan).items():
        seen = np.isfinite(imported.xy[i]).all(-1)
        if not seen.any():
            continue
        flipped = pathway.ops == (FlipLR(),)
        col = 1 - norm[i][..., 1] if flipped else norm[i][..., 1]
        cells = np.stack([col * HM_SIZE[1], norm[i][..., 0] * HM_SIZE[0]], axis=-1)[seen]
        np.testing.assert_allclose(cells, np.round(cells), atol=1e-6)  # whole cells
        detector = pathway.heatmap_to_raw(np.round(cells), RAW_SIZE, spec, HM_SIZE)
        np.testing.assert_allclose(detector, imported.xy[i][seen], atol=1e-6, err_msg=pathway.name)
        checked += len(cells)
    assert checked > 1000
