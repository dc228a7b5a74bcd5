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
    ("A320neo,nan,3.4,2,0,0", r"c.csv, line 3, column range_m \(B\): 'nan' is not a finite"),
    ("A320neo,-5,3.4,2,0,0", r"line 3, column range_m \(B\): '-5' .*range_m = -5"),
    ("A320neo,4500,90,2,0,0", r"line 3, column elevation_deg \(C\): '90' .*elevation = 90 deg"),
    ("A320neo,4500,3.4,2,200,0", r"line 3, column yaw_deg \(E\): '200' .*yaw"),
    ("A320neo,4500,3.4,x,0,0", r"line 3, column pitch_deg \(D\): 'x' is not a number"),
    ("A320neo,4500,3.4,,0,0", r"line 3, column pitch_deg \(D\): '' is empty"),
    ("A320neo,4500,3.4,2", r"line 3: 4 values, the header \(line 1\) has 6 columns: no value "
                           "for yaw_deg, roll_deg"),
    ("A320neo,4500,3.4,2,0,0,7", r"line 3, column G: '7' lies past the header's last column"),
    ('A320neo,"3,5",3.4,2,0,0', r"line 3, column range_m \(B\): '3,5' is not a number \(use a "
                                "point"),
    ("No Such Jet,4500,3.4,2,0,0", r"line 3, column type \(A\): 'No Such Jet'"),
    # physically fine, outside the model's condition space: named the same way
    ("A320neo,4500,3.4,2,0,40", r"line 3, column roll_deg \(F\): '40': roll = 40 deg is "
                                "outside the configured range"),
    ("Mavic 3,5000,3.4,2,0,0", r"line 3, column range_m \(B\): '5000': range_m = 5000 m"),
])
def test_bad_rows_are_refused_by_line_column_and_value(model, tmp_path, row, words):
    """The line as an editor shows it (the header is line 1), the column by its name and its
    spreadsheet letter, and the value (not a data-row count, not Python's float() words)."""
    f = tmp_path / "c.csv"
    f.write_text(HEAD + "A320neo,4500,3.4,2,0,0\n" + row + "\n")
    with pytest.raises(InputError, match=words):
        conditions_from_csv(f, model)


@pytest.mark.parametrize("how", ["bom", "crlf", "quoted", "blank lines", "spaces", "all"])
def test_a_csv_as_spreadsheets_and_editors_save_it_is_read(model, tmp_path, how):
    """A byte-order mark ("CSV UTF-8"), CRLF, quoted fields, trailing empty lines (and rows
    of empty cells), spaces around values: the same conditions as the plain file."""
    plain = HEAD + "A320neo,4500,3.4,2.3,13.2,0.13\nMavic 3,250,3.1,1.5,-20,2\n"
    text = plain
    if how in ("quoted", "all"):
        text = text.replace("A320neo,4500", '"A320neo","4500"').replace("Mavic 3", '"Mavic 3"')
    if how in ("spaces", "all"):
        text = text.replace(",", " , ").replace("type", " type")
    if how in ("blank lines", "all"):
        text = text + "\n,,,,,\n\n\n"
    if how in ("crlf", "all"):
        text = text.replace("\n", "\r\n")
    data = text.encode()
    if how in ("bom", "all"):
        data = b"\xef\xbb\xbf" + data
    (tmp_path / "plain.csv").write_text(plain)
    (tmp_path / "c.csv").write_bytes(data)
    want = conditions_from_csv(tmp_path / "plain.csv", model)
    got = conditions_from_csv(tmp_path / "c.csv", model)
    assert got.names == want.names
    np.testing.assert_array_equal(got.table, want.table)


def test_a_line_break_inside_quotes_keeps_the_line_numbers_true(model, tmp_path):
    f = tmp_path / "c.csv"
    f.write_text(HEAD + '"A320neo",4500,3.4,2,0,0\n"Mavic\nX",250,3,1,0,0\nA320neo,4500,3,2,0,0\n')
    with pytest.raises(InputError, match=r"line 3, column type \(A\): 'Mavic\\nX'"):
        conditions_from_csv(f, model)
    f.write_text(HEAD + '"A320neo",4500,3.4,2,0,0\n"Mavic\n3",250,3,1,0,0\nA320neo,x,1,1,0,0\n')
    with pytest.raises(InputError, match=r"line 5, column range_m \(B\): 'x'"):
        conditions_from_csv(f, model)  # numbers are read before types: the line after it
    f.write_text(HEAD + '"A320 neo note\nspanning",4500,3.4,2,0,0\nA320neo,x,1,1,0,0\n')
    with pytest.raises(InputError, match=r"line (2|4)"):
        conditions_from_csv(f, model)


