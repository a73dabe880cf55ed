"""Property-based fuzzing of every loader of an outside file.

Each test starts from a valid file of one format, damages it at random (bytes flipped,
overwritten, inserted, deleted or cut off; cells, values, lines and keys of text formats
replaced by hostile values; values of pickled dicts and HDF5 datasets swapped for other
types and shapes; HDF5 members made to reach beyond the file -- external storage,
external links, soft links through them, virtual datasets -- or to declare terabytes
they do not store), and feeds it to the loader. The property: the loader either returns,
or raises flylib's own error (a :class:`flylib.errors.FlylibError`) whose message names
the file in one line -- never another exception type.

The default Hypothesis profile ("flylib", tests/conftest.py) keeps the whole file under
a minute (derandomized, so every run checks the same cases);
``pytest tests/interop/test_fuzz_loaders.py --hypothesis-profile=long`` runs many more, random ones.
Known limit found that way: libhdf5 itself can loop forever reading the attributes of a
results.h5 whose object header bytes are damaged (``f.attrs.get`` never returns), which no
Python-level handling can turn into an error; HDF5's checksummed metadata
(``libver="latest"`` object headers) should detect such damage instead (not verified here).
"""

from __future__ import annotations

import atexit
import pickle
import re
import shutil
import tempfile
from functools import lru_cache
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import given, strategies as st
from hypothesis.extra import numpy as hnp

from flylib.errors import ConfigError, FlylibError
from flylib.interop import (
    read_anipose_toml,
    read_df3d_calibration,
    read_df3d_points2d,
    read_dlc_csv,
    read_dlc_h5,
    read_sleap_analysis,
    write_dlc_csv,
)

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "interop"
WORK = Path(tempfile.mkdtemp(prefix="flylib-fuzz-"))
atexit.register(shutil.rmtree, WORK, True)


def _check(load, path: Path, *, multiline_ok: bool = False):
    """Run ``load(path)``: it returns, or raises a FlylibError whose first line names the file."""
    try:
        return load(path)
    except FlylibError as exc:
        text = str(exc)
        assert text, "empty error message"
        first = text.splitlines()[0]
        assert str(path) in first or path.name in first, text
        if not multiline_ok:
            assert "\n" not in text, text


def _write(name: str, data: bytes | str) -> Path:
    path = WORK / name
    path.write_bytes(data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data)
    return path


# -- damage strategies ------------------------------------------------------------------------


