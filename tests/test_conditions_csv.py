"""`apcg generate --conditions CSV`: the file's rows become conditions in the model's types, by
name; a dataset's conditions.csv is read as it is; every bad row is refused by its number."""

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.families import ModelTypes, conditions_from_csv

HEAD = "type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"


@pytest.fixture
def model():
    return ModelTypes()  # the shipped default's types and condition space


def test_rows_become_conditions_by_name(model, tmp_path):
    f = tmp_path / "c.csv"
    f.write_text(HEAD + "A320neo,4500,3.4,2.3,13.2,0.13\nMavic 3,250,3.1,1.5,-20,2\n")
    c = conditions_from_csv(f, model)
    assert c.names == ["A320neo", "Mavic 3"]
    np.testing.assert_allclose(c.table[:, 1:], [[4500, *np.radians([3.4, 2.3, 13.2, 0.13])],
                                                [250, *np.radians([3.1, 1.5, -20, 2])]])


def test_a_datasets_conditions_csv_is_read_as_it_is(model, tiny_training_data):
    c = conditions_from_csv(tiny_training_data / "conditions.csv", model)
    rows = (tiny_training_data / "conditions.csv").read_text().strip().splitlines()[1:]
    assert len(c.table) == len(rows)
    first = rows[0].split(",")
    assert c.names[0] == first[4] and c.table[0, 1] == pytest.approx(float(first[5]))


@pytest.mark.parametrize("row,words", [
    ("A320neo,nan,3.4,2,0,0", "row 2: range_m must be finite"),
    ("A320neo,-5,3.4,2,0,0", "row 2: range_m = -5"),
    ("A320neo,4500,90,2,0,0", "row 2: elevation = 90 deg"),
    ("A320neo,4500,3.4,2,200,0", "row 2: yaw"),
    ("A320neo,4500,3.4,x,0,0", "row 2: could not convert"),
    ("No Such Jet,4500,3.4,2,0,0", "row 2: .*No Such Jet"),
])
def test_bad_rows_are_refused_by_number(model, tmp_path, row, words):
    f = tmp_path / "c.csv"
    f.write_text(HEAD + "A320neo,4500,3.4,2,0,0\n" + row + "\n")
    with pytest.raises(InputError, match=words):
        conditions_from_csv(f, model)


def test_missing_columns_and_empty_files(model, tmp_path):
    f = tmp_path / "c.csv"
    f.write_text("type,range_m\nA320neo,4500\n")
    with pytest.raises(InputError, match="needs the header"):
        conditions_from_csv(f, model)
    f.write_text(HEAD)
    with pytest.raises(InputError, match="no conditions"):
        conditions_from_csv(f, model)