def test_missing_columns_and_empty_files(model, tmp_path):
    f = tmp_path / "c.csv"
    f.write_text("type,range_m\nA320neo,4500\n")
    with pytest.raises(InputError, match=r"c.csv, line 1: the header has no column "
                                         "elevation_deg, pitch_deg, yaw_deg, roll_deg"):
        conditions_from_csv(f, model)
    f.write_text(HEAD)
    with pytest.raises(InputError, match="no conditions"):
        conditions_from_csv(f, model)
    f.write_bytes(b"")
    with pytest.raises(InputError, match="c.csv: the file is empty") as empty:
        conditions_from_csv(f, model)
    # the header it asks for is one the reader takes: the type column included
    assert "header type|type_name,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg " \
        in str(empty.value)
    f.write_bytes(b"\xef\xbb\xbf\r\n\r\n")
    with pytest.raises(InputError, match="c.csv: the file is empty"):
        conditions_from_csv(f, model)
    f.write_bytes(HEAD.encode() + b"A320neo,4500,3.4,2,0,0\nA320\xe9,1,1,1,1,1\n")
    with pytest.raises(InputError, match=r"c.csv, line 3: byte 0xe9 is not UTF-8"):
        conditions_from_csv(f, model)
    f.write_text("\ufeff" + HEAD, encoding="utf-16")
    with pytest.raises(InputError, match="UTF-16"):
        conditions_from_csv(f, model)
    f.write_text(HEAD.replace("pitch_deg", "range_m"))
    with pytest.raises(InputError, match=r"line 1, column D: the column name 'range_m' "
                                         "appears twice"):
        conditions_from_csv(f, model)


@pytest.mark.parametrize("text", [
    HEAD + "A320neo,4500,3.4,2.3,13.2,0.13\nMavic 3,250,3.1,1.5,-20,2\n",
    "\ufeff" + HEAD.replace("\n", "\r\n") + "A320neo, 4500 ,3.4,2.3,13.2,0.13\r\n\r\n"
    '"Mavic 3",250,3.1,1.5,-20,2,,\r\n,,,,,\r\n',  # BOM, CRLF, quotes, spaces, blank rows
    "Roll_deg,yaw_deg,pitch_deg,elevation_deg,range_m,type\n"
    "0.13,13.2,2.3,3.4,4500,A320neo\n2,-20,1.5,3.1,250,Mavic 3\n",  # any column order
    "sample_id,split,shard,type_code,type_name,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"
    "0,train,0,9,A320neo,4500,3.4,2.3,13.2,0.13\n1,test,0,1,Mavic 3,250,3.1,1.5,-20,2\n",
])
def test_the_fast_reader_reads_what_the_careful_one_does(model, tmp_path, text):
    """A plain file is read column by column (10^6 rows in seconds); whatever it reads, the
    careful row-by-row reader reads the same (and it takes every file the fast one will not)."""
    from apcg_core import condition
    f = tmp_path / "c.csv"
    f.write_bytes(text.encode())
    fast = condition._read_conditions_fast(f, model.type_name)
    names, pose, _ = condition._read_conditions_careful(f, model.type_name)
    assert fast is not None
    assert fast[0] == names == ["A320neo", "Mavic 3"]
    assert fast[1].tobytes() == pose.tobytes()


def test_the_fast_reader_leaves_a_bad_row_to_the_careful_one(model, tmp_path):
    from apcg_core import condition
    f = tmp_path / "c.csv"
    f.write_text(HEAD + "A320neo,4500,3.4,2,0,0\n" * 3 + "A320neo,4500,3.4,,0,0\n")
    assert condition._read_conditions_fast(f, model.type_name) is None
    with pytest.raises(InputError, match=r"line 5, column pitch_deg \(D\): '' is empty"):
        conditions_from_csv(f, model)
