"""The one reader of every CSV file the project reads (conditions, types.csv, training logs).

CSV files as users make them: a spreadsheet's "CSV UTF-8" (a byte-order mark first), Windows
line ends (CRLF), quoted fields (a comma or a line break inside quotes), outer spaces around
values and header names, blank lines and rows of empty cells (a spreadsheet's trailing rows).
Every error names the file, the line as an editor shows it (1-based, the header is line 1 when
it is the first line), the column (its header name and its spreadsheet letter) and the value.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
from collections.abc import Iterable, Mapping
from pathlib import Path

from ..errors import InputError


def column_letter(i: int) -> str:
    """The spreadsheet letter of the 0-based column ``i``: A, B, ..., Z, AA, AB, ..."""
    out = ""
    i += 1
    while i:
        i, r = divmod(i - 1, 26)
        out = chr(65 + r) + out
    return out


class CSVRow(Mapping):
    """One data row: ``row[column]`` is the value's text (outer spaces stripped); ``line`` is
    the line it starts on; the typed getters raise an error naming file, line, column and
    value."""

    def __init__(self, table: CSVTable, line: int, values: dict[str, str]) -> None:
        self.table = table
        self.line = line
        self._values = values

    def __getitem__(self, key: str) -> str:
        return self._values[key]

    def __iter__(self):
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def where(self, column: str | None = None) -> str:
        """'FILE, line N, column NAME (C)': where a value is."""
        at = f"{self.table.path}, line {self.line}"
        if column is not None:
            at += f", column {column} ({self.table.letter(column)})"
        return at

    def error(self, column: str, why: str) -> InputError:
        """An InputError naming the file, the line, the column and the value: ``why`` says
        what is wrong and what is accepted."""
        return InputError(f"{self.where(column)}: {self._values.get(column, '')!r} {why}")

    def text(self, column: str, required: bool = True) -> str:
        value = self._values[column]
        if required and not value:
            raise self.error(column, "is empty; a value is needed here")
        return value

    def float(self, column: str, optional: bool = False, finite: bool = True) -> float | None:
        """The value as a number; ``optional``: an empty cell is None."""
        value = self._values[column]
        if not value:
            if optional:
                return None
            raise self.error(column, "is empty; a number is needed here")
        try:
            number = float(value)
        except ValueError:
            hint = " (use a point as the decimal mark)" if "," in value else ""
            raise self.error(column, f"is not a number{hint}") from None
        if finite and not math.isfinite(number):
            raise self.error(column, "is not a finite number")
        return number

    def int(self, column: str) -> int:
        number = self.float(column)
        if number != int(number):
            raise self.error(column, "is not a whole number")
        return int(number)


class CSVTable:
    """A CSV file read whole: ``header`` (column names, outer spaces stripped, lower case),
    ``header_line`` and ``rows`` (CSVRow)."""

    def __init__(self, path, header: list[str], header_line: int) -> None:
        self.path = Path(path)
        self.header = header
        self.header_line = header_line
        self.rows: list[CSVRow] = []
        self.lines: list[str] = []  # the file's text lines as read (BOM gone, ends kept)

    def letter(self, column: str) -> str:
        return column_letter(self.header.index(column)) if column in self.header else "?"

    def __iter__(self):
        return iter(self.rows)

    def __len__(self) -> int:
        return len(self.rows)


def _text(path: Path, what: str) -> str:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise InputError(f"{what} {path} is a directory, not a CSV file") from None
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise InputError(f"{path}: saved as UTF-16 text; save it as \"CSV UTF-8\" (or plain "
                         "UTF-8) and try again")
    try:
        return data.decode("utf-8-sig")  # a spreadsheet's "CSV UTF-8" starts with a BOM
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise InputError(f"{path}, line {line}: byte 0x{data[exc.start]:02x} is not UTF-8 "
                         "text; save the file as \"CSV UTF-8\" (or plain UTF-8)") from None


def read_csv(path, required: Iterable[str] = (), what: str = "CSV file",
             any_of: Iterable[Iterable[str]] = ()) -> CSVTable:
    """Read ``path`` whole. ``required``: column names the header must have (any case);
    ``any_of``: groups of names of which the header must have one. Blank lines and rows of
    empty cells are skipped; a row with fewer values than the header, or with values past its
    last column, is refused by line. ``what`` names the file's role in messages."""
    path = Path(path)
    text = _text(path, what)
    reader = csv.reader(io.StringIO(text, newline=""), skipinitialspace=True)
    table = None
    start = 1
    try:
        for cells in reader:
            line, start = start, reader.line_num + 1
            cells = [c.strip() for c in cells]
            if not any(cells):
                continue  # a blank line, or a row of empty cells
            if table is None:
                table = _header(path, cells, line)
                continue
            table.rows.append(_row(table, cells, line))
    except csv.Error as exc:
        raise InputError(f"{path}, line {reader.line_num}: not readable as CSV ({exc})"
                         ) from None
    need = [c.strip().lower() for c in required]
    groups = [[c.strip().lower() for c in g] for g in any_of]
    if table is None:
        named = ",".join(need) if need else "a header line"
        raise InputError(f"{path}: the file is empty; a {what} needs the header {named} "
                         "and rows under it")
    table.lines = text.splitlines(keepends=True)
    missing = [c for c in need if c not in table.header]
    missing += ["|".join(g) for g in groups if not any(c in table.header for c in g)]
    if missing:
        raise InputError(f"{path}, line {table.header_line}: the header has no column "
                         f"{', '.join(missing)}; a {what} needs the columns "
                         f"{','.join(need + ['|'.join(g) for g in groups])} (found: "
                         f"{','.join(h for h in table.header if h) or 'none'})")
    return table


