"""The aircraft catalog: built-in types (facts in ``types.csv``) and the user's imported ones.

A type's ``index`` is its code in the condition vector and never changes: built-in types keep
their row number in ``types.csv`` (new rows are only appended), user types are numbered from
``USER_INDEX_START`` in the order they were added.
"""

from __future__ import annotations

import difflib
import functools
import hashlib
import json
import math
import os
import random
import re
import time
import unicodedata
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from ..condition import ConditionSpace
from ..errors import InputError
from ..io.atomic import atomic_path
from ..io.csv_table import read_csv
from ..lock import ProcessLock
from ..typetable import name_key, normalize_name, odd_characters
from .checks import check_size
from .mesh import Mesh, sample_surface

TYPES_CSV = Path(__file__).with_name("types.csv")
USER_INDEX_START = 1000
USER_CATEGORY = "user"  # the category of an imported type unless one of the built-in ones
FINE_CLOUD_POINTS = 10_000


@dataclass(frozen=True)
class AircraftType:
    index: int
    name: str
    kind: str  # "aircraft" or "drone"
    range_band: str  # "far" (3-18 km) or "near" (100-600 m): which Table 1 range applies
    category: str
    length_m: float
    span_m: float
    height_m: float
    manufacturer: str = ""
    dims_note: str = ""
    n_engines: str = ""
    propulsion: str = ""
    engine_placement: str = ""
    wing_position: str = ""
    tail_type: str = ""
    sweep_deg: float | None = None
    sweep_ref: str = ""
    n_rotors: str = ""
    rotor_diameter_m: float | None = None
    diagonal_wheelbase_m: float | None = None
    confidence: str = ""
    source: str = "builtin"  # or the path of the imported model for user types
    # diffuse reflectivity at the lidar's wavelength (SPEC section 8); None: the category's
    # default (apcg_core/sensor/reflectivity.py)
    reflectivity: float | None = None

    def summary(self) -> dict:
        return {"name": self.name, "index": self.index, "kind": self.kind,
                "category": self.category, "length_m": self.length_m, "span_m": self.span_m,
                "height_m": self.height_m, "range_band": self.range_band,
                "source": self.source, "reflectivity": self.effective_reflectivity}

    @property
    def effective_reflectivity(self) -> float:
        """Its own reflectivity, else its category's default (SPEC section 8)."""
        from ..sensor.reflectivity import reflectivity_of
        return reflectivity_of(self)


_TEXT_COLUMNS = ("manufacturer", "dims_note", "n_engines", "propulsion", "engine_placement",
                 "wing_position", "tail_type", "sweep_ref", "n_rotors", "confidence")


def _load_builtin() -> list[AircraftType]:
    table = read_csv(TYPES_CSV, required=("index", "name", "kind", "range_band", "category",
                                          "length_m", "span_m", "height_m", *_TEXT_COLUMNS,
                                          "sweep_deg", "rotor_diameter_m",
                                          "diagonal_wheelbase_m"), what="type table")
    return [AircraftType(
        index=row.int("index"), name=row.text("name"), kind=row.text("kind"),
        range_band=row.text("range_band"), category=row.text("category"),
        length_m=row.float("length_m"), span_m=row.float("span_m"),
        height_m=row.float("height_m"), sweep_deg=row.float("sweep_deg", optional=True),
        rotor_diameter_m=row.float("rotor_diameter_m", optional=True),
        diagonal_wheelbase_m=row.float("diagonal_wheelbase_m", optional=True),
        **{k: row[k] for k in _TEXT_COLUMNS}) for row in table]


def mesh_file_stem(name) -> str:
    """The file name (no suffix) of a user type's mesh: its name key where that is plain
    letters and digits, else the key made safe plus a digest of the key, so that two names
    share a file exactly when they are the same name."""
    key = name_key(name)
    safe = "".join(c if c.isalnum() else "_" for c in key)[:80]
    if safe != key:
        safe += "-" + hashlib.sha256(key.encode()).hexdigest()[:10]
    return safe


