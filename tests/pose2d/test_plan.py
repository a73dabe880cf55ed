"""The detection plan, the preprocessing ops and their exact inversion, heatmap decoding."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from flylib.errors import ConfigError
from flylib.pose2d import decode
from flylib.pose2d.plan import (
    Crop,
    DetectionPlan,
    FlipLR,
    FlipUD,
    ModelSpec,
    Pathway,
    Resize,
    Rot90,
    parse_op,
)

RNG = np.random.default_rng(7)
OPS = [
    FlipLR(),
    FlipUD(),
    Rot90(1),
    Rot90(2),
    Rot90(3),
    Crop(5, 3, 40, 30),
    Resize(24, 32),
    Resize(100, 90),
]


def _blob_image(size, xy, sigma=2.0):
    """(1, 1, H, W) float64 Gaussian blob centred at sub-pixel (x, y)."""
    return torch.from_numpy(decode.gaussian_heatmap(size, xy, sigma))[None, None]


def _centroid(image: torch.Tensor) -> np.ndarray:
    img = image[0, 0].double().numpy()
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    return np.array([(img * xx).sum(), (img * yy).sum()]) / img.sum()


@pytest.mark.parametrize(
    "op", [FlipLR(), FlipUD(), Rot90(1), Rot90(2), Rot90(3), Crop(7, 4, 40, 30)]
)
def test_exact_ops_move_pixels_where_the_points_go(op):
    size = (48, 64)
    raw = np.zeros(size)
    x, y = 13, 29
    raw[y, x] = 1.0
    out = op.apply(torch.from_numpy(raw)[None, None])[0, 0].numpy()
    assert out.shape == op.out_size(size)
    rows, cols = np.nonzero(out)
    np.testing.assert_array_equal(op.forward_points(np.array([x, y]), size), [cols[0], rows[0]])


@pytest.mark.parametrize("k", [1, 2, 3])
def test_rot90_matches_numpy(k):
    size = (5, 8)
    img = np.arange(40.0).reshape(size)
    out = Rot90(k).apply(torch.from_numpy(img)[None, None])[0, 0].numpy()
    np.testing.assert_array_equal(out, np.rot90(img, k))
    # the value at a point lands where forward_points says
    for x, y in [(0, 0), (7, 4), (3, 2)]:
        fx, fy = Rot90(k).forward_points(np.array([x, y], float), size)
        assert out[int(fy), int(fx)] == img[y, x]


@pytest.mark.parametrize(
    "size,new", [((60, 80), (30, 40)), ((48, 96), (64, 128)), ((480, 960), (256, 512))]
)
def test_resize_moves_a_blob_centroid_where_the_point_goes(size, new):
    xy = np.array([size[1] * 0.37 + 0.3, size[0] * 0.61 - 0.2])
    sigma = 0.05 * size[1]
    out = Resize(*new).apply(_blob_image(size, xy, sigma).float())
    expected = Resize(*new).forward_points(xy, size)
    np.testing.assert_allclose(_centroid(out), expected, atol=0.03 * max(1, new[1] / size[1]))


@pytest.mark.parametrize("op", OPS)
def test_inverse_undoes_forward(op):
    size = (60, 80)
    pts = RNG.uniform(-0.5, 59.5, size=(10, 3, 2))
    back = op.inverse_points(op.forward_points(pts, size), size)
    np.testing.assert_allclose(back, pts, atol=1e-12)


def _spec(input_size=(64, 128)):
    return ModelSpec("m", "hourglass", "", input_size, 0.22, 1.0, 19)


def _pathway(ops):
    empty = np.zeros(0, dtype=np.int64)
    return Pathway("p", "s", "m", "pre", tuple(ops), empty, empty, empty)


@pytest.mark.parametrize("method", ["taylor", "parabola"])  # exact for a Gaussian blob
@pytest.mark.parametrize(
    "ops",
    [
        (),
        (FlipLR(),),
        (Crop(100, 40, 600, 300), FlipLR()),
        (Rot90(1), FlipUD()),
        (Crop(10, 20, 700, 400), Rot90(3), Resize(300, 200), FlipLR()),
    ],
)
def test_a_heatmap_peak_decodes_back_to_its_raw_pixel(ops, method):
    """Raw pixel -> heatmap position -> Gaussian heatmap -> sub-pixel decode -> raw pixel."""
    raw_size, hm_size = (480, 960), (16, 32)
    pathway, spec = _pathway(ops), _spec()
    # a raw point that stays inside every crop, away from the heatmap border
    raw = np.array([[412.3, 201.7], [300.0, 255.5], [505.25, 262.8]])
    on_hm = pathway.raw_to_heatmap(raw, raw_size, spec, hm_size)
    assert np.all((on_hm > 1) & (on_hm < np.array(hm_size[::-1]) - 2))
    heatmaps = np.stack([decode.gaussian_heatmap(hm_size, p, sigma=1.3) for p in on_hm])[None]
    xy, conf = decode.decode_argmax(torch.from_numpy(heatmaps), method)
    back = pathway.heatmap_to_raw(xy.double().numpy()[0], raw_size, spec, hm_size)
    np.testing.assert_allclose(back, raw, atol=1e-3)
    assert np.all(conf.numpy() > 0.7)


def test_flip_pathway_equals_mirrored_frame():
    """The flip preprocessor is x -> W - x in the raw frame through the whole chain
    (DeepFly2D's normalized x -> 1 - x)."""
    raw_size, hm_size, spec = (480, 960), (16, 32), _spec()
    xy_hm = np.array([[7.3, 5.9]])
    plain = _pathway(()).heatmap_to_raw(xy_hm, raw_size, spec, hm_size)
    flipped = _pathway((FlipLR(),)).heatmap_to_raw(xy_hm, raw_size, spec, hm_size)
    np.testing.assert_allclose(flipped, [[960 - plain[0, 0], plain[0, 1]]], atol=1e-12)


# --- decoding ---------------------------------------------------------------


@pytest.mark.parametrize("method", ["taylor", "parabola"])
@pytest.mark.parametrize("centre", [(10.3, 7.8), (3.0, 4.0), (20.49, 1.6), (5.5, 8.5)])
def test_decode_argmax_recovers_a_gaussian_centre(centre, method):
    hm = torch.from_numpy(decode.gaussian_heatmap((12, 24), centre, sigma=1.7))[None, None]
    xy, conf = decode.decode_argmax(hm * 0.8, method)
    np.testing.assert_allclose(xy[0, 0].numpy(), centre, atol=1e-4)
    peak = 0.8 * decode.gaussian_heatmap((12, 24), centre, 1.7).max()
    assert conf[0, 0].item() == pytest.approx(peak, rel=1e-6)


def test_decode_argmax_handles_negative_values_and_borders():
    hm = torch.full((1, 2, 8, 8), -1.0)
    # a parabola in x around 3.25 sampled with negative neighbours: value-space fit
    xs = torch.arange(8.0)
    hm[0, 0, 4] = -((xs - 3.25) ** 2)
    hm[0, 1, 0, 7] = 5.0  # corner peak: no refinement possible
    xy, conf = decode.decode_argmax(hm, "parabola")
    np.testing.assert_allclose(xy[0, 0].numpy(), [3.25, 4.0], atol=1e-5)
    np.testing.assert_allclose(xy[0, 1].numpy(), [7.0, 0.0])
    assert conf[0, 1].item() == 5.0


def test_topk_peaks_orders_pads_and_refines():
    hm = 0.9 * decode.gaussian_heatmap((20, 30), (6.2, 5.4), 1.2) + 0.5 * decode.gaussian_heatmap(
        (20, 30), (22.7, 13.1), 1.2
    )
    xy, score = decode.topk_peaks(
        torch.from_numpy(hm)[None, None], k=3, threshold=0.05, method="parabola"
    )
    np.testing.assert_allclose(xy[0, 0, 0].numpy(), [6.2, 5.4], atol=1e-3)
    np.testing.assert_allclose(xy[0, 0, 1].numpy(), [22.7, 13.1], atol=1e-3)
    assert score[0, 0, 0] > score[0, 0, 1] > 0
    assert torch.isnan(xy[0, 0, 2]).all() and torch.isnan(score[0, 0, 2])


# --- the plan ---------------------------------------------------------------


@pytest.fixture(scope="module")
def default_data():
    from flylib.config import Config

    return copy.deepcopy(dict(Config.default().data))


def _plan(data: dict) -> DetectionPlan:
    """The plan of the raw config ``data``'s tables (its cameras and skeleton points)."""
    views = [v for v in data["cameras"] if v != "defaults"]
    return DetectionPlan.from_tables(
        data["sources"], data["pose2d"], views, data["skeleton"]["point_names"]
    )


def test_default_plan_structure(default_data):
    plan = _plan(default_data)
    assert plan.view_names == ("rh", "rm", "rf", "f", "lf", "lm", "lh")
    assert len(plan.point_names) == 38
    assert plan.view_sources() == {
        "rh": "vid_rh",
        "rm": "vid_rm",
        "rf": "vid_rf",
        "f": "vid_f",
        "lf": "vid_lf",
        "lm": "vid_lm",
        "lh": "vid_lh",
    }
    filled = plan.filled_mask()
    assert filled.sum(axis=1).tolist() == [19, 19, 16, 14, 16, 19, 19]
    # the front camera: right points from the plain pathway, left points from the mirror
    by_name = {p.name: p for p in plan.pathways}
    assert by_name["f_flip"].ops == (FlipLR(),) and by_name["f"].ops == ()
    f = plan.view_names.index("f")
    lf_claw = plan.point_names.index("lf_claw")
    slot = np.nonzero((by_name["f_flip"].views == f) & (by_name["f_flip"].points == lf_claw))[0]
    assert by_name["f_flip"].channels[slot].tolist() == [4]
    assert [p.name for p in plan.pathways_on("vid_f")] == ["f", "f_flip"]


def _broken(data, edit):
    data = copy.deepcopy(data)
    edit(data)
    return data


@pytest.mark.parametrize(
    "edit,match",
    [
        (
            lambda d: d["pose2d"]["pathways"][0].update(source="nope"),
            r"pathways\[0\].*unknown source 'nope'",
        ),
        (lambda d: d["pose2d"]["pathways"][0].update(model="nope"), r"unknown model 'nope'"),
        (lambda d: d["pose2d"]["pathways"][0].update(preprocessor="nope"), r"unknown preprocessor"),
        (
            lambda d: d["pose2d"]["output_points"]["rh"]["rf_claw"].update(out_channel=19),
            r"rh\.rf_claw\.out_channel",
        ),
        (
            lambda d: d["pose2d"]["output_points"]["rh"].update(
                bogus={"pathway": "rh", "out_channel": 0}
            ),
            r"unknown skeleton point",
        ),
        (
            lambda d: d["pose2d"]["output_points"]["rh"]["rf_claw"].update(pathway="lm_flip"),
            r"view 'rh' takes points from sources",
        ),
        (
            lambda d: d["pose2d"]["preprocessors"][0]["ops"].append({"op": "shear"}),
            r"unknown op 'shear'",
        ),
        (lambda d: d["pose2d"]["models"][0].update(input_size=[250, 512]), r"multiples of 64"),
    ],
)
def test_plan_errors_name_the_key(default_data, edit, match):
    with pytest.raises(ConfigError, match=match):
        _plan(_broken(default_data, edit))


def test_parse_op_validates_parameters():
    assert parse_op({"op": "crop", "x0": 1, "y0": 2, "width": 3, "height": 4}, "w") == Crop(
        1, 2, 3, 4
    )
    assert parse_op({"op": "rot90"}, "w") == Rot90(1)
    with pytest.raises(ConfigError, match=r"w: missing key 'height'"):
        parse_op({"op": "crop", "x0": 1, "y0": 2, "width": 3}, "w")
    with pytest.raises(ConfigError, match=r"unknown key"):
        parse_op({"op": "fliplr", "k": 1}, "w")
    with pytest.raises(ConfigError, match="leaves the"):
        _pathway((Crop(900, 0, 100, 10),)).check_frame((480, 960))