def _header(path: Path, cells: list[str], line: int) -> CSVTable:
    header = [c.lower() for c in cells]
    while header and not header[-1]:
        header.pop()  # a spreadsheet's empty columns past the last one
    seen = set()
    for i, name in enumerate(header):
        if name and name in seen:
            raise InputError(f"{path}, line {line}, column {column_letter(i)}: the column name "
                             f"{cells[i]!r} appears twice in the header")
        seen.add(name)
    return CSVTable(path, header, line)


def _row(table: CSVTable, cells: list[str], line: int) -> CSVRow:
    n = len(table.header)
    extra = [(i, c) for i, c in enumerate(cells[n:], start=n) if c]
    if extra:
        i, c = extra[0]
        raise InputError(f"{table.path}, line {line}, column {column_letter(i)}: {c!r} lies past "
                         f"the header's last column ({table.header[-1]}, "
                         f"{column_letter(n - 1)}); a comma too many, or a value with a comma "
                         "that needs quotes?")
    if len(cells) < n:
        missing = [h for h in table.header[len(cells):] if h]
        raise InputError(f"{table.path}, line {line}: {len(cells)} values, the header (line "
                         f"{table.header_line}) has {n} columns: no value for "
                         f"{', '.join(missing)}")
    values = {}
    for i, h in enumerate(table.header):
        if h:
            values[h] = cells[i]
        elif cells[i]:
            raise InputError(f"{table.path}, line {line}, column {column_letter(i)}: "
                             f"{cells[i]!r} lies under an empty header name")
    return CSVRow(table, line, values)


class NeedsCare(Exception):
    """:func:`read_columns` met something only :func:`read_csv` reads (or refuses) rightly."""


def read_columns(path, columns: Iterable[str], batch: int = 65536):
    """The fast path of :func:`read_csv` for long files (a conditions CSV of 10^6 rows):
    yields, ``batch`` data rows at a time, a dict of the wanted ``columns`` (header names,
    lower case; a tuple of names: the first the header has, under the tuple's first name) as
    lists of their stripped texts, streaming the file without per-row
    objects. It raises :class:`NeedsCare` at the first thing that needs read_csv's care (a
    file that is not plain UTF-8, a header naming a column twice or lacking a wanted one, a
    row of another length, a value under an empty header name, an empty wanted cell): the
    caller then reads the file with :func:`read_csv`, which accepts or refuses it with its
    one message naming the file, line and column. The rows yielded are the rows read_csv
    returns, in order."""
    want = [(c,) if isinstance(c, str) else tuple(c) for c in columns]
    try:
        f = open(path, encoding="utf-8-sig", newline="")  # noqa: SIM115 - closed below
    except OSError:
        raise NeedsCare from None
    with f:
        try:
            yield from _columns(csv.reader(f, skipinitialspace=True), want, batch)
        except (UnicodeDecodeError, csv.Error):
            raise NeedsCare from None


def _columns(reader, want: list[tuple], batch: int):
    header = None
    for cells in reader:
        header = [c.strip().lower() for c in cells]
        if any(header):
            break
    if not header or not any(header):
        raise NeedsCare
    while not header[-1]:
        header.pop()
    names = [h for h in header if h]
    found = [next((a.lower() for a in alts if a.lower() in header), None) for alts in want]
    if len(set(names)) != len(names) or None in found:
        raise NeedsCare
    n = len(header)
    at = [header.index(c) for c in found]
    want = [alts[0] for alts in want]
    unnamed = [i for i, h in enumerate(header) if not h]
    while True:
        rows = list(itertools.islice(reader, batch))
        if not rows:
            return
        if any(len(r) != n for r in rows):
            rows = [r for r in rows if _plain(r, n)]
        out = {}
        for c, i in zip(want, at, strict=True):
            out[c] = vals = [r[i].strip() for r in rows]
            if not all(vals):
                raise NeedsCare  # an empty cell (read_csv skips a row of empty cells)
        if any(r[i].strip() for i in unnamed for r in rows):
            raise NeedsCare
        if rows:
            yield out


def _plain(cells: list, n: int) -> bool:
    """False for a blank row (skipped); True for a row of ``n`` cells, or more where the
    extra ones are empty (cut to ``n``); :class:`NeedsCare` for anything else."""
    if not any(c.strip() for c in cells):
        return False
    if len(cells) < n or any(c.strip() for c in cells[n:]):
        raise NeedsCare
    del cells[n:]
    return True
