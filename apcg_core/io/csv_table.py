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
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from ..errors import InputError

# A number in a CSV: plain ASCII decimal or scientific notation (what spreadsheets and
# programs write), or inf / nan (then refused as not finite where a finite one is needed);
# not Python's own extras (``1_000``, other scripts' digits, which float() reads).
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:inf|infinity|nan)",
                     re.ASCII | re.IGNORECASE)
NUMBER_FORMS = "a plain decimal number, e.g. 12, -3.5 or 1.2e3"


def parse_number(text: str) -> float:
    """``text`` (outer spaces allowed) as a float when it is a plain ASCII number
    (:data:`NUMBER_FORMS`); ValueError otherwise. Every number of every CSV goes through it."""
    text = text.strip()
    if not _NUMBER.fullmatch(text):
        raise ValueError(f"not a plain number: {text!r}")
    return float(text)


def header_names(path) -> list[str] | None:
    """The lower-case column names of a CSV's header (its first line with a value), or None
    when the file cannot be read that far (its reader then says why)."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            for cells in csv.reader(f, skipinitialspace=True):
                names = [c.strip().lower() for c in cells]
                if any(names):
                    return names
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    return None


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
            number = parse_number(value)
        except ValueError:
            hint = " (use a point as the decimal mark)" if "," in value else ""
            raise self.error(column, f"is not a number{hint}; accepted: {NUMBER_FORMS}"
                             ) from None
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
             any_of: Iterable[Iterable[str]] = (),
             allowed: Iterable[str] | None = None) -> CSVTable:
    """Read ``path`` whole. ``required``: column names the header must have (any case);
    ``any_of``: groups of names of which the header must have one; ``allowed``: when given,
    every column the header may have (another is refused, not ignored). Blank lines and rows
    of empty cells are skipped; a row with fewer values than the header, or with values past
    its last column, is refused by line. ``what`` names the file's role in messages."""
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
    if table is None:  # the header it needs: its one-of groups first (a type column), then
        named = ",".join(["|".join(g) for g in groups] + need) or "a header line"
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
    if allowed is not None:
        accepted = [c.strip().lower() for c in allowed]
        unknown = [h for h in table.header if h and h not in accepted]
        if unknown:
            raise InputError(f"{path}, line {table.header_line}, column {unknown[0]} "
                             f"({table.letter(unknown[0])}): a {what} has no column "
                             f"{unknown[0]!r}; accepted columns: {','.join(accepted)}")
    return table


def _header(path: Path, cells: list[str], line: int) -> CSVTable:
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        if any(sep in c for c in cells):  # no column name holds one: another separator
            raise InputError(f"{path}, line {line}: the header is separated by {name}; this "
                             "CSV file must be separated by commas, with '.' as the decimal "
                             "point (a spreadsheet set to a locale with decimal commas saves "
                             "';': export as CSV with ',' between values)")
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


def read_columns(path, columns: Iterable[str], batch: int = 65536, numbers: Iterable[str] = (),
                 block: int = 1 << 23):
    """The fast path of :func:`read_csv` for long files (a conditions CSV of 10^6 rows):
    yields, a piece at a time (``block`` bytes of whole lines the plain way, ``batch`` rows
    through the csv module), a dict of the wanted ``columns`` (header names,
    lower case; a tuple of names: the first the header has, under the tuple's first name):
    lists of their stripped texts, except the columns named in ``numbers`` (by their first
    names), which come as float64 arrays of :func:`parse_number`'s values. Memory holds one
    batch. It raises :class:`NeedsCare` at the first thing that needs read_csv's care (a file
    that is not plain UTF-8, a header naming a column twice or lacking a wanted one, a row of
    another length, a value under an empty header name, an empty wanted cell, a number
    :func:`parse_number` refuses): the caller then reads the file with :func:`read_csv`, which
    accepts or refuses it with its one message naming the file, line and column. The rows
    yielded are the rows read_csv returns, in order.

    Two ways, the same rows and values: a file of printable ASCII without quotes (what
    programs write: 10^5 rows in about a fifth of a second) is split where its bytes are, in
    ``block``-byte pieces, its numbers parsed by numpy's C reader (:func:`numpy.loadtxt`,
    whose values are float()'s); anything else line by line through the csv module."""
    want = [(c,) if isinstance(c, str) else tuple(c) for c in columns]
    numbers = set(numbers)
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError:
        raise NeedsCare from None
    with f:
        if _printable_unquoted(f, block):
            yield from _plain_file_columns(f, want, numbers, block)
            return
    try:
        f = open(path, encoding="utf-8-sig", newline="")  # noqa: SIM115 - closed below
    except OSError:
        raise NeedsCare from None
    with f:
        try:
            reader = csv.reader(f, skipinitialspace=True)
            cols = _header_columns(reader, want)
            while rows := list(itertools.islice(reader, batch)):
                if (out := _batch(rows, *cols, numbers)) is not None:
                    yield out
        except (UnicodeDecodeError, csv.Error):
            raise NeedsCare from None


