"""Every CSV the project reads goes through one reader (apcg_core/io/csv_table.py), which takes
CSV files as spreadsheets and editors save them and names file, line, column and value."""

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.io.csv_table import column_letter, read_csv

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["apcg_core", "dataset_builder", "training", "blender_addon", "tools", "bench"]
READER = ROOT / "apcg_core" / "io" / "csv_table.py"
# Reads of a CSV file's bytes that are not parsing it: (file, the line's text).
NOT_PARSING = {
    ("dataset_builder/build.py", "conditions.csv"): "compared byte for byte with what the "
                                                    "config makes",
}
PARSERS = re.compile(r"\bcsv\s*\.\s*(reader|DictReader|Sniffer)\b|\bloadtxt\b|\bgenfromtxt\b"
                     r"|\bread_csv\b|\bfromfile\b")
PARSER_NAMES = {"reader", "DictReader", "Sniffer", "loadtxt", "genfromtxt", "read_csv",
                "fromfile"}


def _csv_reads(path: Path):
    """(line, text) of every place in ``path`` that parses or reads a CSV: the csv module's
    readers, numpy's text loaders, pandas, and a file whose name ends in .csv opened or read
    (open(...csv...), (... / "x.csv").read_text() / read_bytes() / open())."""
    src = path.read_text()
    tree = ast.parse(src)
    lines = src.splitlines()
    hits = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
        if name == "read_csv" and "csv_table" in src:
            continue  # the one reader itself
        if PARSERS.search(ast.unparse(func)) if name in PARSER_NAMES else False:
            hits.append((node.lineno, lines[node.lineno - 1].strip()))
        elif name in ("open", "read_text", "read_bytes", "readlines"):
            text = ast.unparse(node)
            if ".csv" in text and "write" not in text and "'w'" not in text:
                hits.append((node.lineno, lines[node.lineno - 1].strip()))
    return hits


def test_every_csv_read_goes_through_the_one_reader():
    found = []
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            if f == READER:
                continue
            rel = str(f.relative_to(ROOT))
            for line, text in _csv_reads(f):
                if any(rel == where and what in text for where, what in NOT_PARSING):
                    continue
                found.append(f"{rel}:{line}: {text}")
    assert not found, ("CSV read outside apcg_core/io/csv_table.read_csv (use it, so a BOM, "
                       "CRLF, quotes and blank lines are taken and errors name the line):\n"
                       + "\n".join(found))


def test_the_scan_finds_a_csv_read(tmp_path):
    """The scan above can fail: it finds each way a CSV is read."""
    f = tmp_path / "m.py"
    f.write_text("import csv, numpy as np\nfrom pathlib import Path\n"
                 "a = csv.DictReader(open('x'))\nb = csv.reader([])\n"
                 "c = np.loadtxt('t.csv')\nd = (Path('r') / 'log.csv').read_text()\n"
                 "e = open('conditions.csv')\nf = open('out.csv', 'w')\n")
    assert [line for line, _ in _csv_reads(f)] == [3, 4, 5, 6, 7]


def _write(tmp_path, data: bytes, name="t.csv") -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


def test_bom_crlf_quotes_and_trailing_empty_lines(tmp_path):
    data = (b"\xef\xbb\xbf name , value \r\n\"a, b\",\"1.5\"\r\n\r\n"
            b"\"multi\nline\",2\r\nc,3\r\n,\r\n\r\n\r\n")
    t = read_csv(_write(tmp_path, data), required=["NAME", "value"])
    assert t.header == ["name", "value"]
    assert [dict(r) for r in t] == [{"name": "a, b", "value": "1.5"},
                                    {"name": "multi\nline", "value": "2"},
                                    {"name": "c", "value": "3"}]
    assert [r.line for r in t] == [2, 4, 6]  # as an editor numbers them (header: line 1)
    with pytest.raises(InputError, match=r"t.csv, line 2, column value \(B\): '1.5' is not a "
                                         "whole number"):
        t.rows[0].int("value")
    assert t.rows[2].int("value") == 3 and t.rows[0].float("value") == 1.5


def test_column_letters():
    assert [column_letter(i) for i in (0, 1, 25, 26, 27, 51, 52, 701, 702)] == \
        ["A", "B", "Z", "AA", "AB", "AZ", "BA", "ZZ", "AAA"]


def test_a_training_log_saved_by_a_spreadsheet_reads_the_same(tmp_path):
    from training.figures import read_log
    plain = ("step,epoch,loss_d,loss_g,gp,wasserstein,seconds\n"
             "1,0.1,-1.0,2.0,0.1,1.0,10\n2,0.2,-0.5,1.5,0.05,0.5,20\n")
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "log.csv").write_text(plain)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "log.csv").write_bytes(b"\xef\xbb\xbf" + plain.replace(
        "\n", "\r\n").encode() + b",,,,,,\r\n\r\n")
    a, b = read_log(tmp_path / "a"), read_log(tmp_path / "b")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    (tmp_path / "b" / "log.csv").write_text(plain.replace("0.05", "x"))
    with pytest.raises(InputError, match=r"log.csv, line 3, column gp \(E\): 'x' is not a "
                                         "number"):
        read_log(tmp_path / "b")


def test_the_type_table_is_read_by_the_one_reader(tmp_path, monkeypatch):
    """types.csv too: a damaged copy is named by line, column and value, not a traceback."""
    from apcg_core.catalog import catalog
    text = catalog.TYPES_CSV.read_text().splitlines(keepends=True)
    row = text[3].split(",")
    row[6] = '"3,5"'  # the third type's length_m, with a decimal comma, quoted
    bad = text[:3] + [",".join(row)]
    f = tmp_path / "types.csv"
    f.write_bytes(b"\xef\xbb\xbf" + "".join(bad).replace("\n", "\r\n").encode())
    monkeypatch.setattr(catalog, "TYPES_CSV", f)
    with pytest.raises(InputError, match=r"types.csv, line 4, column length_m \(G\): '3,5' is "
                                         r"not a number \(use a point"):
        catalog.Catalog(include_user=False)
