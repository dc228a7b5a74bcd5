"""A type is its catalog name (SPEC section 3).

A dataset and a model each hold a table of the types they know, in their own code order; the
integer in column 0 of a condition row is a code of one such table and means nothing without
it. :class:`TypeTable` is that table, and :class:`Conditions` carries condition rows together
with the table their codes refer to, so every crossing (dataset -> model, model -> report,
add-on -> model) maps by name and a type the other side does not know is refused by name.
"""

from __future__ import annotations

import difflib
import unicodedata
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

# What a table records of each type (dataset.json and model.json "types" entries).
# mesh_sha256: a user type's (Catalog.mesh_record)
RECORD_KEYS = ("name", "catalog_index", "kind", "category", "range_band", "depth_length_m",
               "bounding_radius_m", "mesh_sha256")


# What each recorded value may be (the catalog's own rules: apcg_core/catalog/catalog.py).
KINDS = ("aircraft", "drone")
RANGE_BANDS = ("far", "near")


def _positive(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0


def _record_problem(r: dict) -> str | None:
    """What is wrong with one type entry's values, or None."""
    if not isinstance(r["name"], str) or not normalize_name(r["name"]):
        return f"name must be a non-empty text, got {r['name']!r}"
    if not _positive(r["depth_length_m"]):
        return f"depth_length_m must be a finite number of metres > 0, got {r['depth_length_m']!r}"
    if "bounding_radius_m" in r and not _positive(r["bounding_radius_m"]):
        return (f"bounding_radius_m must be a finite number of metres > 0, got "
                f"{r['bounding_radius_m']!r}")
    if "kind" in r and r["kind"] not in KINDS:
        return f"kind must be one of {', '.join(KINDS)}, got {r['kind']!r}"
    if "range_band" in r and r["range_band"] not in RANGE_BANDS:
        return f"range_band must be one of {', '.join(RANGE_BANDS)}, got {r['range_band']!r}"
    digest = r.get("mesh_sha256")
    if digest is not None and not (isinstance(digest, str) and len(digest) == 64
                                   and all(c in "0123456789abcdef" for c in digest)):
        return f"mesh_sha256 must be 64 lowercase hexadecimal digits, got {digest!r}"
    index = r.get("catalog_index")
    if index is not None and (isinstance(index, bool) or not isinstance(index, int)):
        return f"catalog_index must be an integer, got {index!r}"
    return None


def _shown(r: dict) -> str:
    text = repr(r.get("name"))
    return text if len(text) <= 60 else text[:57] + "..."


def normalize_name(name) -> str:
    """A type name as it is stored and shown: Unicode NFC, outer whitespace stripped."""
    return unicodedata.normalize("NFC", str(name)).strip()


def name_key(name) -> str:
    """What two names must differ in to be two types: the name normalised, case folded, and
    without whitespace, dashes or underscores ("Jet_A", "Jet A", "jet-a" are one name). Every
    lookup of a type by name (the catalog, a dataset's or a model's table) goes through it."""
    return "".join(c for c in normalize_name(name).casefold()
                   if not c.isspace() and unicodedata.category(c) not in ("Pd", "Pc"))


# Unicode categories no name may hold (a type's, a sensor's): controls, format (zero-width,
# direction marks), surrogates (undecodable bytes), private use and unassigned.
ODD_CATEGORIES = {"Cc", "Cf", "Cs", "Co", "Cn"}


def odd_characters(text: str) -> str:
    """What ``text`` holds that no name may ("" when nothing): a control character, or an
    invisible or unassigned one, worded for a message ("it holds ...")."""
    odd = sorted({unicodedata.category(c) for c in text} & ODD_CATEGORIES)
    if not odd:
        return ""
    return "a control character" if odd == ["Cc"] else (
        "an invisible or unassigned character (Unicode category "
        f"{', '.join(odd)}: a zero-width space, a direction mark)")


def find_preset(ref, directory) -> Path | None:
    """The preset file in ``directory`` (``NAME.toml``) that ``ref`` names, None when it names
    none: the one lookup of every preset, lidar (``lidar_presets/``) and sensor
    (``sensor/presets/``). Names are folded as type names are (:func:`name_key`: case,
    spaces, dashes and underscores), so ``1550NM_day`` is ``1550nm-day``; a reference with a
    path separator is a file, never a preset."""
    directory = Path(directory)
    ref_s = str(ref).strip()
    if not ref_s or "/" in ref_s or "\\" in ref_s:
        return None
    exact = directory / f"{ref_s}.toml"
    if exact.is_file():
        return exact
    key = name_key(ref_s)
    hits = [p for p in sorted(directory.glob("*.toml")) if name_key(p.stem) == key]
    return hits[0] if len(hits) == 1 else None


def _listing(names, limit: int = 12) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" ... ({len(names)} in all)" if len(names) > limit else "")