def user_dir() -> Path:
    """Where user types live: $APCG_DATA_DIR/catalog, else ~/.local/share/apcg/catalog."""
    base = os.environ.get("APCG_DATA_DIR")
    root = Path(base) if base else Path(os.environ.get("XDG_DATA_HOME",
                                                       Path.home() / ".local" / "share")) / "apcg"
    return root / "catalog"


@contextmanager
def _database_file(path, suffix: str = ".part"):
    """atomic_path for the user catalog's own files, which a change of the catalog replaces
    by design (under its lock): the running command's output guard, where there is one, is
    told so, and the file appears at once (other processes read the registry meanwhile)."""
    from .. import outputs
    guard = getattr(outputs, "active", lambda: None)()
    if guard is not None and hasattr(guard, "allow_update"):
        guard.allow_update(path)
    with atomic_path(path, suffix=suffix) as tmp:
        yield tmp


REGISTRY = "user_types.json"
# The highest index a user type ever had in this catalog (a removed type's index is never
# handed to the next: a script's `--type 1013` must not turn into another aircraft). A catalog
# from before this file: the highest index its registry holds.
LAST_INDEX = "last_index"
LOCK_WAIT_S = 120.0  # how long a catalog change waits for another process's change to end
# A registry entry: field -> (accepted types, required). The rest of AircraftType is optional.
_ENTRY_FIELDS = {f.name: f for f in fields(AircraftType)}
_REQUIRED = ("index", "name", "kind", "range_band", "category", "length_m", "span_m",
             "height_m")


def index_key(key) -> int | None:
    """``key`` as a catalog index, or None where it is a name: an integer (not a bool), or a
    text of ASCII digits with an optional sign (a signed whole number is an index; names hold
    a letter; '²' and a fullwidth '５' pass str.isdigit but are no index). The one reading of
    it: :meth:`Catalog.get` and the models' type lookups."""
    if isinstance(key, str):
        return int(key.strip()) if re.fullmatch(r"[+-]?[0-9]+", key.strip()) else None
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        return int(key)
    return None



def mesh_digest(mesh) -> str:
    """SHA-256 of a mesh's float64 vertices and int64 faces: the geometry a result was cast
    against. A user type replaced (`apcg catalog add --force`) by another mesh of the same
    name and size changes nothing else a result records; without it a resumed build mixed
    the two meshes' shards under one stamp (probe finding, stop 54), and a resumed sequence
    its frames (stop 55)."""
    h = hashlib.sha256(np.ascontiguousarray(mesh.vertices, "<f8").tobytes())
    h.update(np.ascontiguousarray(mesh.faces, "<i8").tobytes())
    return h.hexdigest()