def _header_columns(rows, want: list[tuple]):
    """(n, at, names, unnamed) from the first row of ``rows`` with a name in it: the header's
    length, where each wanted column is, the wanted columns' own names, the columns without a
    name."""
    header = None
    for cells in rows:
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
    unnamed = [i for i, h in enumerate(header) if not h]
    return len(header), [header.index(c) for c in found], [alts[0] for alts in want], unnamed


def _batch(rows: list, n: int, at: list, names: list, unnamed: list, numbers) -> dict | None:
    """The wanted columns of csv ``rows`` (None when all are blank)."""
    if any(len(r) != n for r in rows):
        rows = [r for r in rows if _plain(r, n)]
    if not rows:
        return None
    out = {}
    for c, i in zip(names, at, strict=True):
        vals = [r[i].strip() for r in rows]
        if not all(vals):  # a blank row of n cells (read_csv skips it), or an empty cell
            kept = [r for r in rows if _plain(r, n)]
            if len(kept) < len(rows):
                return _batch(kept, n, at, names, unnamed, numbers)
            raise NeedsCare
        if c in numbers:
            try:
                vals = np.fromiter(map(parse_number, vals), np.float64, len(vals))
            except ValueError:
                raise NeedsCare from None
        out[c] = vals
    if any(r[i].strip() for i in unnamed for r in rows):
        raise NeedsCare
    return out


# The bytes of a "plain" file (split where its commas and line ends are): printable ASCII,
# tab and line ends, but no quote (a field that may hold a comma or a line end)
_PLAIN_BYTES = bytes(b for b in range(256) if b in b"\t\n\r" or 0x20 <= b <= 0x7e
                     and b != ord('"'))
_BOM = b"\xef\xbb\xbf"
_BLANK = np.zeros(256, bool)
_BLANK[[ord(c) for c in " \t,\n"]] = True  # what a blank row (no value in any cell) holds


def _printable_unquoted(f, block: int) -> bool:
    """Whether the open binary file is plain (a BOM first allowed; CR only before LF); the
    file is rewound."""
    prev, cr, crlf = b"", 0, 0  # CRs, and CRs before an LF (one may end a block)
    try:
        if f.read(3) != _BOM:
            f.seek(0)
        while data := f.read(block):
            if data.translate(None, _PLAIN_BYTES):
                return False
            cr += data.count(b"\r")
            # CR-LF pairs: within this piece, and the last piece's CR with this one's LF
            crlf += data.count(b"\r\n") + (prev == b"\r" and data[:1] == b"\n")
            prev = data[-1:]
        return cr == crlf
    finally:
        f.seek(0)


def _plain_file_columns(f, want: list[tuple], numbers, block: int):
    """:func:`read_columns` of a plain file (:func:`_printable_unquoted`), ``block`` bytes of
    whole lines at a time."""
    if f.read(3) != _BOM:
        f.seek(0)
    cols = None
    rest = b""
    while True:
        data = f.read(block)
        data, rest = rest + data, b""
        if not data:
            if cols is None:
                raise NeedsCare  # no header
            return
        if f.peek(1):  # more follows
            cut = data.rfind(b"\n") + 1
            if cut:  # whole lines now, the rest with the next piece
                data, rest = data[:cut], data[cut:]
            else:
                rest = data
                continue
        text = data.replace(b"\r\n", b"\n")
        if not text.endswith(b"\n"):
            text += b"\n"
        if cols is None:  # the header: the first line with a name in it
            for line_end in _line_ends(text):
                line = text[:line_end].rsplit(b"\n", 1)[-1]
                if not _BLANK[np.frombuffer(line, np.uint8)].all():
                    break
            else:
                continue
            cols = _header_columns([line.decode("ascii").split(",")], want)
            text = text[line_end + 1:]
        if (out := _plain_block(text, *cols, numbers)) is not None:
            yield out


