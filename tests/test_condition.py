import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from apcg_core.condition import (
    Condition,
    ConditionSpace,
    reference_range_m,
    scale_ratio,
)
from apcg_core.errors import InputError

DEG = math.pi / 180
SPACE = ConditionSpace(n_types=80, drone_types=(76, 77, 78, 79))


def test_table1_defaults():
    d = SPACE.to_dict()
    assert d["aircraft_range_m"] == [3000.0, 18000.0]
    assert d["drone_range_m"] == [100.0, 600.0]
    assert d["elevation_deg"] == pytest.approx([3, 4])
    assert d["pitch_deg"] == pytest.approx([1, 5])
    assert d["yaw_deg"] == pytest.approx([-60, 60])
    assert d["roll_deg"] == pytest.approx([-5, 5])
    n = SPACE.n_types
    for v in SPACE.counts.values():
        n *= v
    assert n == 10**6
    assert ConditionSpace.from_dict(d) == SPACE


@given(t=st.integers(0, 79), u=st.lists(st.floats(0, 1), min_size=5, max_size=5))
def test_nu_round_trip(t, u):
    lo, hi = SPACE.range_bounds(t)
    row = [t, lo + u[0] * (hi - lo)]
    for name, f in zip(("elevation", "pitch", "yaw", "roll"), u[1:], strict=True):
        a, b = getattr(SPACE, name)
        row.append(a + f * (b - a))
    row = np.array(row)
    nu = SPACE.encode(row[None])[0]
    assert ((nu >= -1) & (nu <= 1)).all()
    back = SPACE.decode(nu)[0]
    assert back[0] == t
    np.testing.assert_allclose(back[1:], row[1:], rtol=1e-12, atol=1e-12)


def test_nu_ends_and_drone_range():
    c = Condition.from_degrees(79, 600.0, 4.0, 5.0, 60.0, 5.0)
    np.testing.assert_allclose(SPACE.encode(c), [1, 1, 1, 1, 1, 1])
    c = Condition.from_degrees(0, 3000.0, 3.0, 1.0, -60.0, -5.0)
    np.testing.assert_allclose(SPACE.encode(c), [-1, -1, -1, -1, -1, -1])
    d = SPACE.decode_one(SPACE.encode(c))
    assert d.type_index == 0 and d.range_m == pytest.approx(3000.0)


def test_out_of_range_names_field_and_range():
    with pytest.raises(InputError, match=r"range_m = 2000 m .*\[3000 m, 18000 m\]"):
        SPACE.encode(Condition.from_degrees(0, 2000.0, 3.5, 2, 0, 0))
    with pytest.raises(InputError, match=r"range_m = 2000 m .*\[100 m, 600 m\]"):
        SPACE.encode(Condition.from_degrees(77, 2000.0, 3.5, 2, 0, 0))
    with pytest.raises(InputError, match=r"yaw = 61 deg .*\[-60 deg, 60 deg\]"):
        SPACE.encode(Condition.from_degrees(0, 5000.0, 3.5, 2, 61, 0))
    with pytest.raises(InputError, match=r"type_index = 80.0 .*0 \.\. 79"):
        SPACE.encode(np.array([[80, 5000.0, 3.5 * DEG, 0.03, 0, 0]]))


@pytest.mark.parametrize("field,kwargs", [
    ("range_m", dict(range_m=float("nan"))),
    ("elevation", dict(elevation=float("nan"))),
    ("pitch", dict(pitch=float("inf"))),
    ("yaw", dict(yaw=float("nan"))),
    ("roll", dict(roll=float("-inf"))),
])
def test_nan_is_refused_naming_the_field(field, kwargs):
    base = dict(type_index=0, range_m=5000.0, elevation=0.06)
    base.update(kwargs)
    with pytest.raises(InputError, match=field):
        Condition(**base)


@pytest.mark.parametrize("b0,said", [(90.0, "overhead"), (-90.0, "straight below"),
                                     (95.0, "overhead"), (-95.0, "straight below")])
def test_overhead_is_refused_clearly(b0, said):
    with pytest.raises(InputError, match=said):
        Condition.from_degrees(0, 5000.0, b0)


