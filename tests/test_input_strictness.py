"""Input never silently dropped or read loosely: a conditions CSV's columns and numbers (plain
ASCII numbers only; every column one the reader takes; type and type_name agreeing), a sensor
file's tables and types, a negative type index named as an index."""

import numpy as np
import pytest

from apcg_core.catalog import Catalog
from apcg_core.errors import InputError
from apcg_core.families import ModelTypes, conditions_from_csv
from apcg_core.sensor.params import PRESET_DIR, load_sensor

HEAD = "type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"


@pytest.fixture(scope="module")
def model():
    return ModelTypes()


@pytest.mark.parametrize("value", ["1_0", "\u0663", "\uff13", "0x10", "1e", "."])
def test_only_plain_ascii_numbers_are_numbers(model, tmp_path, value):
    f = tmp_path / "c.csv"
    f.write_text(HEAD + f"A320neo,4500,3,{value},0,0\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"line 2, column pitch_deg \(D\): .* is not a number; "
                                         "accepted: a plain decimal number"):
        conditions_from_csv(f, model)
    from apcg_core.io.csv_table import parse_number
    with pytest.raises(ValueError):
        parse_number(value)


@pytest.mark.parametrize("value,number", [("12", 12.0), ("-3.5", -3.5), ("+.5", 0.5),
                                          ("1.2e3", 1200.0), (" 5. ", 5.0), ("1E-2", 0.01)])
def test_plain_numbers_are_read(value, number):
    from apcg_core.io.csv_table import parse_number
    assert parse_number(value) == number


def test_an_unknown_column_is_refused_naming_the_accepted_ones(model, tmp_path):
    f = tmp_path / "c.csv"
    f.write_text(HEAD.strip() + ",note\nA320neo,4500,3.4,2,0,0,first\n")
    with pytest.raises(InputError, match=r"line 1, column note \(G\): a conditions CSV has no "
                                         r"column 'note'; accepted columns: type,range_m,"):
        conditions_from_csv(f, model)


def test_a_datasets_own_columns_are_read(model, tmp_path):
    f = tmp_path / "conditions.csv"
    f.write_text("sample_id,split,shard,type_code,type_name,range_m,elevation_deg,pitch_deg,"
                 "yaw_deg,roll_deg\n0,train,0,9,A320neo,4500,3.4,2.3,13.2,0.13\n")
    assert conditions_from_csv(f, model).names == ["A320neo"]


def test_type_and_type_name_must_agree(model, tmp_path):
    f = tmp_path / "c.csv"
    head = "type,type_name,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"
    f.write_text(head + "A320neo,A320neo,4500,3,2,0,0\nA320neo,737-800,4500,3,2,0,0\n")
    with pytest.raises(InputError, match=r"line 3, column type \(A\): 'A320neo' and type_name "
                                         r"'737-800' name different types"):
        conditions_from_csv(f, model)
    f.write_text(head + "A320neo,A320neo,4500,3,2,0,0\n")
    c = conditions_from_csv(f, model)
    assert c.names == ["A320neo"]
    np.testing.assert_allclose(c.table[0, 1], 4500)


def _sensor_text() -> str:
    return (PRESET_DIR / "1550nm-night.toml").read_text()


@pytest.mark.parametrize("extra,words", [
    ("\n[lidar]\nname = \"x\"\n", "holds a [lidar] table, which a sensor file does not take: "
                                  "give the file to --lidar"),
    ("\n[extra]\na = 1\n", "table [extra] unknown in a sensor file")])
def test_a_sensor_file_with_other_tables_is_refused(tmp_path, extra, words):
    f = tmp_path / "s.toml"
    f.write_text(_sensor_text() + extra)
    with pytest.raises(InputError, match=words.replace("[", r"\[").replace("]", r"\]")):
        load_sensor(f)
    f.write_text(_sensor_text())
    assert load_sensor(f).name == "1550nm-night"


def test_a_sensor_name_must_be_text(tmp_path):
    f = tmp_path / "s.toml"
    text = _sensor_text()
    assert 'name = "1550nm-night"' in text
    f.write_text(text.replace('name = "1550nm-night"', "name = 5"))
    with pytest.raises(InputError, match="sensor value name in .* must be text .*got 5"):
        load_sensor(f)


@pytest.mark.parametrize("key", ["-1", "-0042", "+7000"])
def test_a_signed_type_index_is_named_as_an_index(key):
    with pytest.raises(InputError, match=f"unknown type index {int(key)}; accepted: 0 .. "):
        Catalog(include_user=False).get(key)
