"""Small files that would make a loader allocate without bound: DeepFly3D
pickles (shared, deep, cyclic structures; constructors asked for huge sizes; declared
lengths beyond the file) and DeepLabCut CSVs with millions of columns. Each is one
``ImportFormatError`` line naming the file, raised before anything large is built."""

from __future__ import annotations

import pickle
import struct

import numpy as np
import pytest

from flylib.errors import ImportFormatError
from flylib.interop import read_df3d_points2d, read_dlc_csv, safe_pickle
from flylib.interop.safe_pickle import load_restricted

SIZES = [(480, 960)] * 7
_reconstruct = pytest.importorskip("numpy._core.multiarray")._reconstruct


def _refused(tmp_path, data: bytes, *fragments: str, load=None) -> str:
    path = tmp_path / "df3d_result_bomb.pkl"
    path.write_bytes(data)
    with pytest.raises(ImportFormatError) as err:
        (load or (lambda p: read_df3d_points2d(p, SIZES)))(path)
    text = str(err.value)
    assert "\n" not in text and text.startswith(str(path)), text
    for fragment in fragments:
        assert fragment in text, text
    return text


def _shared_nested(levels: int, width: int = 16) -> list:
    x = [1.0, 1.0]
    for _ in range(levels):
        x = [x] * width
    return x


def test_shared_nested_lists_of_the_probe_are_refused(tmp_path):
    """The probe's case: a few hundred bytes that np.asarray would expand to 7.8 GB."""
    data = pickle.dumps({"points2d": _shared_nested(7)}, protocol=2)
    assert len(data) < 400
    _refused(tmp_path, data, "expands to more than 268435456 values")


def test_expansion_limit_counts_the_tree_not_the_objects(tmp_path, monkeypatch):
    """5 distinct lists, a tree of 200,979 values (131,072 numbers, 69,905 lists, the
    dict and its key): loaded at exactly that limit, refused one below it."""
    data = pickle.dumps({"points2d": _shared_nested(4)}, protocol=4)
    path = tmp_path / "x.pkl"
    path.write_bytes(data)
    monkeypatch.setattr(safe_pickle, "MAX_EXPANDED_VALUES", 200_979)
    assert np.asarray(load_restricted(path, "test")["points2d"]).size == 131_072
    monkeypatch.setattr(safe_pickle, "MAX_EXPANDED_VALUES", 200_978)
    _refused(
        tmp_path,
        data,
        "expands to more than 200978 values",
        load=lambda p: load_restricted(p, "test"),
    )


def test_nesting_100000_deep_is_refused(tmp_path):
    n = 100_000
    data = b"\x80\x02}X\x08\x00\x00\x00points2d" + b"]" * (n + 1) + b"a" * n + b"s."
    _refused(tmp_path, data, "nested more than 32 levels deep")


def test_a_list_holding_itself_is_refused(tmp_path):
    cycle: list = []
    cycle.append(cycle)
    _refused(tmp_path, pickle.dumps({"points2d": cycle}), "reference cycle")


def test_declared_length_beyond_the_file_is_refused_without_allocating(tmp_path):
    """BINBYTES8 declaring 1 TiB: the C unpickler would allocate it before reading."""
    data = b"\x80\x04\x8e" + struct.pack("<Q", 1 << 40) + b"abc."
    _refused(tmp_path, data, "not a readable DeepFly3D 2D result pickle", "1099511627776")


