"""The column reader of long CSV files (apcg_core/io/csv_table.read_columns) yields exactly the
rows and values of the careful reader (read_csv), or leaves the file to it (NeedsCare): a plain
file split where its bytes are and parsed by numpy's C reader, anything else through the csv
module, at any block size (a block boundary inside a line, a CRLF, a header)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apcg_core.errors import InputError
from apcg_core.io import csv_table
from apcg_core.io.csv_table import NeedsCare, read_columns, read_csv

COLS = (("type", "type_name"), "range_m", "yaw_deg")
NUMBERS = ("range_m", "yaw_deg")


def careful(path):
    """What read_csv makes of the file, as read_columns gives it (or the InputError)."""
    try:
        table = read_csv(path)
        kind = "type" if "type" in table.header else "type_name"
        return {"type": [r.text(kind) for r in table.rows],
                **{k: [r.float(k, finite=False) for r in table.rows] for k in NUMBERS}}
    except (InputError, KeyError) as exc:  # refused, or a column missing
        return exc


def fast(path, block):
    out = {"type": [], "range_m": [], "yaw_deg": []}
    for batch in read_columns(path, COLS, numbers=NUMBERS, block=block, batch=3):
        for k in out:
            assert isinstance(batch[k], np.ndarray) == (k in NUMBERS)
            if k in NUMBERS:
                assert batch[k].dtype == np.float64
            out[k] += list(batch[k])
    return out


def agree(path):
    """read_columns at several block sizes against read_csv: the same rows, the same float
    bits, or NeedsCare (never a different answer). Returns whether the fast reader read it."""
    want = careful(path)
    answers = set()
    for block in (1, 5, 17, 64, 1 << 20):
        try:
            got = fast(path, block)
        except NeedsCare:
            answers.add("care")
            continue
        answers.add("read")
        assert not isinstance(want, InputError), f"read what read_csv refuses: {want}"
        assert got["type"] == want["type"]
        for k in NUMBERS:
            assert np.array(got[k]).tobytes() == np.array(want[k], np.float64).tobytes()
    assert len(answers) == 1, f"the block size changed the answer: {answers}"
    return answers == {"read"}


HEAD = "type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"
ROWS = "A320neo,4500,3.4,2.3,13.2,0.13\nMavic 3,250,3.1,1.5,-20,2\n"


@pytest.mark.parametrize("text, read", [
    (HEAD + ROWS, True),
    ("\ufeff" + (HEAD + ROWS).replace("\n", "\r\n"), True),  # a spreadsheet's BOM and CRLF
    ("\n\n" + HEAD + "\n" + ROWS + "\n , ,\t,\n,,,,,\n", True),  # blank lines, empty rows
    (HEAD + "  A320neo , 4500 ,\t3.4,2.3, 13.2 ,0.13\n", True),  # outer spaces and tabs
    (HEAD + ROWS.rstrip("\n"), True),  # no last line end
    (HEAD.replace("type,", "TYPE ,") + ROWS, True),  # the header's case and spaces
    ("roll_deg,yaw_deg,note,range_m,type_name\n1,2,x y,3e3,A320neo\n4,5,,6.5,G650ER\n", True),
    (HEAD + "A320neo,1_000,3,2,1,0\n", False),  # not a plain number: refused, never misread
    (HEAD + "A320neo,nan,3,2,inf,0\nA320neo,-0,3,2,1e400,0\n", True),  # any number float() reads
    (HEAD + '"A320neo",4500,3.4,2.3,13.2,0.13\n', True),  # quotes: the csv module
    (HEAD + '"A320, neo",4500,3.4,2.3,13.2,0.13\n', True),
    (HEAD + "A320n\u00e9o,4500,3.4,2.3,13.2,0.13\n", True),  # not ASCII: the csv module
    (HEAD + ROWS + "A320neo,4500,3.4,2.3,13.2,0.13,,\n", True),  # extra empty cells
    (HEAD.rstrip("\n") + ",,\n" + ROWS, True),  # a spreadsheet's empty columns
    (HEAD + ROWS + "A320neo,4500,3.4,2.3,13.2,0.13,x\n", False),  # a value past the header
    (HEAD + ROWS + "A320neo,4500,3.4,2.3,13.2\n", False),  # a short row
    (HEAD + "A320neo,,3.4,2.3,13.2,0.13\n", False),  # an empty wanted cell
    (HEAD + " ,4500,3.4,2.3,13.2,0.13\n", False),
    (HEAD + "A320neo,4500,3.4,2.3,13.2,0.13\rMavic 3,250,3.1,1.5,-20,2\r", True),  # CR alone
    (HEAD + "A320neo,45 00,3.4,2.3,13.2,0.13\n", False),  # not a number
    (HEAD + "A320neo,4500,3.4,2.3,0x10,0.13\n", False),
    (HEAD.replace("yaw_deg", "range_m"), False),  # a name twice
    (HEAD.replace("yaw_deg", "yaw"), False),  # a wanted column missing
    ("\n \n,,\n", False),  # no header
    (HEAD + "A320neo,4500,3.4,2.3,13.2,0.13\x00\n", True),  # a NUL: the csv module
    (HEAD + "A320neo,4500,3.4,2.3,13.2,0.13\x0b\n", True),  # stripped by str.strip
])
def test_every_block_size_reads_what_read_csv_reads(tmp_path, text, read):
    f = tmp_path / "c.csv"
    f.write_bytes(text.encode())
    assert agree(f) == read


def test_a_long_plain_file_is_split_where_its_bytes_are(tmp_path):
    """Thousands of rows with long and short names, signs and exponents, read in blocks that
    cut lines anywhere: the plain way (not the csv module's) gives read_csv's values."""
    rng = np.random.default_rng(3)
    names = ["A320neo", "Matrice 300 RTK", "F-16C Fighting Falcon", "x" * 80, "G650ER"]
    lines = [HEAD.rstrip("\n")]
    for i in range(3000):
        r, y = rng.uniform(-1e4, 1e4, 2)
        form = ("{:.17g}", "{:.3e}", "{:+.2f}", " {} ")[i % 4]
        lines.append(f"{names[i % 5]},{form.format(r)},3,2,{form.format(y)},0")
    f = tmp_path / "long.csv"
    f.write_text("\r\n".join(lines) + "\r\n")
    with open(f, "rb") as handle:
        assert csv_table._printable_unquoted(handle, 1 << 10)
    assert agree(f)
    got = fast(f, 1 << 12)
    assert len(got["type"]) == 3000 and got["type"][3] == "x" * 80


def test_the_plain_way_is_the_one_a_plain_file_takes(tmp_path):
    """A file without quotes, of printable ASCII, is plain; a quote, a byte past ASCII, a NUL,
    or a CR not before an LF (anywhere, also across a block's edge) makes it the csv module's."""
    f = tmp_path / "c.csv"
    for text, plain in [(HEAD + ROWS, True), (HEAD.replace("\n", "\r\n") + ROWS, True),
                        (HEAD + '"A320neo"' + ROWS[7:], False), (HEAD + "é" + ROWS, False),
                        (HEAD + ROWS + "\x00", False), (HEAD + ROWS.replace("\n", "\r"), False),
                        (HEAD + ROWS + "\r", False)]:
        f.write_bytes(text.encode())
        for block in (1, 2, 3, 1 << 16):
            with open(f, "rb") as handle:
                assert csv_table._printable_unquoted(handle, block) == plain, (text, block)
                assert handle.tell() == 0


_PLAIN_CELLS = ["A320neo", "Mavic 3", " G650ER ", "", " ", "\t", "4500", "-20", " 3.4 ",
                "1e3", "1_0", "nan", "x", "1e400", "+.5", "0x10", "1 2", "7.", "-0"]
_CELLS = st.sampled_from(_PLAIN_CELLS + ['"A320neo"', '"1,5"', "é", '"a""b"'])
_ENDS = st.sampled_from(["\n", "\r\n", "\r"])


@settings(max_examples=300, deadline=None)
@given(header=st.sampled_from([HEAD.rstrip("\n"), "range_m,TYPE_NAME,yaw_deg,x",
                               "type,,range_m,yaw_deg", "type,range_m,yaw_deg,,"]),
       rows=st.one_of(st.lists(st.lists(_CELLS, min_size=0, max_size=7), max_size=12),
                      st.lists(st.lists(st.sampled_from(_PLAIN_CELLS), min_size=3, max_size=5),
                               max_size=12)),
       ends=st.lists(_ENDS, min_size=1, max_size=3), bom=st.booleans(),
       last_end=st.booleans())
def test_any_file_reads_as_read_csv_reads_it_or_goes_to_it(tmp_path_factory, header, rows,
                                                           ends, bom, last_end):
    """Generated files (cells of every kind, short and long rows, blank ones, quotes, CR, LF and
    CRLF, a BOM): read_columns gives read_csv's rows and values or hands the file over."""
    lines = [header] + [",".join(r) for r in rows]
    text = "".join(line + ends[i % len(ends)] for i, line in enumerate(lines))
    if not last_end:
        text = text.rstrip("\r\n")
    f = tmp_path_factory.mktemp("fuzz") / "c.csv"
    f.write_bytes((("\ufeff" if bom else "") + text).encode())
    agree(f)


def test_the_generated_files_take_both_ways(tmp_path):
    """The fuzz above reaches the plain way: a file of plain cells and LF or CRLF ends is plain
    (read there, or handed over where a cell needs care)."""
    f = tmp_path / "c.csv"
    f.write_bytes(b"range_m,TYPE_NAME,yaw_deg,x\r\n 4500,A320neo, -20 ,1_0\r\n"
                   b"1e3,Mavic 3,+.5,\r\n")
    with open(f, "rb") as handle:
        assert csv_table._printable_unquoted(handle, 4)
    assert agree(f)
