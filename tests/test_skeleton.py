"""Skeleton: the 38-point fly, limb chains, bones, limb ids, validation, array round-trip."""

from __future__ import annotations

import numpy as np
import pytest

from flylib.errors import ConfigError
from flylib.skeleton import Skeleton, skeleton_problems


@pytest.fixture(scope="module")
def fly() -> Skeleton:
    return Skeleton.fly()


def test_fly_has_38_points_10_limbs_and_28_bones(fly):
    assert fly.name == "fly38"
    assert fly.n_points == len(fly) == 38
    assert fly.n_limbs == 10
    # six 5-joint legs (4 bones each) + two 3-point abdomens (2 each); antennae have none
    assert fly.n_bones == 6 * 4 + 2 * 2 == 28
    assert fly.point_names[0] == "lf_thorax_coxa"
    assert fly.point_names[19] == "rf_thorax_coxa"
    assert fly.index("rf_claw") == 23
    assert fly.index("r_abdomen2") == 37


def test_fly_bones_follow_each_limb_chain(fly):
    bones = [tuple(b) for b in fly.bones.tolist()]
    assert bones[:4] == [(0, 1), (1, 2), (2, 3), (3, 4)]  # lf leg, body to claw
    assert (16, 17) in bones and (17, 18) in bones  # l_abdomen0 -> 1 -> 2
    assert not any(15 in b for b in bones)  # l_antenna is a single-point limb
    i, j = fly.bone_index_pairs()
    # every bone joins two points of the same limb
    assert np.all(fly.limb_id[i] == fly.limb_id[j])


def test_fly_limb_id_and_palette(fly):
    assert fly.limb_id.shape == (38,)
    assert fly.limb_names[fly.limb_id[fly.index("rm_claw")]] == "rm_leg"
    assert fly.limb_names[fly.limb_id[fly.index("l_antenna")]] == "l_antenna"
    assert np.bincount(fly.limb_id).tolist() == [5, 5, 5, 1, 3, 5, 5, 5, 1, 3]
    assert fly.palette["rf_leg"] == "#ba1e31"
    assert fly.limb_color("lf_leg") == "#0f7399"
    assert fly.limb_color("nope", default="#000000") == "#000000"


def test_derived_arrays_are_read_only(fly):
    with pytest.raises(ValueError):
        fly.bones[0, 0] = 5
    with pytest.raises(ValueError):
        fly.limb_id[0] = 3


def test_point_outside_every_limb_has_limb_id_minus_one():
    sk = Skeleton(point_names=("a", "b", "c"), limbs={"arm": ("a", "b")})
    assert sk.limb_id.tolist() == [0, 0, -1]
    assert sk.bones.tolist() == [[0, 1]]


def test_index_of_unknown_point_lists_known_points(fly):
    with pytest.raises(KeyError, match="unknown point 'rf_femurr'.*lf_thorax_coxa"):
        fly.index("rf_femurr")


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (
            {"point_names": ["a", "b"], "limb_points": {"arm": ["a", "bb"]}},
            "skeleton.limb_points.arm: unknown point 'bb' (known: a, b)",
        ),
        (
            {"point_names": ["a", "b", "c"], "limb_points": {"x": ["a", "b"], "y": ["b", "c"]}},
            "skeleton.limb_points.y: point 'b' already belongs to limb 'x'",
        ),
        ({"point_names": ["a", "a"]}, "skeleton.point_names: point 'a' is listed twice"),
        ({"point_names": []}, "skeleton.point_names: expected a non-empty list"),
        (
            {"point_names": ["a"], "limb_points": {"x": ["a"]}, "limb_palette": {"x": "red"}},
            "skeleton.limb_palette.x: expected a hex colour",
        ),
        (
            {"point_names": ["a"], "limb_points": {"x": ["a"]}, "limb_palette": {"z": "#ffffff"}},
            "skeleton.limb_palette.z: unknown limb 'z'",
        ),
        ({"point_names": ["a"], "limbs": {}}, "skeleton.limbs: unknown key"),
    ],
)
def test_invalid_skeleton_tables_name_the_key(spec, message):
    assert any(message in p for p in skeleton_problems(spec))
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Skeleton.from_spec(spec)


def test_from_arrays_recovers_chain_order_not_index_order():
    sk = Skeleton(
        point_names=("tip", "base", "mid", "lone"),
        limbs={"arm": ("base", "mid", "tip"), "solo": ("lone",)},
        palette={"arm": "#123456"},
        name="toy",
    )
    assert sk.bones.tolist() == [[1, 2], [2, 0]]
    back = Skeleton.from_arrays(
        sk.point_names, sk.limb_names, sk.limb_id, sk.bones, sk.palette, sk.name
    )
    assert back == sk
    assert back.limbs["arm"] == ("base", "mid", "tip")


def test_fly_round_trips_through_arrays(fly):
    back = Skeleton.from_arrays(
        fly.point_names, fly.limb_names, fly.limb_id, fly.bones, fly.palette, fly.name
    )
    assert back == fly
    assert back != Skeleton(point_names=fly.point_names)