def each_once(keys, resolve) -> list:
    """``[resolve(k) for k in keys]``, resolving each distinct key once (a 10^6-row request
    names a few types). Keys are told apart by type and value, so 1.0 is not taken for 1."""
    keys = keys if isinstance(keys, list) else list(keys)
    if set(map(type, keys)) <= {str}:  # names (a CSV's): one lookup each, no key tuples
        known = {n: resolve(n) for n in dict.fromkeys(keys)}  # in order of first appearance
        return list(map(known.__getitem__, keys))
    known: dict = {}
    return [known[k] if (k := (type(n), n)) in known else known.setdefault(k, resolve(n))
            for n in keys]


@dataclass(frozen=True)
class TypeTable:
    """The types of one dataset or model; code i is ``records[i]``. ``owner`` names the holder
    in messages ("model models/x", "dataset data/demo")."""

    records: tuple
    owner: str = "this table"

    def __post_init__(self) -> None:
        recs = tuple(dict(r) for r in self.records)
        if not recs:
            raise InputError(f"{self.owner} holds no types")
        for r in recs:
            missing = [k for k in ("name", "depth_length_m") if k not in r]
            if missing:
                raise InputError(f"{self.owner}: a type entry lacks {missing}: {r}")
            bad = _record_problem(r)
            if bad:
                raise InputError(f"{self.owner}: type entry {_shown(r)}: {bad}")
        seen: dict = {}
        for r in recs:
            key = name_key(r["name"])
            if key in seen:
                raise InputError(f"{self.owner} lists type {r['name']!r} twice (names that "
                                 "differ in case, spaces, '-' or '_' are one type)")
            seen[key] = len(seen)
        object.__setattr__(self, "records", recs)
        object.__setattr__(self, "_code", seen)

    @classmethod
    def from_records(cls, records, owner: str = "this table") -> TypeTable:
        """From dataset.json / model.json ``types`` entries; entries with a ``code`` are put
        in code order and the codes must be 0 .. n-1."""
        recs = list(records)
        if recs and all("code" in r for r in recs):
            codes = sorted(int(r["code"]) for r in recs)
            if codes != list(range(len(recs))):
                raise InputError(f"{owner}: type codes must be 0 .. {len(recs) - 1}, got {codes}")
            recs.sort(key=lambda r: int(r["code"]))
        return cls(tuple({k: r[k] for k in RECORD_KEYS if k in r} for r in recs), owner)

    def to_records(self) -> list[dict]:
        return [{"code": i, **r} for i, r in enumerate(self.records)]

    # --- lookups ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.records)

    @property
    def names(self) -> list[str]:
        return [r["name"] for r in self.records]

    def __contains__(self, name) -> bool:
        return isinstance(name, str) and name_key(name) in self._code

    def code(self, name: str) -> int:
        """The code of type ``name`` (any spelling the catalog takes: :func:`name_key`);
        refuses a type this table lacks, with the nearest name it knows."""
        if not isinstance(name, str):
            raise InputError(f"a type is given by its catalog name, got {name!r}; "
                             f"{self.owner} knows: {_listing(self.names)}")
        code = self._code.get(name_key(name))
        if code is None:
            close = difflib.get_close_matches(name_key(name), list(self._code), n=1)
            hint = f" (did you mean {self.names[self._code[close[0]]]!r}?)" if close else ""
            raise InputError(f"type {name!r} is not one {self.owner} knows{hint}; it knows: "
                             f"{_listing(self.names)}")
        return code

    def codes(self, names) -> np.ndarray:
        return np.array(each_once(names, self.code), dtype=np.int64)

    def name(self, code) -> str:
        c = int(code)
        if not 0 <= c < len(self.records):
            raise InputError(f"type code {code!r} is not one of {self.owner}'s 0 .. "
                             f"{len(self.records) - 1}")
        return self.records[c]["name"]

    def column(self, key: str) -> np.ndarray:
        """One recorded value per code (e.g. ``depth_length_m``), as an array."""
        return np.array([r[key] for r in self.records])

    def is_near(self, codes) -> np.ndarray:
        """Whether each code's type uses the near (drone) range band."""
        near = np.array([r.get("range_band") == "near" for r in self.records])
        return near[np.asarray(codes, dtype=np.int64)]

    def _code_map(self, to: TypeTable) -> np.ndarray:
        """Each code of this table as a code of ``to`` (-1: a type ``to`` lacks), made once per
        pair of tables: a request recodes every block of its rows (10^5 blocks of a 10^7-row
        CSV), and the names' keys cost 0.3 ms a time for 98 types."""
        # id(to) -> (to, its codes): holding ``to`` keeps its id from naming another table
        maps = self.__dict__.setdefault("_maps", {})
        hit = maps.get(id(to))
        if hit is None:
            if len(maps) >= 16:  # held tables stay few in a long session (the add-on's)
                maps.clear()
            hit = maps[id(to)] = (to, np.array([to._code.get(name_key(n), -1)
                                                for n in self.names], dtype=np.int64))
            hit[1].flags.writeable = False
        return hit[1]

    def recode(self, codes, to: TypeTable) -> np.ndarray:
        """Codes of this table as codes of ``to`` (by name); refuses types ``to`` lacks,
        naming them."""
        codes = np.asarray(codes)
        if codes.size and (np.any(codes != np.round(codes)) or codes.min() < 0
                           or codes.max() >= len(self)):
            raise InputError(f"type codes {np.unique(codes)[:8].tolist()} are not all codes "
                             f"of {self.owner} (0 .. {len(self) - 1})")
        codes = codes.astype(np.int64)
        out = self._code_map(to)[codes]
        if (out < 0).any():
            lacking = sorted({self.names[c] for c in codes[out < 0]})
            raise InputError(f"{to.owner} was not trained on (or does not hold) type"
                             f"{'s' if len(lacking) > 1 else ''} {_listing(lacking, 6)}; "
                             f"it knows: {_listing(to.names)}")
        return out