def test_physical_limits():
    with pytest.raises(InputError, match="range_m"):
        Condition(0, 0.0, 0.05)
    with pytest.raises(InputError, match=r"pitch = 91 deg"):
        Condition.from_degrees(0, 5000.0, 3, pitch_deg=91)
    with pytest.raises(InputError, match="type_index"):
        Condition(-1, 5000.0, 0.05)
    with pytest.raises(InputError, match="type_index"):
        Condition(True, 5000.0, 0.05)
    with pytest.raises(InputError, match="type_index"):
        Condition.from_array([1.5, 5000.0, 0.05, 0, 0, 0])


def test_reference_range_rule():
    assert reference_range_m(3000.0) == 3000.0  # exactly 3 km: >=, not the paper's >
    assert scale_ratio(3000.0) == 1.0
    assert reference_range_m(2999.999) == 100.0
    assert scale_ratio(18000.0) == 6.0
    assert scale_ratio(550.0) == 5.5
    assert scale_ratio(50.0) == 0.5  # q < 1 for targets nearer than 100 m
    np.testing.assert_allclose(scale_ratio(np.array([50.0, 3000.0, 9000.0])), [0.5, 1.0, 3.0])
    c = Condition.from_degrees(0, 4500.0, 3.4)
    assert c.q == 1.5 and c.reference_range_m == 3000.0


def test_condition_array_round_trip():
    c = Condition.from_degrees(12, 4500.0, 3.4, 2.3, 13.2, 0.13)
    assert Condition.from_array(c.as_array()) == c
    d = c.to_degrees()
    assert d["yaw_deg"] == pytest.approx(13.2)


def test_check_int_accepts_whole_numbers_in_range_only():
    from apcg_core.errors import check_int
    assert check_int("n", np.int64(5), 1) == 5 and type(check_int("n", np.int64(5), 1)) is int
    assert check_int("n", 3, 1, 3) == 3
    for bad in (0, 4, 2.0, True, "2", None, float("nan")):
        with pytest.raises(InputError, match=r"n must be an integer in 1\.\.3 \(why\), got "):
            check_int("n", bad, 1, 3, hint=" (why)")
    with pytest.raises(InputError, match="count must be an integer >= 1, got -1"):
        check_int("count", -1, 1)


def test_generation_refuses_a_bad_count_for_every_model_kind():
    from apcg_core.families import load_model
    model = load_model(runtime="onnx")
    row = model.condition("A320neo", 4500.0, math.radians(3.4), math.radians(2.3),
                          math.radians(13.2), 0.0)
    assert model.repeated_conditions(row, 3).shape == (3, 6)
    for bad in (0, 1.5, True):
        with pytest.raises(InputError, match="count must be an integer >= 1"):
            model.generate(row, count=bad)


def test_a_bad_row_beyond_the_first_block_is_named_by_its_own_row(monkeypatch):
    """check() works in blocks of CHECK_ROWS rows: a value out of range (or NaN) in a later
    block is still named with its row in the whole table."""
    import apcg_core.condition as condition
    monkeypatch.setattr(condition, "CHECK_ROWS", 7)
    space = ConditionSpace()
    table = space.decode(np.zeros((30, 6)))
    assert space.check(table) is not None
    for bad, says in ((np.nan, "must be finite"), (1e6, "outside the configured range")):
        t = table.copy()
        t[23, 1] = bad
        with pytest.raises(InputError, match=f"row 23: range_m.*{says}"):
            space.check(t)


def test_a_range_refusal_says_which_band_the_type_is_in():
    space = ConditionSpace(n_types=3, drone_types=(2,))
    with pytest.raises(InputError, match=r"\(the aircraft band: this type is not one of"):
        space.check([[1, 300.0, np.radians(3.5), np.radians(2), 0, 0]])
    with pytest.raises(InputError, match=r"\(the drone band: this type is one of"):
        space.check([[2, 5000.0, np.radians(3.5), np.radians(2), 0, 0]])
    # a table without drones has one band: nothing to tell
    with pytest.raises(InputError, match=r"18000 m\]$"):
        ConditionSpace(n_types=3).check([[1, 300.0, np.radians(3.5), np.radians(2), 0, 0]])


@given(st.floats(-180, 180, allow_nan=False))
def test_degrees_shown_are_the_shortest_that_give_the_radians(deg):
    from apcg_core.condition import degrees_of
    from apcg_core.lidar import DEG
    rad = deg * DEG
    shown = degrees_of(rad)
    assert shown * DEG == rad
    assert len(repr(shown)) <= len(repr(deg))  # never longer than the value given
    assert degrees_of(60 * DEG) == 60.0 and 60 * DEG / DEG != 60.0