@st.composite
def damaged_bytes(draw, seed: bytes, max_ops: int = 4) -> bytes:
    """``seed`` with 1..max_ops random byte-level injuries."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, max_ops))):
        if not data:
            break
        op = draw(st.sampled_from(["flip", "overwrite", "truncate", "insert", "delete", "zero"]))
        pos = draw(st.integers(0, len(data) - 1))
        if op == "flip":
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "overwrite":
            chunk = draw(st.binary(min_size=1, max_size=64))
            data[pos : pos + len(chunk)] = chunk
        elif op == "truncate":
            del data[pos:]
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif op == "delete":
            del data[pos : pos + draw(st.integers(1, 64))]
        else:  # a zeroed block, like a torn write
            n = draw(st.integers(1, 512))
            data[pos : pos + n] = bytes(min(n, len(data) - pos))
    return bytes(data)


HOSTILE_TEXT = st.one_of(
    st.sampled_from(
        [
            "",
            "nan",
            "NaN",
            "inf",
            "-inf",
            "1e400",
            "-0",
            "0",
            "-1",
            "1e-8",
            "x",
            '"',
            "'",
            "[",
            "]",
            "{}",
            "[]",
            "null",
            "~",
            "true",
            "1,2",
            "\x00",
            "\ufeff",
            "wide",
            "[1, [2]]",
            '"wide"',
            "!!python/object/apply:os.system ['touch pwned']",
            "99999999999999999999999",
            "0x10",
            "1_000",
            "- a",
            ": b",
            "&a",
            "*a",
        ]
    ),
    st.text(max_size=10),
)


@st.composite
def damaged_lines(draw, seed: str, cell_sep: str = ",") -> str:
    """``seed`` with random cells replaced, lines deleted/duplicated/swapped, or cut short."""
    lines = seed.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            break
        op = draw(st.sampled_from(["cell", "cell", "cell", "delete", "duplicate", "swap", "cut"]))
        i = draw(st.integers(0, len(lines) - 1))
        if op == "cell":
            cells = lines[i].split(cell_sep)
            j = draw(st.integers(0, len(cells) - 1))
            cells[j] = draw(HOSTILE_TEXT)
            if draw(st.booleans()) and len(cells) > 1:
                del cells[draw(st.integers(0, len(cells) - 1))]
            lines[i] = cell_sep.join(cells)
        elif op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "swap":
            k = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[k] = lines[k], lines[i]
        else:
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
            del lines[i + 1 :]
    return "\n".join(lines) + ("\n" if draw(st.booleans()) else "")


_TOKEN = re.compile(r'-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?|"[^"\n]*"|\btrue\b|\bfalse\b|\bnull\b')


@st.composite
def damaged_tokens(draw, seed: str) -> str:
    """``seed`` with random scalar tokens (numbers, strings, booleans) replaced."""
    spans = [m.span() for m in _TOKEN.finditer(seed)]
    text = seed
    for a, b in sorted(
        draw(st.lists(st.sampled_from(spans), min_size=1, max_size=4, unique=True)), reverse=True
    ):
        text = text[:a] + draw(HOSTILE_TEXT) + text[b:]
    return text


def text_damage(seed: str, cell_sep: str = ","):
    return st.one_of(
        damaged_tokens(seed),
        damaged_lines(seed, cell_sep),
        damaged_bytes(seed.encode()).map(lambda b: b.decode("utf-8", "replace")),
        damaged_bytes(seed.encode()),
    )


SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(),
    st.text(max_size=8),
    st.binary(max_size=8),
    st.complex_numbers(),
)
ARRAYS = hnp.arrays(
    dtype=st.sampled_from(
        [np.float64, np.float32, np.int64, np.uint8, np.bool_, np.complex128, "<U3", "S2"]
    ),
    shape=hnp.array_shapes(min_dims=0, max_dims=5, min_side=0, max_side=4),
)
VALUES = st.recursive(
    st.one_of(SCALARS, ARRAYS),
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.tuples(inner, inner),
        st.dictionaries(st.text(max_size=4), inner, max_size=3),
    ),
    max_leaves=8,
)


@st.composite
def damaged_dict(draw, seed: dict) -> dict:
    """``seed`` (a nested dict) with random values replaced, keys dropped or added."""
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in seed.items()}
    for _ in range(draw(st.integers(1, 3))):
        target = data
        nested = [k for k, v in data.items() if isinstance(v, dict)]
        if nested and draw(st.booleans()):
            target = data[draw(st.sampled_from(nested))]
        op = draw(st.sampled_from(["replace", "replace", "drop", "add"]))
        keys = list(target)
        if op == "add" or not keys:
            target[draw(st.one_of(st.text(max_size=4), st.integers(-3, 9)))] = draw(VALUES)
        elif op == "drop":
            del target[draw(st.sampled_from(keys))]
        else:
            target[draw(st.sampled_from(keys))] = draw(VALUES)
    return data


def pickle_damage(seed: dict):
    return st.one_of(
        damaged_dict(seed).map(pickle.dumps),
        damaged_bytes(pickle.dumps(seed)),
        damaged_bytes(pickle.dumps(seed, protocol=2)),
        VALUES.map(pickle.dumps),
    )


# -- DeepFly3D pickles ----------------------------------------------------------------------------


def _df3d_2d_seed() -> dict:
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, size=(3, 4, 38, 2))
    points[:, 1, :5] = 0.0
    return {
        "points2d": points,
        "camera_ordering": np.arange(3),
        "heatmap_confidence": rng.uniform(0, 1, size=(3, 4, 19, 1)),
    }


def _df3d_calib_seed() -> dict:
    import cv2

    calib = {"name": "rig"}
    for i in range(3):
        calib[i] = {
            "R": cv2.Rodrigues(np.array([0.0, 0.3 * i, 0.0]))[0],
            "tvec": np.array([0.0, 0.0, 110.0]),
            "intr": np.array([[16000.0, 0, 480], [0, 16000.0, 240], [0, 0, 1]]),
            "distort": np.zeros(5),
        }
    return calib


@given(pickle_damage(_df3d_2d_seed()))
def test_fuzz_df3d_2d_pickle(data):
    path = _write("df3d_result_fuzz.pkl", data)
    _check(lambda p: read_df3d_points2d(p, [(480, 960)] * 3), path)


class _Call:
    """Pickles as ``func(*args)``: an admitted global called with hostile arguments."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def _shared(levels: int, width: int) -> list:
    x = [0.5, 0.5]
    for _ in range(levels):
        x = [x] * width
    return x