def _line_ends(text: bytes):
    i = text.find(b"\n")
    while i >= 0:
        yield i
        i = text.find(b"\n", i + 1)


def _plain_block(text: bytes, n: int, at: list, names: list, unnamed: list, numbers):
    """The wanted columns of whole plain lines ``text`` (LF ends, the last line ended): split
    where its bytes are when every line is a row of ``n`` cells under named columns; through
    the csv module otherwise (blank rows, extra cells, a value numpy's reader refuses)."""
    a = np.frombuffer(text, np.uint8)
    ends = np.flatnonzero(a == 10)
    starts = np.concatenate(([0], ends[:-1] + 1))
    comma = np.flatnonzero(a == 44)
    before = np.searchsorted(comma, starts)  # commas before each line
    regular = (not unnamed and len(ends)
               and (np.searchsorted(comma, ends) - before == n - 1).all()
               and not _any_blank(text, a, starts, ends))
    if not regular:
        return _csv_block(text, n, at, names, unnamed, numbers) if len(ends) else None
    out = {}
    text_cols = [(c, i) for c, i in zip(names, at, strict=True) if c not in numbers]
    number_cols = [(c, i) for c, i in zip(names, at, strict=True) if c in numbers]
    for c, i in text_cols:
        lo = starts if i == 0 else comma[before + i - 1] + 1
        hi = ends if i == n - 1 else comma[before + i]
        out[c] = _texts(text, a, lo, hi)
    if number_cols:
        try:
            values = np.loadtxt(io.StringIO(text.decode("ascii")), dtype=np.float64,
                                delimiter=",", comments=None, usecols=[i for _, i in number_cols],
                                ndmin=2)
        except ValueError:  # a value numpy's reader refuses: parse_number decides
            return _csv_block(text, n, at, names, unnamed, numbers)
        if len(values) != len(ends):
            raise NeedsCare
        for j, (c, _) in enumerate(number_cols):
            out[c] = np.ascontiguousarray(values[:, j])
    return out


def _any_blank(text: bytes, a: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> bool:
    """Whether a line holds only spaces, tabs and commas (looked at only where the first byte
    is one of them)."""
    maybe = _BLANK[a[starts]]
    return any(_BLANK[np.frombuffer(text[i:j], np.uint8)].all()
               for i, j in zip(starts[maybe].tolist(), ends[maybe].tolist(), strict=True))


def _csv_block(text: bytes, n, at, names, unnamed, numbers):
    return _batch(list(csv.reader(io.StringIO(text.decode("ascii")), skipinitialspace=True)),
                  n, at, names, unnamed, numbers)


_WIDE = 64  # cells longer than this are cut out one by one


def _texts(text: bytes, a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> list:
    """The stripped texts of the cells text[lo:hi] (``a``: its bytes as uint8), each distinct
    text decoded once."""
    size = hi - lo
    width = int(size.max())
    if width > _WIDE:
        cut = [text[i:j].decode("ascii").strip() for i, j in zip(lo.tolist(), hi.tolist(),
                                                                     strict=True)]
        if not all(cut):
            raise NeedsCare
        return cut
    cells = np.zeros((len(lo), max(width, 1)), np.uint8)
    k = np.arange(width)
    inside = k < size[:, None]
    cells[:, :width][inside] = a[(lo[:, None] + k)[inside]]
    distinct, which = np.unique(cells.view(f"S{max(width, 1)}").ravel(), return_inverse=True)
    stripped = [d.decode("ascii").strip() for d in distinct]
    if not all(stripped):
        raise NeedsCare  # an empty cell (read_csv skips a row of empty cells)
    return np.array(stripped, dtype=object)[which].tolist()


def _plain(cells: list, n: int) -> bool:
    """False for a blank row (skipped); True for a row of ``n`` cells, or more where the
    extra ones are empty (cut to ``n``); :class:`NeedsCare` for anything else."""
    if not any(c.strip() for c in cells):
        return False
    if len(cells) < n or any(c.strip() for c in cells[n:]):
        raise NeedsCare
    del cells[n:]
    return True
