"""The two pictures of the docs that come from flylib's own facts, drawn with matplotlib:

- ``keypoints.png`` (docs/reference/keypoints.md): the 38 points of the default skeleton,
  numbered by their index, on the demo's synthetic fly (:func:`flylib.synthetic_fly`, frame
  0), from above and from each side, bones and colours from the skeleton's limbs and palette;
- ``rig.png`` (docs/guides/cameras.md): the default config's cameras seen from above, each
  at its position in the rig (:meth:`flylib.CameraGroup.from_config`), with its name,
  azimuth and footage file.

Run: ``python docs/images/make_figures.py`` (writes both beside this file; a test checks
the pictures are current: tests/project/test_docs.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from flylib import CameraGroup, Config, Skeleton, synthetic_fly  # noqa: E402

HERE = Path(__file__).resolve().parent
#: what each panel shows: title, the world axes drawn right and up (sign, axis), the points labelled
PANELS = (
    ("from above (head up)", (-1, 1), (1, 0), "lr"),
    ("the fly's right side (head right)", (1, 0), (1, 2), "r"),
    ("the fly's left side (head left)", (-1, 0), (1, 2), "l"),
)


def _project(points: np.ndarray, right: tuple[int, int], up: tuple[int, int]) -> np.ndarray:
    return np.stack([right[0] * points[:, right[1]], up[0] * points[:, up[1]]], axis=-1)


def keypoints_figure(path: Path) -> None:
    """``keypoints.png``: every point of the default skeleton, numbered."""
    skeleton = Skeleton.fly()
    pose = synthetic_fly(1)[0]
    bones = np.asarray(skeleton.bones, int)
    limb_of = {p: limb for limb, pts in skeleton.limbs.items() for p in pts}
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.4), width_ratios=[1.0, 1.3, 1.3])
    for ax, (title, right, up, sides) in zip(axes, PANELS, strict=True):
        xy = _project(pose, right, up)
        # the far side first, faded: it is behind the near one in a side view
        order = sorted(range(len(xy)), key=lambda i: skeleton.point_names[i][0] in sides)
        for a, b in bones:
            near = skeleton.point_names[a][0] in sides
            color = skeleton.limb_color(limb_of[skeleton.point_names[a]])
            ax.plot(*xy[[a, b]].T, color=color, lw=2.0, alpha=1.0 if near else 0.15)
        for i in order:
            name = skeleton.point_names[i]
            near = name[0] in sides
            color = skeleton.limb_color(limb_of[name])
            ax.plot(*xy[i], "o", ms=5, color=color, alpha=1.0 if near else 0.15)
            if near:
                ax.annotate(
                    str(i),
                    xy[i],
                    xytext=(4, 3),
                    textcoords="offset points",
                    fontsize=7.5,
                    color="black",
                )
        ax.set_title(title, fontsize=11)
        ax.set_aspect("equal")
        ax.margins(0.08)
        ax.set_xticks([])
        ax.set_yticks([])
    handles = [
        plt.Line2D([], [], color=skeleton.limb_color(limb), lw=3, label=limb)
        for limb in skeleton.limb_names
    ]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=9, frameon=False)
    fig.suptitle(
        "fly38: the default skeleton's points by index (the demo's synthetic fly, frame 0)",
        fontsize=12,
    )
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def rig_figure(path: Path) -> None:
    """``rig.png``: the default config's cameras from above, the fly (enlarged) at the centre."""
    config = Config.default()
    views = config.view_names()
    rig = CameraGroup.from_config(config, {v: (480, 960) for v in views})
    defaults, specs = config.camera_table()
    files = config.source_patterns()
    source_of = {p["name"]: p["source"] for p in config.data["pose2d"]["pathways"]}
    plan = config.data["pose2d"]["output_points"]  # view -> point -> its pathway
    footage_of = {
        view: ", ".join(sorted({files[source_of[e["pathway"]]] for e in plan[view].values()}))
        for view in views
    }
    skeleton = Skeleton.fly()
    pose = synthetic_fly(1)[0]
    distance = float(defaults["distance"])
    fly = _project(pose - pose.mean(0), (-1, 1), (1, 0)) * (0.45 * distance / np.ptp(pose[:, 0]))
    limb_of = {p: limb for limb, pts in skeleton.limbs.items() for p in pts}

    fig, ax = plt.subplots(figsize=(7.2, 7.2))
    for a, b in np.asarray(skeleton.bones, int):
        color = skeleton.limb_color(limb_of[skeleton.point_names[a]])
        ax.plot(*fly[[a, b]].T, color=color, lw=1.5)
    ring = np.linspace(0, 2 * np.pi, 200)
    ax.plot(distance * np.cos(ring), distance * np.sin(ring), color="0.85", lw=1, zorder=0)
    for name, position in zip(rig.names, rig.positions, strict=True):
        x, y = -position[1], position[0]  # from above, head up: the fly's left on the left
        ax.annotate(
            "",
            xy=(0.6 * x, 0.6 * y),
            xytext=(0.9 * x, 0.9 * y),
            arrowprops={"arrowstyle": "->", "color": "0.4"},
        )
        ax.plot(x, y, "s", ms=14, color="#333333")
        footage = footage_of[name]
        azimuth = specs[name].get("azimuth_deg", defaults.get("azimuth_deg"))
        ax.annotate(
            f"{name}\n{footage}\nazimuth {azimuth:g}°",
            (x, y),
            xytext=(1.37 * x, 1.27 * y),
            ha="center",
            va="center",
            fontsize=10,
        )
    ax.text(
        0, -0.42 * distance, "fly (enlarged)\nhead up, left on the left", ha="center", fontsize=9
    )
    ax.set_aspect("equal")
    lim = 1.5 * distance
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.axis("off")
    ax.set_title(
        f"the default rig from above: {len(views)} cameras at distance {distance:g}, elevation 0",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(outdir: Path = HERE) -> list[Path]:
    paths = [outdir / "keypoints.png", outdir / "rig.png"]
    keypoints_figure(paths[0])
    rig_figure(paths[1])
    return paths


if __name__ == "__main__":
    for written in main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE):
        print(f"{written} ({written.stat().st_size // 1024} KiB)")
