"""Visualization: spec parsing and kwargs merging, pixel-exact drawing, the compositor,
streaming renders of the real DeepFly3D sample, and the summary figure."""

from __future__ import annotations

import copy
import dataclasses
import pickle
import warnings

import av
import cv2
import numpy as np
import pytest

from flylib.camera.rig import CameraGroup
from flylib.config import Config
from flylib.errors import ConfigError
from flylib.results import PoseResult
from flylib.skeleton import Skeleton
from flylib.visualization import (
    Compositor,
    read_video_specs,
    render_videos,
    resolve_output_fps,
    summary_figure,
)
from flylib.visualization.compose import frame_stamp
from flylib.visualization.draw import (
    draw_skeleton_2d,
    draw_skeleton_3d,
    skeleton_colors,
    to_panel_coords,
)
from flylib.visualization.specs import video_specs
from flylib.visualization.summary import error_per_view, error_ticks, trajectory_points

VIEWS = ["rh", "rm", "rf", "f", "lf", "lm", "lh"]
RED, BLUE = "#ff0000", "#0000ff"


def tiny_skeleton() -> Skeleton:
    """Two 2-point limbs (one bone each) and a lone point in no limb."""
    return Skeleton(
        point_names=("a0", "a1", "b0", "b1", "lone"),
        limbs={"a": ("a0", "a1"), "b": ("b0", "b1")},
        palette={"a": RED, "b": BLUE},
    )


def vis_table(**overrides) -> dict:
    """A visualization table in the default config's style: one video, f and rf panels."""
    table = {
        "background": "black",
        "kwargs": {
            "imshow": {"width": 480, "height": 240},
            "skeleton_2d": {"line_thickness": 2, "width": 480, "height": 240},
            "skeleton_3d": {"line_thickness": 2, "width": 480, "height": 240},
        },
        "videos": [
            {
                "video_name": "pose2d",
                "panels": [
                    {"plot": "imshow", "view": "f", "x0": 240, "y0": 0},
                    {"plot": "skeleton_2d", "view": "f", "x0": 240, "y0": 0},
                    {"plot": "imshow", "view": "rf", "x0": 0, "y0": 240},
                    {"plot": "skeleton_2d", "view": "rf", "x0": 0, "y0": 240},
                ],
            },
        ],
    }
    table.update(overrides)
    return table


def config_dict(table: dict) -> dict:
    return {"cameras": {"defaults": {}, **{v: {} for v in VIEWS}}, "visualization": table}


# -- specs ----------------------------------------------------------------------------


def test_specs_merge_kwargs_most_specific_wins_and_canvas_autosizes():
    table = vis_table()
    table["kwargs"]["point_radius"] = 7  # global, every plot
    table["kwargs"]["skeleton_2d"]["palette"] = {"a": "#010203", "b": "#040506"}
    video = table["videos"][0]
    video["kwargs"] = {"line_thickness": 5, "skeleton_2d": {"point_radius": 4}}
    video["panels"][3].update(point_radius=1, palette={"b": "white"})
    (spec,) = read_video_specs(table, view_names=VIEWS)
    imshow_f, skel_f, _, skel_rf = spec.panels
    assert (imshow_f.point_radius, imshow_f.line_thickness) == (7, 5)
    assert (skel_f.point_radius, skel_f.line_thickness) == (4, 5)
    assert skel_rf.point_radius == 1
    # palettes merge limb by limb across levels
    assert skel_f.palette == {"a": (1, 2, 3), "b": (4, 5, 6)}
    assert skel_rf.palette == {"a": (1, 2, 3), "b": (255, 255, 255)}
    assert spec.background == (0, 0, 0)
    assert skel_rf.where == "visualization.videos[0].panels[3]"
    assert spec.canvas_size({"f": (480, 960), "rf": (480, 960)}) == (720, 480)