@dataclass(frozen=True)
class Conditions:
    """Condition rows ``table`` (N, 6) [type code, r0 m, beta0, pitch, yaw, roll rad] whose
    type codes are codes of ``types``."""

    types: TypeTable
    table: np.ndarray

    def __post_init__(self) -> None:
        t = np.atleast_2d(np.asarray(self.table, dtype=np.float64))
        if t.ndim != 2 or t.shape[1] != 6:
            raise InputError(f"a condition table has shape (N, 6), got {np.shape(self.table)}")
        object.__setattr__(self, "table", t)

    @classmethod
    def from_names(cls, types: TypeTable, names, pose) -> Conditions:
        """Rows for type ``names`` (one per row) and ``pose`` (N, 5) [r0 m, beta0, pitch,
        yaw, roll rad], coded in ``types``."""
        pose = np.atleast_2d(np.asarray(pose, dtype=np.float64))
        names = [names] if isinstance(names, str) else list(names)
        if pose.shape != (len(names), 5):
            raise InputError(f"{len(names)} type names need a pose table of shape "
                             f"({len(names)}, 5), got {pose.shape}")
        return cls(types, np.column_stack([types.codes(names), pose]))

    def __len__(self) -> int:
        return len(self.table)

    def __getitem__(self, idx) -> Conditions:
        return Conditions(self.types, self.table[idx])

    @property
    def codes(self) -> np.ndarray:
        return self.table[:, 0].astype(np.int64)

    @property
    def names(self) -> list[str]:
        names = self.types.names
        return [names[c] for c in self.codes]

    def recoded(self, to: TypeTable) -> np.ndarray:
        """The table with its type codes mapped (by name) into ``to``."""
        out = self.table.copy()
        out[:, 0] = self.types.recode(self.table[:, 0], to)
        return out


__all__ = ["Conditions", "RECORD_KEYS", "TypeTable", "each_once"]