class Catalog:
    """All types known to this process: built-in, then the user's.

    The user's types are a small database in :attr:`user_path`: ``user_types.json`` (the
    registry) and one ``.npz`` mesh per type. Every change (:meth:`add_user_type`,
    :meth:`remove_user_type`) holds a lock on the folder, reads the registry as it is on disk
    then, and replaces it atomically, so changes from several processes at once are never lost.
    """

    def __init__(self, user_path: Path | None = None, include_user: bool = True) -> None:
        self.user_path = Path(user_path) if user_path else user_dir()
        self.include_user = include_user
        self._builtin: list[AircraftType] = _load_builtin()
        self._set_types(self._builtin + (self._load_user() if include_user else []))
        self._meshes: dict[int, Mesh] = {}
        self.last_replaced: AircraftType | None = None  # by the last add_user_type (force)

    def _set_types(self, types: list[AircraftType]) -> None:
        self.types = types
        self._by_name = {normalize_name(t.name).casefold(): t for t in types}
        self._by_key = {name_key(t.name): t for t in types}
        self._by_index = {t.index: t for t in types}

    # --- lookup ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.types)

    def __iter__(self):
        return iter(self.types)

    def names(self) -> list[str]:
        return [t.name for t in self.types]

    def get(self, key) -> AircraftType:
        """A type by name (case-insensitive, outer spaces ignored; a user type also by its
        name key, see :func:`name_key`) or index (an int, or a string of digits: no type is
        named by a number); unknown keys name close matches."""
        if isinstance(key, AircraftType):
            return key
        if (index := index_key(key)) is not None:
            key = index
            if int(key) in self._by_index:
                return self._by_index[int(key)]
            raise InputError(f"unknown type index {key}; accepted: 0 .. "
                             f"{max(t.index for t in self.types if t.source == 'builtin')} "
                             "(built-in) and the user types listed by `apcg catalog list`")
        t = self._by_name.get(normalize_name(key).casefold())
        if t is None:
            t = self._by_key.get(name_key(key))
        if t is None:
            close = difflib.get_close_matches(str(key), self.names(), n=4, cutoff=0.5)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise InputError(f"unknown aircraft type {key!r}{hint} "
                             "(`apcg catalog list` shows all types)")
        return t

    # --- geometry --------------------------------------------------------------------------
    def mesh(self, key) -> Mesh:
        """The type's mesh in the body frame (metres, origin at the centre of mass); cached."""
        t = self.get(key)
        if t.index not in self._meshes:
            if t.source == "builtin":
                from .builders import build
                self._meshes[t.index] = build(t).mesh
            else:
                self._meshes[t.index] = self._read_user_mesh(t)
        return self._meshes[t.index]

    def mesh_record(self, key) -> dict:
        """What stamps the type's geometry into a stored result made from it (a dataset's
        header, a sequence's record, a model's type table): ``{"mesh_sha256": ...}``
        (:func:`mesh_digest`) for a user type, whose mesh ``catalog add --force`` may replace
        under the same name and size; ``{}`` for a built-in type, whose mesh is its catalog
        entry and this version's builders, and whose float64 vertices, computed with numpy's
        sines and cosines, may differ in the last bit between CPUs (numpy's float64 sin and
        cos take other code on AVX-512), which would make one plan's header differ between
        the machines of one job array."""
        t = self.get(key)
        return {} if t.source == "builtin" else {"mesh_sha256": mesh_digest(self.mesh(t))}

    def depth_length_m(self, key) -> float:
        """l of PC2Im (SPEC section 5): the fuselage length; for drones the largest horizontal
        dimension of the model (rotor discs included, so depths stay inside [-1, 1])."""
        t = self.get(key)
        if t.kind == "drone":
            ext = self.mesh(t).extents
            return float(max(ext[0], ext[1]))
        return float(t.length_m)

    def fine_cloud(self, key, n: int = FINE_CLOUD_POINTS, seed: int = 0) -> np.ndarray:
        """The paper's 'fine point cloud': n points on the surface, area-weighted, seeded."""
        return sample_surface(self.mesh(key), n, seed)

    def condition_space(self, **ranges) -> ConditionSpace:
        """The Table 1 condition space over every type of this catalog (codes 0 .. n-1 in
        catalog order); near-band types (small drones) use the drone range."""
        near = tuple(i for i, t in enumerate(self.types) if t.range_band == "near")
        return ConditionSpace(n_types=len(self.types), drone_types=near, **ranges)

    # --- user types: files -----------------------------------------------------------------
    def _registry(self) -> Path:
        return self.user_path / REGISTRY

    def _user_mesh_file(self, name: str) -> Path:
        return self.user_path / f"{mesh_file_stem(name)}.npz"

    def _legacy_mesh_file(self, name: str) -> Path:
        """Where catalogs written before name keys kept a type's mesh."""
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        return self.user_path / f"{safe}.npz"

    def _read_user_mesh(self, t: AircraftType) -> Mesh:
        path = self._user_mesh_file(t.name)
        if not path.exists() and self._legacy_mesh_file(t.name).exists():
            path = self._legacy_mesh_file(t.name)
        fix = (f"add the type again (apcg catalog add MODEL --name {t.name!r} --force), or "
               f"remove it (apcg catalog remove {t.name!r})")
        if not path.exists():
            raise InputError(f"the mesh of user type {t.name!r} ({path}) is missing; {fix}")
        try:
            with np.load(path, allow_pickle=False) as z:
                return Mesh(z["vertices"], z["faces"])
        except Exception as exc:  # noqa: BLE001 - zipfile, numpy and KeyError on a bad file
            raise InputError(f"the mesh of user type {t.name!r} ({path}) is damaged "
                             f"({type(exc).__name__}); {fix}") from exc

    def _damaged(self, what: str) -> InputError:
        reg = self._registry()
        return InputError(
            f"the user catalog {reg} is damaged: {what}; fix that entry in a text editor, or "
            f"move the file aside (mv '{reg}' '{reg}.bad') and add your types again with "
            f"`apcg catalog add` (their meshes stay in {self.user_path})")

    def _read_registry(self) -> list[AircraftType]:
        """The user types as the registry holds them now; a damaged registry (not JSON, cut
        short, an entry short of a field or with a wrong value) is named with the fix."""
        reg = self._registry()
        try:
            text = reg.read_bytes().decode("utf-8-sig")
        except FileNotFoundError:
            return []
        except UnicodeDecodeError:
            raise self._damaged("it is not UTF-8 text") from None
        if not text.strip():
            raise self._damaged("it is empty")
        try:
            entries = json.loads(text)
        except json.JSONDecodeError as exc:
            raise self._damaged(f"not valid JSON (line {exc.lineno}, column {exc.colno}: "
                                f"{exc.msg}; cut short?)") from None
        if not isinstance(entries, list):
            raise self._damaged(f"it holds a JSON {type(entries).__name__}, not a list of "
                                "types")
        types, keys, indices = [], {}, set()
        for i, e in enumerate(entries):
            t = self._entry(i, e)
            if t.index in indices:
                raise self._damaged(f"entry {i + 1} ({t.name!r}) repeats the index {t.index}")
            if name_key(t.name) in keys:
                raise self._damaged(f"entry {i + 1} ({t.name!r}) has the same name as "
                                    f"{keys[name_key(t.name)]!r}")
            indices.add(t.index)
            keys[name_key(t.name)] = t.name
            types.append(t)
        return types

    def _entry(self, i: int, e) -> AircraftType:
        at = f"entry {i + 1}"
        if not isinstance(e, dict):
            raise self._damaged(f"{at} is a JSON {type(e).__name__}, not an object")
        if isinstance(e.get("name"), str):
            at += f" ({e['name']!r})"
        missing = [k for k in _REQUIRED if k not in e]
        if missing:
            raise self._damaged(f"{at} has no {', '.join(missing)}")
        unknown = [k for k in e if k not in _ENTRY_FIELDS]
        if unknown:
            raise self._damaged(f"{at} has fields this version does not know: "
                                f"{', '.join(unknown)}")
        idx = e["index"]
        if not isinstance(idx, int) or isinstance(idx, bool) or idx < USER_INDEX_START:
            raise self._damaged(f"{at}: index {idx!r} is not a whole number >= "
                                f"{USER_INDEX_START}")
        name = e["name"]
        if not isinstance(name, str) or not name_key(name) or name.strip().isdigit():
            raise self._damaged(f"{at}: name {name!r} is not a type name")
        if e["kind"] not in ("aircraft", "drone"):
            raise self._damaged(f"{at}: kind {e['kind']!r} is not 'aircraft' or 'drone'")
        if e["range_band"] not in ("far", "near"):
            raise self._damaged(f"{at}: range_band {e['range_band']!r} is not 'far' or 'near'")
        for k, v in e.items():
            if k in ("index", "name", "kind", "range_band"):
                continue
            if k == "reflectivity":
                ok = v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)
                                   and math.isfinite(v) and 0 < v <= 1)
                if not ok:
                    raise self._damaged(f"{at}: reflectivity {v!r} is not a number in (0, 1] "
                                        "(or null)")
                continue
            if k.endswith("_m") or k.endswith("_deg"):
                finite = (isinstance(v, (int, float)) and not isinstance(v, bool)
                          and math.isfinite(v))
                if k in _REQUIRED and not (finite and v >= 0):
                    raise self._damaged(f"{at}: {k} {v!r} is not a number >= 0")
                if k not in _REQUIRED and not (v is None or finite):
                    raise self._damaged(f"{at}: {k} {v!r} is not a number (or null)")
            elif not isinstance(v, str):
                raise self._damaged(f"{at}: {k} {v!r} is not text")
        return AircraftType(**{**e, "name": normalize_name(name)})

    def _last_index(self) -> int:
        """The highest index a user type ever had here (``LAST_INDEX``), or -1; a damaged
        record is named (it would hand out an index again)."""
        path = self.user_path / LAST_INDEX
        try:
            text = path.read_text().strip()
        except FileNotFoundError:
            return -1
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{path} cannot be read ({exc})") from None
        if not text.isdigit() or not text.isascii():
            raise InputError(f"{path} is damaged (it holds {text[:40]!r}, not an index); write "
                             "the highest type index your catalog ever had into it, or delete "
                             "it if no type was ever removed")
        return int(text)

    def _load_user(self) -> list[AircraftType]:
        return self._read_registry()

    def _write_registry(self, users: list[AircraftType]) -> None:
        with _database_file(self._registry()) as tmp:
            tmp.write_text(json.dumps([asdict(u) for u in users], indent=1,
                                      ensure_ascii=False) + "\n", encoding="utf-8")

    @contextmanager
    def _changing(self):
        """Hold the user catalog's lock (waiting up to LOCK_WAIT_S for another process's
        change), yield the user types as they are on disk now, and take the result in."""
        lock = ProcessLock(self.user_path / ".lock", "change of the user catalog")
        deadline = time.monotonic() + LOCK_WAIT_S
        while True:
            try:
                lock.acquire()
                break
            except InputError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.02 + 0.05 * random.random())
        try:
            users = self._read_registry()
            yield users
        finally:
            lock.release()
        self._set_types(self._builtin + users)

    # --- user types: changes ---------------------------------------------------------------
    def _conflict(self, name: str, force: bool, users=None,
                  given: str | None = None, lookalike: bool = False) -> AircraftType | None:
        """The user type that ``name`` would replace (with ``force``), or None; a built-in
        type of that name, or a user type without ``force``, is refused naming it. With
        ``lookalike`` a built-in type whose name reads the same once compatibility forms are
        folded (NFKC: 'Ａ320neo' is 'A320neo') is refused too."""
        key = name_key(name)
        shown = name if given is None else given
        folded = name_key(unicodedata.normalize("NFKC", name)) if lookalike else key
        same = next((t for t in self._builtin if name_key(t.name) in (key, folded)), None)
        if same is not None:
            raise InputError(f"type name {shown!r}: a built-in type named {same.name!r} "
                             "already exists (names are compared ignoring case, spaces, '-' "
                             "and '_'); choose another --name")
        users = self.types[len(self._builtin):] if users is None else users
        same = next((t for t in users if name_key(t.name) in (key, folded)), None)
        if same is not None and not force:
            raise InputError(f"type name {shown!r}: a type named {same.name!r} already exists "
                             "(names are compared ignoring case, spaces, '-' and '_'); choose "
                             f"another --name, or --force to replace {same.name!r}")
        return same

    def categories(self) -> list[str]:
        """The categories a type may have: the built-in types' and ``user``."""
        return sorted({t.category for t in self._builtin}) + [USER_CATEGORY]

    def check_new_type(self, name: str, kind: str, force: bool = False,
                       category: str | None = None) -> str:
        """Refuse a name, kind or category a new user type cannot have (before any file is
        read); return the name as it will be stored (normalised: NFC, outer spaces
        stripped)."""
        if kind not in ("aircraft", "drone"):
            raise InputError(f"kind must be 'aircraft' or 'drone', got {kind!r}")
        if category is not None and category not in self.categories():
            close = difflib.get_close_matches(str(category), self.categories(), n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise InputError(f"category {category!r} unknown{hint}; accepted: "
                             f"{', '.join(self.categories())}")
        if any("\ud800" <= c <= "\udfff" for c in str(name)):  # undecodable bytes of argv
            raise InputError(f"type name {name!r} not accepted: it is not valid UTF-8 text; "
                             "give the name in UTF-8")
        clean = normalize_name(name)
        if not name_key(clean) or clean.isdigit() or any(c in clean for c in "/\\\0") \
                or re.fullmatch(r"[+-]?[0-9]+", clean):
            raise InputError(f"type name {name!r} not accepted: it must have a letter or "
                             "digit, not be a number such as 7, +7 or -5 (numbers are catalog "
                             "indices) and have no '/' or '\\'")
        what = odd_characters(clean)
        if what:
            raise InputError(f"type name {name!r} not accepted: it holds {what}")
        # a name that reads as another (a fullwidth 'Ａ', a ligature) is that name
        self._conflict(clean, force, given=name, lookalike=True)
        return clean

    def add_user_type(self, name: str, mesh: Mesh, kind: str, category: str,
                      source: str, force: bool = False,
                      unit_scale: float = 1.0, reflectivity: float | None = None
                      ) -> AircraftType:
        """Register an imported model as a new type (stored under :attr:`user_path`).

        A size implausible for ``kind`` (checks.SIZE_LIMITS_M) is refused, with the likely unit
        (``unit_scale``: the metres per file unit the mesh was scaled by), unless ``force``;
        a user type of the same name (:func:`name_key`) is refused unless ``force``, which
        replaces it (its index kept)."""
        name = self.check_new_type(name, kind, force, category)
        if reflectivity is not None:
            from ..sensor.reflectivity import check_reflectivity
            reflectivity = check_reflectivity(reflectivity, "--reflectivity")
        check_size(mesh.extents, kind, force, unit_scale, name=repr(name))
        ext = mesh.extents
        band = "near" if kind == "drone" and max(ext[0], ext[1]) < 5.0 else "far"
        with self._changing() as users:
            old = self._conflict(name, force, users)
            index = old.index if old is not None else \
                max([USER_INDEX_START - 1, self._last_index()] + [t.index for t in users]) + 1
            t = AircraftType(index=index, name=name, kind=kind, range_band=band,
                             category=category, length_m=float(ext[0]), span_m=float(ext[1]),
                             height_m=float(ext[2]), source=str(source),
                             reflectivity=reflectivity)
            with _database_file(self._user_mesh_file(name), suffix=".part.npz") as tmp:
                np.savez(tmp, vertices=mesh.vertices, faces=mesh.faces)
            if old is not None:
                users[users.index(old)] = t
            else:
                users.append(t)
            if index > self._last_index():
                with _database_file(self.user_path / LAST_INDEX) as tmp:
                    tmp.write_text(f"{index}\n")
            self._write_registry(users)
            if old is not None and self._legacy_mesh_file(old.name) != \
                    self._user_mesh_file(name):
                self._legacy_mesh_file(old.name).unlink(missing_ok=True)
        self._meshes.pop(index, None)
        self.last_replaced = old
        return t

    def remove_user_type(self, name: str) -> AircraftType:
        """Remove a user type (its registry entry, then its mesh); built-in types stay."""
        with self._changing() as users:
            key = name_key(name)
            t = next((u for u in users if name_key(u.name) == key), None)
            if t is None:
                if any(name_key(b.name) == key for b in self._builtin):
                    raise InputError(f"{name!r} is a built-in type; only your own types can "
                                     "be removed")
                known = ", ".join(repr(u.name) for u in users) or "none"
                raise InputError(f"no user type named {name!r}; your types: {known}")
            users.remove(t)
            self._write_registry(users)
            for f in {self._user_mesh_file(t.name), self._legacy_mesh_file(t.name)}:
                f.unlink(missing_ok=True)
        self._meshes.pop(t.index, None)
        return t


@functools.lru_cache(maxsize=1)
def default_catalog() -> Catalog:
    """The process-wide catalog (built-in and user types), built lazily and cached."""
    return Catalog()