def test_panel_size_keeps_aspect_when_one_side_is_given():
    table = vis_table(kwargs={})
    panels = table["videos"][0]["panels"]
    panels[0].update(width=300)
    panels[1].update(height=100)
    panels[2].update(scale=0.25)
    panels[3].update(width=100, height=100, scale=2.0)
    p = read_video_specs(table, view_names=VIEWS)[0].panels
    frame = (480, 960)
    assert p[0].size(frame) == (300, 150)
    assert p[1].size(frame) == (200, 100)
    assert p[2].size(frame) == (240, 120)
    assert p[3].size(frame) == (200, 200)
    # the automatic canvas covers every panel and is rounded up to even sizes
    odd = read_video_specs(vis_table(kwargs={"width": 101, "height": 51}), view_names=VIEWS)[0]
    assert odd.canvas_size({"f": (480, 960), "rf": (480, 960)}) == (342, 292)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (
            lambda t: t["videos"][0]["panels"][1].update(plot="heatmap"),
            r"visualization\.videos\[0\]\.panels\[1\]\.plot: unknown plot 'heatmap'",
        ),
        (
            lambda t: t["videos"][0]["panels"][2].update(view="top"),
            r"visualization\.videos\[0\]\.panels\[2\]\.view: 'top' is not a view of the rig",
        ),
        (
            lambda t: t["videos"][0].update(width=600),
            r"visualization\.videos\[0\]\.panels\[0\]: panel is off the canvas",
        ),
        (
            lambda t: t["videos"][0]["panels"][3].update(x0=-1),
            r"visualization\.videos\[0\]\.panels\[3\]: panel is off the canvas",
        ),
        (
            lambda t: t["videos"][0]["panels"][0].update(radius=3),
            r"visualization\.videos\[0\]\.panels\[0\]: unknown key 'radius'",
        ),
        (
            lambda t: t["videos"][0]["panels"][0].update(line_thickness=0),
            r"visualization\.videos\[0\]\.panels\[0\]\.line_thickness must be",
        ),
        (
            lambda t: t["kwargs"]["skeleton_2d"].update(palette={"a": "notacolour"}),
            r"visualization\.videos\[0\]\.panels\[1\]\.palette\.a: 'notacolour' is not a colour",
        ),
        (
            lambda t: t["videos"][0].update(output_fps=10, speed=2),
            r"visualization\.videos\[0\]: give output_fps or speed, not both",
        ),
        (
            lambda t: t["videos"].append(copy.deepcopy(t["videos"][0])),
            r"visualization\.videos\[1\]: video_name 'pose2d' is used twice",
        ),
    ],
)
def test_bad_specs_raise_config_error_naming_the_key(mutate, message):
    table = vis_table()
    mutate(table)
    with pytest.raises(ConfigError, match=message):
        read_video_specs(table, view_names=VIEWS)


def test_panel_off_an_explicit_canvas_is_caught_once_the_frame_size_is_known():
    table = vis_table(kwargs={})  # panels take the frame size: unknown until render
    table["videos"][0]["width"] = 1000
    (spec,) = read_video_specs(table, view_names=VIEWS)
    with pytest.raises(
        ConfigError,
        match=r"videos\[0\]\.panels\[0\]: panel 960x480 at "
        r"\(240, 0\) runs off the 1000x",
    ):
        spec.canvas_size({"f": (480, 960), "rf": (480, 960)})


def test_a_configs_videos_are_its_tables_specs_checked_against_its_cameras():
    table = vis_table()
    from_table = read_video_specs(table, view_names=VIEWS)
    from_config = video_specs(Config.from_dict(config_dict(table)))
    assert from_table == from_config
    assert [p.plot for p in from_table[0].panels] == ["imshow", "skeleton_2d"] * 2