def _deep(levels: int) -> list:
    x: list = [0.5, 0.5]
    for _ in range(levels):
        x = [x]
    return x


HUGE = st.integers(2**31, 2**62)
PICKLE_BOMBS = st.one_of(
    # shared lists that expand past the bound, or stay tiny (nothing in between: a
    # value under the bound really is materialized by the loader)
    st.tuples(st.integers(1, 14), st.integers(2, 40))
    .filter(lambda lw: lw[1] ** lw[0] > 2**28 or lw[1] ** lw[0] < 10**4)
    .map(lambda lw: _shared(*lw)),
    st.integers(33, 300).map(_deep),
    HUGE.map(lambda n: _Call(np.ndarray, (n,))),
    st.tuples(HUGE, st.sampled_from(["f8", "u1", "(1000,)f8"])).map(
        lambda nd: _Call(np.ndarray, (nd[0] // 10**6, 10**6), np.dtype(nd[1]))
    ),
    HUGE.map(lambda n: _Call(bytes, n)),
    HUGE.map(lambda n: _Call(bytearray, n)),
    st.integers(4, 9).map(lambda levels: _Call(str, _shared(levels, 16))),
)


@given(
    st.tuples(PICKLE_BOMBS, st.sampled_from([2, 4, 5])).map(
        lambda bp: pickle.dumps({"points2d": bp[0]}, protocol=bp[1])
    )
)
def test_fuzz_df3d_pickle_bombs(data):
    """Small pickles that would allocate without bound: refused in one line (or tiny)."""
    path = _write("df3d_result_bomb.pkl", data)
    _check(lambda p: read_df3d_points2d(p, [(480, 960)] * 3), path)


@given(pickle_damage(_df3d_calib_seed()))
def test_fuzz_df3d_calibration_pickle(data):
    path = _write("calib_fuzz.pkl", data)
    _check(read_df3d_calibration, path)


# -- DeepLabCut / Lightning Pose CSV and HDF5 ---------------------------------------------------------


@lru_cache
def _dlc_csv_seed() -> str:
    xy = np.random.default_rng(1).uniform(0, 960, size=(4, 3, 2))
    xy[0] = np.nan
    xy[2, 1] = np.nan
    return write_dlc_csv(WORK / "seed.csv", xy, None, ["head", "thorax", "tail"]).read_text()


LP_CSV = """scorer,heatmap_tracker,heatmap_tracker,heatmap_tracker,heatmap_tracker,heatmap_tracker,heatmap_tracker
bodyparts,paw1,paw1,paw1,paw2,paw2,paw2
coords,x,y,likelihood,x,y,likelihood
0,10.5,20.25,0.99,30.0,40.0,0.2
1,11.5,21.25,0.95,,,
2,12.5,22.25,0.05,32.0,42.0,0.9
"""

MULTI_CSV = """scorer,DLC,DLC,DLC,DLC,DLC,DLC
individuals,fly1,fly1,fly1,fly2,fly2,fly2
bodyparts,head,head,head,head,head,head
coords,x,y,likelihood,x,y,likelihood
0,1,2,0.9,3,4,0.8
1,,,,5,6,0.7
"""


@given(
    st.one_of(text_damage(_dlc_csv_seed()), text_damage(LP_CSV), text_damage(MULTI_CSV)),
    st.sampled_from([None, "fly1"]),
)
def test_fuzz_dlc_and_lightning_pose_csv(text, individual):
    path = _write("view_fuzz.csv", text)
    _check(lambda p: read_dlc_csv(p, individual), path)


def _h5_seed(name: str) -> bytes:
    return (DATA / name).read_bytes()


@st.composite
def damaged_h5(draw, seed: bytes) -> bytes:
    """An HDF5 file damaged in its bytes, or with a dataset/attribute replaced or removed."""
    if draw(st.booleans()):
        return draw(damaged_bytes(seed, max_ops=3))
    path = WORK / "h5_edit.h5"
    path.write_bytes(seed)
    with h5py.File(path, "r+") as f:
        items = []
        f.visititems(lambda name, obj: items.append(name))
        for _ in range(draw(st.integers(1, 3))):
            name = draw(st.sampled_from(items)) if items else ""
            obj = f[name] if name else f
            op = draw(st.sampled_from(["attr", "attr", "dataset", "delete"]))
            if op == "attr" and len(obj.attrs):
                key = draw(st.sampled_from(sorted(obj.attrs)))
                obj.attrs[key] = draw(
                    st.one_of(
                        st.binary(max_size=40).map(np.bytes_),
                        st.integers(-5, 5),
                        st.text(st.characters(exclude_characters="\x00"), max_size=8),
                        st.sampled_from(
                            [
                                b"(lp0\n.",
                                b"N.",
                                b"(dp0\n.",
                                b"cos\nsystem\n(S'touch pwned'\ntR.",
                                b"(lp0\n(I0\nI1\ntp1\na.",
                                b"I5\n.",
                            ]
                        ).map(np.bytes_),
                    )
                )
            elif op == "dataset" and isinstance(obj, h5py.Dataset):
                parent, leaf = name.rsplit("/", 1) if "/" in name else ("", name)
                del f[name]
                (f[parent] if parent else f)[leaf] = draw(
                    ARRAYS.filter(lambda a: a.dtype.kind != "U")
                )
            elif op == "delete" and name:
                del f[name]
                items = [i for i in items if not (i == name or i.startswith(name + "/"))]
    return path.read_bytes()


#: The value every byte outside a fuzzed HDF5 file holds: a loader that returns it has
#: read beyond the file (the probe saw /etc/ssl's bytes become 1e175-pixel points).
OUTSIDE = 12345.678


@lru_cache
def _outside_files() -> tuple[Path, Path]:
    """A raw file and an HDF5 file (dataset ``/data``) full of :data:`OUTSIDE`."""
    raw = WORK / "outside.bin"
    raw.write_bytes(np.full(1 << 16, OUTSIDE).tobytes())
    h5 = WORK / "outside.h5"
    with h5py.File(h5, "w") as f:
        f["data"] = np.full((4, 4, 4, 4), OUTSIDE)
        f.create_group("group")["data"] = np.full((4, 4, 4, 4), OUTSIDE)
    return raw, h5


@st.composite
def hostile_h5(draw, seed: bytes) -> bytes:
    """An HDF5 file with one member made to reach beyond it or to declare far more than
    it stores: external storage, an external link (to a dataset or through a group),
    a soft link through an external link, a virtual dataset, a sparse dataset of
    terabytes, or a chunk larger than any budget."""
    raw, other = _outside_files()
    path = WORK / "h5_hostile.h5"
    path.write_bytes(seed)
    with h5py.File(path, "r+") as f:
        items: list[str] = []
        f.visititems(
            lambda name, obj: items.append(name) if isinstance(obj, h5py.Dataset) else None
        )
        name = draw(st.sampled_from(sorted(items)))
        old = f[name]
        shape, dtype = old.shape or (1,), old.dtype if old.dtype.kind in "biuf" else np.float64
        del f[name]
        op = draw(
            st.sampled_from(
                ["external", "extlink", "extgroup", "soft-ext", "virtual", "sparse", "chunk"]
            )
        )
        if op == "external":
            nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
            f.create_dataset(name, shape=shape, dtype=dtype, external=[(str(raw), 0, nbytes)])
        elif op == "extlink":
            f[name] = h5py.ExternalLink(str(other), "/data")
        elif op == "extgroup":
            parent = name.rsplit("/", 1)[0] if "/" in name else ""
            if parent:
                del f[parent]
                f[parent] = h5py.ExternalLink(str(other), "/group")
            else:
                f[name] = h5py.ExternalLink(str(other), "/group/data")
        elif op == "soft-ext":
            f["__elsewhere"] = h5py.ExternalLink(str(other), "/group")
            f[name] = h5py.SoftLink("/__elsewhere/data")
        elif op == "virtual":
            layout = h5py.VirtualLayout(shape=(4, 4, 4, 4), dtype="<f8")
            layout[...] = h5py.VirtualSource(str(other), "data", shape=(4, 4, 4, 4))
            f.create_virtual_dataset(name, layout)
        elif op == "sparse":
            big = (*shape[:-1], 10**12) if len(shape) > 1 else (10**12,)
            f.create_dataset(name, shape=big, dtype=dtype, chunks=True)
        else:
            f.create_dataset(
                name,
                shape=shape,
                maxshape=tuple(None for _ in shape),
                chunks=(*([1] * (len(shape) - 1)), 1 << 30),
                dtype=dtype,
            )
    return path.read_bytes()


def _never_outside(result) -> None:
    """A loader that returned read nothing from beyond its file."""
    if result is not None:
        assert not np.any(np.asarray(result.xy) == OUTSIDE), "read data from another file"


DLC_H5_SEEDS = ["dlc_table.h5", "dlc_fixed.h5", "dlc_multianimal_table.h5"]


@given(
    st.sampled_from(DLC_H5_SEEDS).flatmap(lambda n: damaged_h5(_h5_seed(n))),
    st.sampled_from([None, "fly1"]),
)
def test_fuzz_dlc_h5(data, individual):
    path = _write("view_fuzz.h5", data)
    _check(lambda p: read_dlc_h5(p, individual), path)


@given(st.sampled_from(DLC_H5_SEEDS).flatmap(lambda n: hostile_h5(_h5_seed(n))))
def test_fuzz_dlc_h5_reaching_beyond_the_file(data):
    path = _write("view_hostile.h5", data)
    _never_outside(_check(lambda p: read_dlc_h5(p, "fly1"), path))


# -- SLEAP analysis files (written by sleap-io) ----------------------------------------------------------


@lru_cache
def _sleap_seeds() -> tuple[bytes, bytes]:
    sio = pytest.importorskip("sleap_io")
    skeleton = sio.Skeleton(["head", "thorax", "abdomen"])
    video = sio.Video(filename="camera_0.mp4")
    track = sio.Track("fly")
    seeds = []
    for detect in (True, False):
        frames = []
        for t in range(4):
            instances = (
                [
                    sio.PredictedInstance.from_numpy(
                        np.array([[1.0 + t, 2.0], [3.0, 4.0], [np.nan, np.nan]]),
                        skeleton=skeleton,
                        point_scores=np.array([0.9, 0.8, 0.0]),
                        score=1.0,
                        track=track,
                    )
                ]
                if detect
                else []
            )
            frames.append(sio.LabeledFrame(video=video, frame_idx=t, instances=instances))
        labels = sio.Labels(
            labeled_frames=frames,
            videos=[video],
            skeletons=[skeleton],
            tracks=[track] if detect else [],
        )
        path = WORK / f"sleap_seed_{detect}.analysis.h5"
        sio.save_analysis_h5(labels, str(path))
        seeds.append(path.read_bytes())
    return tuple(seeds)


@given(st.data(), st.sampled_from([None, 0, "fly", "1"]))
def test_fuzz_sleap_analysis(data, track):
    seed = data.draw(st.sampled_from(_sleap_seeds()))
    path = _write("view_fuzz.analysis.h5", data.draw(damaged_h5(seed)))
    _check(lambda p: read_sleap_analysis(p, track), path)


@given(st.data())
def test_fuzz_sleap_analysis_reaching_beyond_the_file(data):
    seed = data.draw(st.sampled_from(_sleap_seeds()))
    path = _write("view_hostile.analysis.h5", data.draw(hostile_h5(seed)))
    _never_outside(_check(read_sleap_analysis, path))


# -- Anipose TOML ----------------------------------------------------------------------------------

ANIPOSE = """[cam_0]
name = "rh"
size = [960, 480]
matrix = [[16000.0, 0.0, 480.0], [0.0, 16000.0, 240.0], [0.0, 0.0, 1.0]]
distortions = [0.01, 0.0, 0.0, 0.0, 0.0]
rotation = [0.0, 1.0, 0.0]
translation = [0.0, 0.0, 110.0]

[cam_1]
name = "rm"
size = [960, 480]
matrix = [[16000.0, 0.0, 480.0], [0.0, 16000.0, 240.0], [0.0, 0.0, 1.0]]
distortions = [0.0, 0.0, 0.0, 0.0, 0.0]
rotation = [0.0, 0.5, 0.0]
translation = [0.0, 0.0, 110.0]

[metadata]
adjusted = false
"""


@given(text_damage(ANIPOSE, cell_sep=" "))
def test_fuzz_anipose_toml(text):
    from flylib.interop import load_calibration

    path = _write("calibration_fuzz.toml", text)
    _check(read_anipose_toml, path)
    _check(
        lambda p: load_calibration({"file": str(p)}, ["rh", "rm"]),
        path,
    )


# -- config YAML ---------------------------------------------------------------------------------------


@lru_cache
def _config_seed() -> str:
    return (REPO / "config" / "config.yaml").read_text()


@given(
    st.one_of(
        damaged_tokens(_config_seed()),
        damaged_lines(_config_seed(), cell_sep=": "),
        damaged_bytes(_config_seed().encode(), max_ops=2),
    )
)
def test_fuzz_config_yaml(text):
    from flylib.config import Config

    path = _write("config_fuzz.yaml", text)
    # a ConfigError may list several problems, one per line under a first line naming the file
    _check(Config.from_file, path, multiline_ok=True)
    assert not (WORK / "pwned").exists() and not Path("pwned").exists()


def test_config_error_type_is_a_flylib_error():
    assert issubclass(ConfigError, FlylibError)


# -- results.h5 and stage artifacts ----------------------------------------------------------------------


@lru_cache
def _results_seeds() -> tuple[bytes, bytes]:
    from flylib.camera.rig import CameraGroup
    from flylib.results import PoseResult, write_stage
    from flylib.skeleton import Skeleton

    views = ["a", "b", "c"]
    skeleton = Skeleton(
        point_names=("p0", "p1", "p2"), limbs={"leg": ("p0", "p1", "p2")}, palette={}, name="t"
    )
    cameras = CameraGroup.from_arrays(
        views,
        np.array([[0.0, a, 0.0] for a in (-0.5, 0.0, 0.5)]),
        np.tile([0.0, 0.0, 110.0], (3, 1)),
        np.tile([16000.0, 16000.0, 480.0, 240.0], (3, 1)),
        np.zeros((3, 5)),
    )
    rng = np.random.default_rng(2)
    pts3d = rng.normal(scale=2.0, size=(6, 3, 3))
    pts2d = cameras.project(pts3d)
    result = PoseResult(
        cameras=cameras,
        skeleton=skeleton,
        pts2d=pts2d,
        conf=np.ones(pts2d.shape[:3]),
        pts3d=pts3d,
        reproj_error=np.zeros(pts2d.shape[:3]),
        image_sizes={v: (480, 960) for v in views},
    )
    result.save(WORK / "results_seed.h5")
    write_stage(
        WORK / "stage_seed.h5",
        "triangulation",
        {"points": pts2d, "points3d": pts3d},
        cameras=cameras,
        attrs={"summary": "{}"},
    )
    return (WORK / "results_seed.h5").read_bytes(), (WORK / "stage_seed.h5").read_bytes()


@given(st.data())
def test_fuzz_results_h5(data):
    from flylib.results import (
        Pose2dData,
        PoseResult,
        read_cameras,
        read_skeleton,
        read_stage,
    )

    results, stage = _results_seeds()
    path = _write("results_fuzz.h5", data.draw(damaged_h5(results)))
    for load in (
        PoseResult.load,
        Pose2dData.load,
        read_skeleton,
        lambda p: read_cameras(p, "pose2d"),
    ):
        _check(load, path)
    path = _write("stage_fuzz.h5", data.draw(damaged_h5(stage)))
    _check(lambda p: read_stage(p, "triangulation"), path)
