"""The aircraft catalog: built-in types (facts in ``types.csv``) and the user's imported ones.

A type's ``index`` is its code in the condition vector and never changes: built-in types keep
their row number in ``types.csv`` (new rows are only appended), user types are numbered from
``USER_INDEX_START`` in the order they were added.
"""

from __future__ import annotations

import csv
import difflib
import functools
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..condition import ConditionSpace
from ..errors import InputError
from .mesh import Mesh

TYPES_CSV = Path(__file__).with_name("types.csv")
USER_INDEX_START = 1000
FINE_CLOUD_POINTS = 10_000


def _f(v):
    return float(v) if v not in (None, "") else None


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

    def summary(self) -> dict:
        return {"name": self.name, "index": self.index, "kind": self.kind,
                "category": self.category, "length_m": self.length_m, "span_m": self.span_m,
                "height_m": self.height_m, "range_band": self.range_band,
                "source": self.source}


def _load_builtin() -> list[AircraftType]:
    out = []
    with open(TYPES_CSV, newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            out.append(AircraftType(
                index=int(row["index"]), name=row["name"], kind=row["kind"],
                range_band=row["range_band"], category=row["category"],
                length_m=float(row["length_m"]), span_m=float(row["span_m"]),
                height_m=float(row["height_m"]), manufacturer=row["manufacturer"],
                dims_note=row["dims_note"], n_engines=row["n_engines"],
                propulsion=row["propulsion"], engine_placement=row["engine_placement"],
                wing_position=row["wing_position"], tail_type=row["tail_type"],
                sweep_deg=_f(row["sweep_deg"]), sweep_ref=row["sweep_ref"],
                n_rotors=row["n_rotors"], rotor_diameter_m=_f(row["rotor_diameter_m"]),
                diagonal_wheelbase_m=_f(row["diagonal_wheelbase_m"]),
                confidence=row["confidence"]))
    return out


def user_dir() -> Path:
    """Where user types live: $APCG_DATA_DIR/catalog, else ~/.local/share/apcg/catalog."""
    base = os.environ.get("APCG_DATA_DIR")
    root = Path(base) if base else Path(os.environ.get("XDG_DATA_HOME",
                                                       Path.home() / ".local" / "share")) / "apcg"
    return root / "catalog"


class Catalog:
    """All types known to this process: built-in, then the user's."""

    def __init__(self, user_path: Path | None = None, include_user: bool = True) -> None:
        self.user_path = Path(user_path) if user_path else user_dir()
        self.types: list[AircraftType] = _load_builtin()
        if include_user:
            self.types += self._load_user()
        self._by_name = {t.name.lower(): t for t in self.types}
        self._by_index = {t.index: t for t in self.types}
        self._meshes: dict[int, Mesh] = {}

    # --- lookup ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.types)

    def __iter__(self):
        return iter(self.types)

    def names(self) -> list[str]:
        return [t.name for t in self.types]

    def get(self, key) -> AircraftType:
        """A type by name (case-insensitive, outer spaces ignored) or index (an int, or a
        string of digits: no type is named by a number); unknown keys name close matches."""
        if isinstance(key, AircraftType):
            return key
        if isinstance(key, str) and key.strip().isdigit():
            key = int(key.strip())
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            if int(key) in self._by_index:
                return self._by_index[int(key)]
            raise InputError(f"unknown type index {key}; accepted: 0 .. "
                             f"{max(t.index for t in self.types if t.source == 'builtin')} "
                             "(built-in) and the user types listed by `apcg catalog list`")
        t = self._by_name.get(str(key).strip().lower())
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
                with np.load(self._user_mesh_file(t.name)) as z:
                    self._meshes[t.index] = Mesh(z["vertices"], z["faces"])
        return self._meshes[t.index]

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

    # --- user types ------------------------------------------------------------------------
    def _registry(self) -> Path:
        return self.user_path / "user_types.json"

    def _user_mesh_file(self, name: str) -> Path:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        return self.user_path / f"{safe}.npz"

    def _load_user(self) -> list[AircraftType]:
        reg = self._registry()
        if not reg.exists():
            return []
        try:
            entries = json.loads(reg.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"the user catalog {reg} is corrupt ({exc}); fix or delete it"
                             ) from exc
        return [AircraftType(**e) for e in entries]

    def check_new_type(self, name: str, kind: str) -> None:
        """Refuse a name or kind a new user type cannot have (before any file is read)."""
        if name.lower() in self._by_name:
            raise InputError(f"a type named {name!r} already exists; choose another --name")
        if kind not in ("aircraft", "drone"):
            raise InputError(f"kind must be 'aircraft' or 'drone', got {kind!r}")
        if not name.strip() or name.strip().isdigit() or any(c in name for c in "/\\\0"):
            raise InputError(f"type name {name!r} not accepted: it must be non-empty, not a "
                             "number (numbers are catalog indices) and have no '/' or '\\'")

    def add_user_type(self, name: str, mesh: Mesh, kind: str, category: str,
                      source: str, force: bool = False,
                      unit_scale: float = 1.0) -> AircraftType:
        """Register an imported model as a new type (stored under :attr:`user_path`).

        A size implausible for ``kind`` (checks.SIZE_LIMITS_M) is refused, with the likely unit
        (``unit_scale``: the metres per file unit the mesh was scaled by), unless ``force``."""
        from .checks import check_size

        self.check_new_type(name, kind)
        check_size(mesh.extents, kind, force, unit_scale, name=repr(name))
        users = [t for t in self.types if t.source != "builtin"]
        index = max([USER_INDEX_START - 1] + [t.index for t in users]) + 1
        ext = mesh.extents
        band = "near" if kind == "drone" and max(ext[0], ext[1]) < 5.0 else "far"
        t = AircraftType(index=index, name=name, kind=kind, range_band=band,
                         category=category, length_m=float(ext[0]), span_m=float(ext[1]),
                         height_m=float(ext[2]), source=str(source))
        self.user_path.mkdir(parents=True, exist_ok=True)
        tmp = self._user_mesh_file(name).with_suffix(".tmp.npz")
        np.savez(tmp, vertices=mesh.vertices, faces=mesh.faces)
        os.replace(tmp, self._user_mesh_file(name))
        entries = [asdict(u) for u in users] + [asdict(t)]
        tmp = self._registry().with_suffix(".tmp")
        tmp.write_text(json.dumps(entries, indent=1))
        os.replace(tmp, self._registry())  # atomic: never a half-written registry
        self.types.append(t)
        self._by_name[name.lower()] = t
        self._by_index[index] = t
        return t


def sample_surface(mesh: Mesh, n: int, seed: int = 0, return_faces: bool = False):
    """n points uniformly on the surface (faces chosen by area, uniform barycentrics);
    with ``return_faces`` also the face each point lies on."""
    rng = np.random.default_rng(seed)
    areas = mesh.face_areas
    face = rng.choice(len(areas), size=n, p=areas / areas.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    tri = mesh.vertices[mesh.faces[face]]
    pts = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return (pts, face) if return_faces else pts


@functools.lru_cache(maxsize=1)
def default_catalog() -> Catalog:
    """The process-wide catalog (built-in and user types), built lazily and cached."""
    return Catalog()