def test_output_fps_precedence_and_nonsense_container_rate():
    table = vis_table(speed=0.5, default_fps=25)
    table["videos"].append(
        {"video_name": "fixed", "output_fps": 12.5, "panels": [{"plot": "imshow", "view": "f"}]}
    )
    table["videos"].append(
        {"video_name": "fast", "speed": 2, "panels": [{"plot": "imshow", "view": "f"}]}
    )
    slow, fixed, fast = read_video_specs(table, view_names=VIEWS)
    assert resolve_output_fps(fixed, table, 0.2) == 12.5
    assert resolve_output_fps(slow, table, 100.0) == 50.0  # global speed
    assert resolve_output_fps(fast, table, 100.0) == 200.0  # video speed beats global
    with pytest.warns(UserWarning, match=r"0\.2 fps, not plausible.*default_fps = 25"):
        assert resolve_output_fps(fast, table, 0.2) == 50.0
    plain = read_video_specs(vis_table(), view_names=VIEWS)[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_output_fps(plain, vis_table(), 100.0) == 100.0
    with pytest.warns(UserWarning, match="unknown.*30 fps"):
        assert resolve_output_fps(plain, vis_table(), None) == 30.0


# -- drawing --------------------------------------------------------------------------


def test_2d_point_lands_on_its_pixel_in_the_palette_colour_and_nan_draws_nothing():
    skel = tiny_skeleton()
    point_colors, bone_colors = skeleton_colors(skel)
    assert point_colors.tolist() == [[255, 0, 0]] * 2 + [[0, 0, 255]] * 2 + [[128] * 3]
    img = np.zeros((60, 80, 3), np.uint8)
    xy = np.full((5, 2), np.nan)
    xy[0] = (17, 23)  # a0 alone: a1 is missing, so bone a draws nothing
    xy[2] = (60, 40)  # b0 with b1 at NaN in y only
    xy[3] = (50, np.nan)
    draw_skeleton_2d(img, xy, skel.bones, point_colors, bone_colors, radius=2, thickness=3)
    assert img[23, 17].tolist() == [255, 0, 0]
    assert img[40, 60].tolist() == [0, 0, 255]
    # anti-aliased discs of radius 2: nothing beyond the edge pixels, nothing else drawn
    ys, xs = np.nonzero(img.any(axis=-1))
    dist = np.minimum(np.hypot(xs - 17, ys - 23), np.hypot(xs - 60, ys - 40))
    assert dist.max() < 3.5
    blank = np.zeros_like(img)
    draw_skeleton_2d(blank, np.full((5, 2), np.nan), skel.bones, point_colors, bone_colors)
    assert not blank.any()


def test_2d_bone_joins_its_points_in_the_limb_colour():
    skel = tiny_skeleton()
    point_colors, bone_colors = skeleton_colors(skel, {"b": (0, 200, 0)})
    img = np.zeros((50, 100, 3), np.uint8)
    xy = np.full((5, 2), np.nan)
    xy[2], xy[3] = (10, 25), (90, 25)
    draw_skeleton_2d(img, xy, skel.bones, point_colors, bone_colors, radius=0, thickness=3)
    assert (img[25, 10:91] == (0, 200, 0)).all()
    assert not img[20].any() and not img[30].any()


@pytest.mark.parametrize("near_limb", ["a", "b"])
def test_3d_nearer_bone_covers_the_farther_one_where_they_cross(near_limb):
    skel = tiny_skeleton()
    point_colors, bone_colors = skeleton_colors(skel)
    xy = np.full((5, 2), np.nan)
    xy[0], xy[1] = (10, 50), (90, 50)  # limb a: horizontal
    xy[2], xy[3] = (50, 10), (50, 90)  # limb b: vertical, crossing at (50, 50)
    depth = np.full(5, np.nan)
    near, far = (0, 1), (2, 3)
    if near_limb == "b":
        near, far = far, near
    depth[list(near)], depth[list(far)] = 10.0, 20.0
    img = np.zeros((100, 100, 3), np.uint8)
    draw_skeleton_3d(img, xy, depth, skel.bones, point_colors, bone_colors, radius=2, thickness=5)
    want = [255, 0, 0] if near_limb == "a" else [0, 0, 255]
    assert img[50, 50].tolist() == want
    assert img[50, 30].tolist() == [255, 0, 0] and img[30, 50].tolist() == [0, 0, 255]


def test_3d_points_behind_the_camera_or_nan_are_not_drawn():
    skel = tiny_skeleton()
    point_colors, bone_colors = skeleton_colors(skel)
    xy = np.array([[10, 10], [30, 10], [50, 50], [70, 50], [5, 5]], float)
    depth = np.array([-1.0, 5.0, np.nan, 5.0, 5.0])
    img = np.zeros((60, 80, 3), np.uint8)
    draw_skeleton_3d(img, xy, depth, skel.bones, point_colors, bone_colors, radius=2)
    assert not img[10, 10].any() and not img[50, 50].any() and not img[10, 20].any()
    assert img[10, 30].tolist() == [255, 0, 0] and img[50, 70].tolist() == [0, 0, 255]
    assert img[5, 5].tolist() == [128, 128, 128]


def test_panel_coordinates_match_opencv_resize_alignment():
    frame = np.zeros((480, 960), np.uint8)
    frame[50:52, 100:102] = 255  # a 2x2 block centred at (100.5, 50.5)
    small = cv2.resize(frame, (480, 240), interpolation=cv2.INTER_AREA)
    y, x = np.unravel_index(np.argmax(small), small.shape)
    mapped = to_panel_coords(np.array([100.5, 50.5]), (480, 960), (480, 240))
    np.testing.assert_allclose(mapped, [x, y], atol=1e-12)
    up = cv2.resize(np.pad(np.ones((1, 1)), 2), (15, 15), interpolation=cv2.INTER_LINEAR)
    y, x = np.unravel_index(np.argmax(up), up.shape)  # 5x5 -> 15x15: pixel 2 -> 7
    np.testing.assert_allclose(to_panel_coords(np.array([2.0, 2.0]), (5, 5), (15, 15)), [x, y])


# -- compositor -----------------------------------------------------------------------


def test_compositor_draws_panels_in_order_with_backgrounds():
    skel = tiny_skeleton()
    table = {
        "background": [10, 20, 30],
        "videos": [
            {
                "video_name": "v",
                "panels": [
                    {"plot": "imshow", "view": "f", "x0": 0, "y0": 0, "width": 100},
                    {
                        "plot": "skeleton_2d",
                        "view": "f",
                        "x0": 0,
                        "y0": 0,
                        "width": 100,
                        "point_radius": 1,
                    },
                    {"plot": "imshow", "view": "rf", "x0": 100, "y0": 0, "width": 100},
                    {
                        "plot": "skeleton_3d",
                        "view": "rf",
                        "x0": 0,
                        "y0": 50,
                        "width": 100,
                        "background": "white",
                        "point_radius": 1,
                    },
                ],
            }
        ],
    }
    (spec,) = read_video_specs(table, view_names=VIEWS)
    sizes = {"f": (100, 200), "rf": (100, 200)}
    comp = Compositor(spec, skel, sizes)
    assert (comp.width, comp.height) == (200, 100)
    frame = np.full((100, 200, 3), 77, np.uint8)
    pts2d = np.full((5, 2), np.nan)
    pts2d[0] = (40.5, 20.5)  # raw pixel -> panel (20, 10)
    xy3 = np.full((5, 2), np.nan)
    xy3[2] = (120.5, 40.5)  # -> panel (60, 20) -> canvas (60, 70)
    canvas = comp.compose({"f": frame}, {"f": pts2d}, {"rf": (xy3, np.array([1.0, 1, 1, 1, 1]))})
    assert canvas[10, 20].tolist() == [255, 0, 0]  # 2D point over imshow
    assert canvas[5, 50].tolist() == [77, 77, 77]  # resized frame
    assert canvas[70, 60].tolist() == [0, 0, 255]  # 3D point
    assert canvas[90, 10].tolist() == [255, 255, 255]  # skeleton_3d background
    assert canvas[20, 150].tolist() == [10, 20, 30]  # rf: no frame given
    # the canvas is reused; a second call redraws from scratch
    canvas = comp.compose({}, {}, {})
    assert canvas[10, 20].tolist() == [10, 20, 30]


def _two_panel_compositor(labels: bool) -> Compositor:
    table = {
        "background": "black",
        "labels": labels,
        "videos": [
            {
                "video_name": "v",
                "panels": [
                    {"plot": "imshow", "view": "f", "x0": 0, "y0": 0, "width": 200},
                    {"plot": "skeleton_2d", "view": "f", "x0": 0, "y0": 0, "width": 200},
                    {"plot": "imshow", "view": "rf", "x0": 200, "y0": 0, "width": 200},
                ],
            }
        ],
    }
    (spec,) = read_video_specs(table, view_names=VIEWS)
    return Compositor(spec, tiny_skeleton(), {"f": (100, 200), "rf": (100, 200)})


def test_panels_carry_their_view_name_and_the_canvas_the_frame_and_time():
    frame = np.full((100, 200, 3), 60, np.uint8)
    frames = {"f": frame, "rf": frame}
    stamp = frame_stamp(12, 60, 100.0)
    assert stamp == "frame 12 / 59   0.120 s" and frame_stamp(3, 15, None) == "frame 3 / 14"
    plain = _two_panel_compositor(False).compose(frames, {}, {}, stamp=stamp).copy()
    labelled = _two_panel_compositor(True).compose(frames, {}, {}, stamp=stamp)
    assert (plain == 60).all()  # labels off: the footage alone
    changed = np.argwhere((labelled != plain).any(-1))
    # ...on: white text on a black outline in three places, nothing anywhere else
    top_left = changed[(changed[:, 0] < 25) & (changed[:, 1] < 30)]  # "f"
    rf_name = changed[(changed[:, 0] < 25) & (changed[:, 1] >= 200) & (changed[:, 1] < 240)]
    bottom = changed[changed[:, 0] > 75]  # the stamp, across the first panel
    assert len(top_left) and len(rf_name) and len(bottom)
    assert len(top_left) + len(rf_name) + len(bottom) == len(changed)
    assert bottom[:, 1].max() > 150  # a whole line of text, not one glyph
    assert labelled[6:25, 200:240].max() == 255 and labelled[6:25, 200:240].min() == 0
    # the imshow panel and the skeleton over it share one area: one name, not two
    assert len(_two_panel_compositor(True).labelled) == 2


def test_the_demo_videos_play_slowed_unless_the_config_sets_a_rate():
    (spec,) = read_video_specs(vis_table(), view_names=VIEWS)
    assert resolve_output_fps(spec, {}, 100.0, 0.1) == pytest.approx(10.0)
    assert resolve_output_fps(spec, {"output_fps": 25}, 100.0, 0.1) == 25
    assert resolve_output_fps(spec, {"speed": 0.5}, 100.0, 0.1) == pytest.approx(50.0)
    assert resolve_output_fps(spec, {}, 100.0) == 100.0
    from flylib.demo import DEMO_DEFAULTS

    frames, fps, speed = (DEMO_DEFAULTS[k] for k in ("frames", "fps", "video_speed"))
    assert frames / (fps * speed) >= 5.0  # seconds of video: long enough to watch


def test_labels_must_be_a_boolean():
    with pytest.raises(ConfigError, match="visualization.labels: expected true or false"):
        read_video_specs(vis_table(labels="yes"), view_names=VIEWS)


# -- streaming render on the real DeepFly3D sample --------------------------------------


def load_df3d_points2d(path) -> np.ndarray:
    """DeepFly3D's normalized [row/480, col/960] 2D -> fly38 ``(V, T, 38, 2)`` pixels."""
    with open(path, "rb") as f:
        raw = np.asarray(pickle.load(f)["points2d"], dtype=float)
    xy = np.stack([raw[..., 1] * 960.0, raw[..., 0] * 480.0], axis=-1)
    missing = (raw[..., 0] == 0) & ((raw[..., 1] == 0) | (raw[..., 1] == 1))
    xy[missing] = np.nan
    out = np.full_like(xy, np.nan)
    out[:, :, (np.arange(38) + 19) % 38] = xy
    return out


def decoded_video(path):
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        rate = stream.average_rate
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    return np.stack(frames), rate


@pytest.fixture(scope="module")
def df3d_result(df3d_pickle):
    config = Config.default()
    cameras = CameraGroup.from_config(config, image_sizes={v: (480, 960) for v in VIEWS})
    pts2d = load_df3d_points2d(df3d_pickle)
    pts3d = cameras.triangulate(pts2d)
    return config, PoseResult(
        cameras=cameras, skeleton=Skeleton.from_config(config), pts2d=pts2d, pts3d=pts3d
    )


def test_default_videos_render_for_the_deepfly3d_sample(tmp_path, df3d_sample_dir, df3d_result):
    config, result = df3d_result
    footage = {v: [df3d_sample_dir / f"camera_{i}.mp4"] for i, v in enumerate(VIEWS)}
    with pytest.warns(UserWarning, match=r"0\.2 fps, not plausible.*30 fps"):
        paths = render_videos(config.visualization, result, footage, tmp_path, progress=False)
    assert [p.name for p in paths] == ["pose2d.mp4", "pose3d.mp4"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pose2d.mp4", "pose3d.mp4"]
    frames2d, rate = decoded_video(paths[0])
    assert frames2d.shape == (15, 960, 960, 3) and rate == 30
    frames3d, _ = decoded_video(paths[1])
    assert frames3d.shape == (15, 960, 960, 3)

    # the rf footage fills its panel at (0, 240), half size
    with av.open(str(footage["rf"][0])) as c:
        first = next(c.decode(video=0)).to_ndarray(format="rgb24")
    rf_panel = cv2.resize(first, (480, 240), interpolation=cv2.INTER_AREA).astype(int)
    background = frames3d[0, 240:480, :480].astype(int)
    assert np.median(np.abs(background - rf_panel)) < 6
    # rf's detections land where DeepFly3D put them, in their limb's palette colour
    skel = result.skeleton
    point_colors, _ = skeleton_colors(skel)
    rf = VIEWS.index("rf")
    t = 7
    seen = np.flatnonzero(np.isfinite(result.pts2d[rf, t, :, 0]))
    assert seen.size >= 10
    hits = 0
    for p in seen:
        x, y = np.round(to_panel_coords(result.pts2d[rf, t, p], (480, 960), (480, 240)))
        pixel = frames2d[t, 240 + int(y), int(x)].astype(int)
        hits += np.abs(pixel - point_colors[p]).max() < 60
    assert hits >= 0.7 * seen.size


def test_views_without_footage_draw_the_background(tmp_path, df3d_sample_dir, df3d_result):
    config, result = df3d_result
    data = copy.deepcopy(config.data)
    data["visualization"]["videos"] = data["visualization"]["videos"][:1]
    data["visualization"]["output_fps"] = 7
    data["visualization"]["background"] = [0, 0, 200]
    footage = {"rf": [df3d_sample_dir / "camera_2.mp4"]}
    with pytest.warns(UserWarning, match="no footage for views 'f', 'lf', 'rm', 'lm'"):
        (path,) = render_videos(data["visualization"], result, footage, tmp_path, progress=False)
    frames, rate = decoded_video(path)
    assert rate == 7 and frames.shape == (15, 960, 960, 3)
    # the f panel (240..720, 0..240) has no footage and view f has no detections: below
    # its name (top-left corner), the background
    assert np.abs(frames[:, 30:235, 245:715].astype(int) - [0, 0, 200]).max() < 12
    assert frames[:, 6:24, 246:262].max() > 200  # the name "f", white


# -- summary ----------------------------------------------------------------------------


def test_summary_figure_writes_a_png(tmp_path, df3d_result):
    _, result = df3d_result
    error = np.linalg.norm(result.cameras.project(result.pts3d) - result.pts2d, axis=-1)
    full = dataclasses.replace(result, reproj_error=error)
    path = summary_figure(full, tmp_path / "out" / "summary.png")
    image = cv2.imread(str(path))
    assert image.shape == (950, 1400, 3)
    assert image.std() > 10  # not a blank canvas
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["summary.png"]
    # without a 3D result the figure still renders (2D coverage, "no data" panels)
    bare = dataclasses.replace(result, pts3d=None)
    bare_png = cv2.imread(str(summary_figure(bare, tmp_path / "bare.png", dpi=40)))
    assert bare_png.shape == (380, 560, 3)


def test_error_axis_has_readable_ticks_and_the_medians_sit_under_the_boxes():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    assert error_ticks(6.5) == [0.0, 0.25, 0.5, 0.75, 1.0, 2.0, 5.0]
    assert error_ticks(140.0) == [0.0, 0.25, 0.5, 0.75, 1.0, 2, 5, 10, 20, 50, 100]
    assert error_ticks(0.4) == [0.0, 0.25, 0.5, 0.75, 1.0]
    rng = np.random.default_rng(0)
    error = np.abs(rng.normal(0, 1.5, (3, 50, 4)))  # (V, T, P)
    error[1, :5, 0] = 60.0  # a few gross outliers in one view
    fig = Figure()
    ax = fig.add_subplot()
    error_per_view(ax, error, ["rh", "f", "lh"])
    FigureCanvasAgg(fig).draw()
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels[:5] == ["0", "0.25", "0.5", "0.75", "1"] and labels[-2:] == ["20", "50"]
    medians = [f"{np.median(e):.2f}" for e in error.reshape(3, -1)]
    assert [t.get_text() for t in ax.get_xticklabels()] == [
        f"{v}\n{m} px" for v, m in zip(["rh", "f", "lh"], medians)
    ]
    assert not ax.texts  # no number printed inside the plot, over the boxes


def test_per_frame_median_matches_numpy_nanmedian():
    from flylib.visualization.summary import row_nanmedian

    rng = np.random.default_rng(0)
    rows = rng.normal(size=(400, 9))
    rows[rng.random(rows.shape) < 0.4] = np.nan
    rows[3] = np.nan  # no observation at all in a frame
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        expected = np.nanmedian(rows, axis=1)
    np.testing.assert_array_equal(row_nanmedian(rows), expected)


def test_trajectory_points_are_the_leg_tips():
    skel = Skeleton.from_config(Config.default())
    names = [skel.point_names[i] for i in trajectory_points(skel)]
    assert names == ["lf_claw", "lm_claw", "lh_claw", "rf_claw", "rm_claw", "rh_claw"]


def test_short_footage_is_an_error_naming_the_file_and_counts(
    tmp_path, df3d_sample_dir, df3d_result
):
    """Footage and result of different lengths (a truncated MP4 with its
    header) fail the job instead of drawing the background with a warning."""
    from flylib.errors import FootageError

    config, result = df3d_result
    longer = dataclasses.replace(
        result,
        pts2d=np.concatenate([result.pts2d] * 2, axis=1),
        pts3d=np.concatenate([result.pts3d] * 2, axis=0),
    )
    table = {
        "output_fps": 10,
        "background": "white",
        "videos": [
            {
                "video_name": "rf_only",
                "panels": [
                    {"plot": "imshow", "view": "rf", "width": 240},
                    {
                        "plot": "skeleton_3d",
                        "view": "rf",
                        "width": 240,
                        "point_radius": 0,
                        "line_thickness": 1,
                    },
                ],
            }
        ],
    }
    footage = {"rf": [df3d_sample_dir / "camera_2.mp4"]}
    with pytest.raises(
        FootageError,
        match=f"^{df3d_sample_dir / 'camera_2.mp4'}: footage of view 'rf' has 15 "
        "frames but the result has 30",
    ):
        render_videos(table, longer, footage, tmp_path, progress=False)
    assert not list(tmp_path.glob("*.mp4"))


def test_canvas_encoder_keeps_colours_and_crops_to_even_size(tmp_path):
    from flylib.visualization.compose import CanvasEncoder

    canvas = np.zeros((65, 97, 3), np.uint8)
    canvas[:, :48] = (186, 30, 49)
    canvas[:, 48:] = (117, 190, 203)
    encoder = CanvasEncoder(tmp_path / "c.mp4", 25, 97, 65)
    for _ in range(3):
        encoder.write_frame(canvas)
    encoder.close()
    frames, rate = decoded_video(tmp_path / "c.mp4")
    assert frames.shape == (3, 64, 96, 3) and rate == 25
    # away from the chroma-subsampled edge, colours survive RGB -> I420 -> H.264 -> RGB
    assert np.abs(frames[:, :, 4:40].astype(int) - (186, 30, 49)).max() <= 4
    assert np.abs(frames[:, :, 56:92].astype(int) - (117, 190, 203)).max() <= 4


def test_missing_footage_raises_footage_error_and_leaves_no_file(tmp_path, df3d_result):
    from flylib.errors import FootageError

    config, result = df3d_result
    footage = {"f": [tmp_path / "nope" / "camera_3.mp4"]}
    with pytest.raises(FootageError, match="camera_3.mp4"):
        render_videos(config.visualization, result, footage, tmp_path / "out", progress=False)
    assert not any((tmp_path / "out").iterdir())


def test_image_sequence_footage_renders_at_the_default_rate(tmp_path, df3d_sample_dir, df3d_result):
    from flylib.io import natural_key

    config, result = df3d_result
    images = sorted(df3d_sample_dir.glob("camera_2_img_*.jpg"), key=natural_key)
    table = {
        "default_fps": 12,
        "videos": [
            {
                "video_name": "rf",
                "panels": [
                    {"plot": "imshow", "view": "rf", "scale": 0.25},
                    {"plot": "skeleton_2d", "view": "rf", "scale": 0.25, "point_radius": 1},
                ],
            }
        ],
    }
    with pytest.warns(UserWarning, match="frame rate is unknown.*default_fps = 12"):
        (path,) = render_videos(
            table,
            result,
            {"rf": images},
            tmp_path,
            progress=False,
        )
    frames, rate = decoded_video(path)
    assert frames.shape == (15, 120, 240, 3) and rate == 12
    first = cv2.cvtColor(cv2.imread(str(images[0])), cv2.COLOR_BGR2RGB)
    small = cv2.resize(first, (240, 120), interpolation=cv2.INTER_AREA).astype(int)
    assert np.median(np.abs(frames[0].astype(int) - small)) < 6