class _Call:
    """Pickles as ``func(*args)`` (a REDUCE of an admitted global)."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


@pytest.mark.parametrize(
    ("call", "fragment"),
    [
        # the admitted type itself, called: an 80 GB allocation
        (_Call(np.ndarray, (10**10,)), "shape (10000000000,) and dtype float64"),
        (_Call(np.ndarray, (10**5,), np.dtype(("f8", (10**5,)))), "dtype ('<f8', (100000,))"),
        (_Call(_reconstruct, np.ndarray, (10**10,), b"b"), "(10000000000,)"),
        (_Call(bytes, 10**12), "(1000000000000,)"),
        (_Call(bytearray, 10**12), "(1000000000000,)"),
    ],
    ids=["ndarray", "ndarray-subarray-dtype", "_reconstruct", "bytes", "bytearray"],
)
@pytest.mark.parametrize("protocol", [2, 4])
def test_admitted_constructors_asked_for_huge_sizes_are_refused(tmp_path, call, fragment, protocol):
    _refused(tmp_path, pickle.dumps({"points2d": call}, protocol=protocol), fragment)


def test_str_of_a_shared_structure_is_refused(tmp_path):
    """str() of nested shared lists prints the whole expansion."""
    inner = pickle.dumps(_shared_nested(7), protocol=2)[2:-1]
    data = b"\x80\x02c__builtin__\nstr\n(" + inner + b"tR."
    _refused(tmp_path, data, "str() of a list")


def test_plain_data_and_arrays_still_load(tmp_path):
    value = {
        "points2d": np.random.default_rng(0).uniform(size=(7, 3, 38, 2)),
        "l": [b"x", bytearray(b"y"), "z", 3, (1.0, None)],
    }
    for protocol in (0, 2, 5):
        path = tmp_path / f"ok{protocol}.pkl"
        path.write_bytes(pickle.dumps(value, protocol=protocol))
        back = load_restricted(path, "test")
        np.testing.assert_array_equal(back["points2d"], value["points2d"])
        assert back["l"] == value["l"]


# -- config files and JSON nested without bound -------------------------------------------------

NESTED = {
    "flow-100000.yaml": lambda: "pose2d: " + "[" * 100_000 + "]" * 100_000,
    "flow-900.yaml": lambda: "pose2d: " + "[" * 900 + "]" * 900,
    "block-2000.yaml": lambda: (
        "".join(" " * i + "k:\n" for i in range(2000)) + " " * 2000 + "v: 1\n"
    ),
    "self-alias.yaml": lambda: "pose2d: &x [*x]\n",
    "laughs.yaml": lambda: (
        "a: &a [x, x, x, x, x, x, x, x, x, x]\n"
        + "".join(
            f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join([f'*{chr(97 + i)}'] * 10)}]\n"
            for i in range(8)
        )
    ),
    "inline-100000.toml": lambda: "a = " + "[" * 100_000 + "]" * 100_000,
    "inline-tables-900.toml": lambda: "a = " + "{x = " * 900 + "1" + "}" * 900,
    "dotted-100000.toml": lambda: "a" + ".a" * 100_000 + " = 1\n",
    "header-100000.toml": lambda: "[a" + ".a" * 100_000 + "]\nx = 1\n",
}


@pytest.mark.parametrize("name", sorted(NESTED))
def test_check_config_on_deep_nesting_is_one_line(tmp_path, capsys, name):
    from flylib.cli import main

    path = tmp_path / name
    path.write_text(NESTED[name]())
    assert main(["check-config", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(path) in err, err
    assert any(
        what in err
        for what in ("nested more than 64 levels", "contains itself", "expands to more than")
    ) or ("maximum nesting depth" in err and "100000" in name), err


def test_a_config_nested_as_deep_as_the_bound_still_loads(tmp_path):
    from flylib.config.loading import MAX_NESTING, parse_text

    inner = "[" * (MAX_NESTING - 1) + "]" * (MAX_NESTING - 1)
    assert parse_text(f"a: {inner}\n", "yaml", "x")["a"] is not None
    assert parse_text(f"a = {inner}\n", "toml", "x")["a"] is not None
    with pytest.raises(Exception, match="nested more than 64"):
        parse_text(f"a: [{inner}]\n", "yaml", "x")


def test_deep_json_argument_is_one_config_error():
    from flylib.config.loading import parse_json
    from flylib.errors import ConfigError

    assert parse_json('{"format": "dlc_csv", "files": {"rh": "a.csv"}}', "--x")["format"]
    for text in ("[" * 100_000 + "]" * 100_000, "[" * 65 + "]" * 65):
        with pytest.raises(ConfigError, match=r"^--import-spec: (nested|is nested) more than 64"):
            parse_json(text, "--import-spec")


@pytest.mark.parametrize(
    "text", ["[cam_0]\nx = " + "[" * 100_000 + "]" * 100_000, "cam_0" + ".a" * 100_000 + " = 1\n"]
)
def test_deeply_nested_anipose_calibration_is_one_line(tmp_path, text):
    from flylib.interop import read_anipose_toml

    path = tmp_path / "calibration.toml"
    path.write_text(text)
    with pytest.raises(ImportFormatError, match="nested more than 64 levels deep") as err:
        read_anipose_toml(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


# -- DeepLabCut CSV with millions of columns ---------------------------------------------------


@pytest.mark.parametrize("where", ["scorer", "bodyparts", "data"])
def test_dlc_csv_with_3_million_columns_is_one_line(tmp_path, where):
    """The probe's case (3M columns: > 120 s and 3 GB before) in the first header row, a
    later header row, or a data row under a normal header."""
    wide = ",x" * 3_000_000
    head = ["scorer,DLC,DLC,DLC", "bodyparts,head,head,head", "coords,x,y,likelihood"]
    rows = ["0,1,2,0.9"]
    if where == "data":
        rows[0] += wide
    else:
        i = 0 if where == "scorer" else 1
        head[i] += wide
    path = tmp_path / "rh.csv"
    path.write_text("\n".join(head + rows) + "\n")
    with pytest.raises(ImportFormatError) as err:
        read_dlc_csv(path)
    text = str(err.value)
    assert text.startswith(str(path)) and "\n" not in text, text
    if where != "data":
        assert "more than 100000 columns" in text, text


def test_dlc_csv_column_bound_is_exact(tmp_path, monkeypatch):
    from flylib.interop import dlc

    monkeypatch.setattr(dlc, "MAX_CSV_COLUMNS", 301)  # the index column + 100 body parts
    for parts, loads in ((100, True), (101, False)):
        head = [
            "scorer" + ",DLC" * (3 * parts),
            "bodyparts" + "".join(f",p{k},p{k},p{k}" for k in range(parts)),
            "coords" + ",x,y,likelihood" * parts,
        ]
        path = tmp_path / f"rh{parts}.csv"
        path.write_text("\n".join([*head, "0" + ",1,2,0.5" * parts]) + "\n")
        if loads:
            kp = read_dlc_csv(path)
            assert kp.xy.shape == (1, parts, 2) and (kp.xy == [1, 2]).all()
        else:
            with pytest.raises(ImportFormatError, match="line 1 has more than 301 columns"):
                read_dlc_csv(path)


@pytest.mark.parametrize(
    "text",
    [
        "subject:\n" + "".join(" " * (i + 1) + "k:\n" for i in range(600)) + " " * 601 + "v: 1\n",
        "subject: &x {a: *x}\n",
    ],
    ids=["600-deep", "self-alias"],
)
def test_deep_nwb_sidecar_is_one_config_error(tmp_path, text):
    from flylib.config.nwb_metadata import read_sidecar
    from flylib.errors import ConfigError

    path = tmp_path / "nwb.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        read_sidecar(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    assert "nested more than 64" in message or "contains itself" in message, message
