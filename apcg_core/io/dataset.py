"""The on-disk dataset format (documented in docs/DATASET.md), readable with numpy alone.

A shard is a standard ``.npz`` (an uncompressed zip of ``.npy`` arrays) written so that the
same content always gives the same bytes (fixed zip timestamps, fixed member order), first to
``NAME.part`` and then renamed: a file with its final name is always complete.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..depth import BACKGROUND, norm
from ..errors import InputError, check_int
from .atomic import atomic_path

FORMAT_VERSION = 1
SHARD_KEYS = ("sample_id", "conditions", "nu", "offsets", "pixel", "depth", "delta_range_m",
              "clipped", "n_clamped", "n_rays")
# A photon dataset's shards (a [sensor] in the config, SPEC section 8) also hold these; an
# ideal dataset's shards do not, and are byte-identical to those built before they existed.
PHOTON_KEYS = ("label", "count", "pulse", "target_offsets", "target_pixel", "target_signal_pe")
# An ideal dataset built with ``incidence = true`` also holds each point's cosine of incidence
# (what an incidence output is trained on, docs/DATASET.md); others do not.
INCIDENCE_KEYS = ("cos_incidence",)
OPTIONAL_KEYS = PHOTON_KEYS + INCIDENCE_KEYS
# Every shard built since shards record their dataset also holds this member (last): a short
# JSON string of digests of what in dataset.json determines the shard's bytes
# (``dataset_stamp``), so that a shard of another dataset of the same plan (another lidar,
# backend, sensor, ...) is told apart. Shards built before it have none (read, checked by
# their content: ``foreign_shard``).
STAMP_KEY = "dataset"
_EPOCH = (1980, 1, 1, 0, 0, 0)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes, part_suffix: str = ".part") -> None:
    """Write ``data`` to ``path`` through ``path`` + ``part_suffix`` + fsync + rename."""
    path = Path(path)
    with atomic_path(path, part_suffix) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    _fsync_dir(path.parent)


def _npz_member(name: str, arr) -> tuple[zipfile.ZipInfo, np.ndarray]:
    """A .npz member's zip entry (fixed date and mode: bytes that depend only on the array)
    and the array as np.save stores it (0-d kept, others C-contiguous)."""
    info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
    info.external_attr = 0o644 << 16
    a = np.asarray(arr)
    return info, a if a.ndim == 0 else np.ascontiguousarray(a)


def write_npz(path: Path, members, part_suffix: str = ".part") -> None:
    """An uncompressed .npz at ``path`` (through ``path`` + ``part_suffix`` + fsync + rename)
    of ``members``, (name, array or a function that makes it) pairs, each made, written into
    the file and let go in turn: memory holds one member at a time, not the whole file. For
    a job's own files (np.load reads them); a file whose bytes must depend only on its arrays
    is ``npz_bytes``'s."""
    path = Path(path)
    with atomic_path(path, part_suffix) as tmp, open(tmp, "wb") as f:
        with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED) as zf:
            for name, arr in members:
                info, a = _npz_member(name, arr() if callable(arr) else arr)
                with zf.open(info, "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, a, allow_pickle=False)
                del a
        f.flush()
        os.fsync(f.fileno())
    _fsync_dir(path.parent)


def npz_bytes(arrays: dict) -> bytes:
    """An uncompressed .npz of ``arrays`` (in the given order) whose bytes depend only on them.
    A 0-d array (a scene frame's ``meta``) stays 0-d, as ``np.savez`` stores it."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info, a = _npz_member(name, arr)
            member = io.BytesIO()
            np.lib.format.write_array(member, a, allow_pickle=False)
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def json_bytes(obj) -> bytes:
    return (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode()


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class Shard:
    """One shard's arrays (see docs/DATASET.md for each one's meaning)."""

    sample_id: np.ndarray  # (n,) int64
    conditions: np.ndarray  # (n, 6) float64 [type_code, range_m, elevation, pitch, yaw, roll] rad
    nu: np.ndarray  # (n, 6) float32, the cGAN's condition vector
    offsets: np.ndarray  # (n + 1,) int64: sample i owns points offsets[i]:offsets[i+1]
    pixel: np.ndarray  # (P,) uint16/uint32: row * W + col in the H x W depth image
    depth: np.ndarray  # (P,) float16: PC2Im depth d at that pixel (background -1 elsewhere)
    delta_range_m: np.ndarray  # (P,) float32: slant range minus r0 (metres)
    clipped: np.ndarray  # (n,) bool: the target's angular box reached beyond the window
    n_clamped: np.ndarray  # (n,) int32: target pixels whose depth was clamped into [-1+eps, 1]
    n_rays: np.ndarray  # (n,) int32: rays cast (0 for the points backend)
    # photon datasets only (docs/DATASET.md): per point 1 signal / 0 noise, the events in its
    # bin, its pulse (events output); per cell any sub-ray hit, the expected signal
    # photo-electrons per pulse, sample i owning target_offsets[i]:target_offsets[i+1]
    label: np.ndarray | None = None  # (P,) uint8
    count: np.ndarray | None = None  # (P,) int32
    pulse: np.ndarray | None = None  # (P,) int32
    target_offsets: np.ndarray | None = None  # (n + 1,) int64
    target_pixel: np.ndarray | None = None  # (T,) uint16/uint32
    target_signal_pe: np.ndarray | None = None  # (T,) float32
    # ideal datasets built with incidence = true: per point the cosine of the angle between
    # the cell's ray and the face it met
    cos_incidence: np.ndarray | None = None  # (P,) float16
    # the dataset it was built for (``dataset_stamp`` of its header; None: a shard built
    # before shards recorded it)
    dataset: str | None = None
    # (H, W) of the lidar whose header it was read under (``load_shard``), never stored: its
    # pixels are row * W + col of that image, so ``depth_images`` takes no other size
    image_size: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.sample_id)

    def to_bytes(self) -> bytes:
        keys = SHARD_KEYS + tuple(k for k in OPTIONAL_KEYS if getattr(self, k) is not None)
        arrays = {k: getattr(self, k) for k in keys}
        if self.dataset is not None:  # last: every array before it keeps its bytes
            arrays[STAMP_KEY] = np.array(self.dataset)
        return npz_bytes(arrays)

    @classmethod
    def load(cls, path) -> Shard:
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in SHARD_KEYS if k not in z.files]
                if missing:
                    raise InputError(f"dataset shard {path} lacks arrays {missing}; it is not "
                                     "an APCG shard or is from another format version")
                arrays = {k: z[k] for k in SHARD_KEYS + OPTIONAL_KEYS if k in z.files}
                if STAMP_KEY in z.files:
                    stamp = z[STAMP_KEY]
                    if stamp.ndim != 0 or stamp.dtype.kind != "U":
                        raise ValueError(f"its {STAMP_KEY} member is not a string")
                    arrays[STAMP_KEY] = str(stamp)
        except FileNotFoundError:
            raise InputError(f"dataset shard {path} is missing; run the same `apcg dataset "
                             "build` again to remake it") from None
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"dataset shard {path} is corrupt or unreadable ({exc}); delete "
                             "it and run the build again to remake it") from exc
        shard = cls(**arrays)
        n = len(shard.sample_id)
        if len(shard.offsets) != n + 1 or shard.offsets[-1] != len(shard.pixel):
            raise InputError(f"dataset shard {path} is inconsistent (offsets do not match the "
                             "points); delete it and build again")
        per_point = [k for k in ("label", "count", "pulse", "cos_incidence")
                     if getattr(shard, k) is not None
                     and len(getattr(shard, k)) != len(shard.pixel)]
        t_off, t_pix = shard.target_offsets, shard.target_pixel
        if per_point or (t_off is not None and (
                len(t_off) != n + 1 or t_pix is None or t_off[-1] != len(t_pix)
                or shard.target_signal_pe is None or len(shard.target_signal_pe) != len(t_pix))):
            raise InputError(f"dataset shard {path} is inconsistent (its per-point arrays "
                             f"{per_point or ['target_*']} do not match its points); delete it "
                             "and build again")
        return shard

    def depth_images(self, height: int, width: int, dtype=np.float16) -> np.ndarray:
        """Dense standard depth images (n, H, W), background -1 (PC2Im, eq. 15)."""
        self._check_image_size(height, width)
        n = len(self)
        img = np.full(n * height * width, BACKGROUND, dtype=dtype)
        s = np.repeat(np.arange(n), np.diff(self.offsets))
        img[s * height * width + self.pixel.astype(np.int64)] = self.depth
        return img.reshape(n, height, width)

    def _check_image_size(self, height, width) -> None:
        """Refuse an H x W other than the shard's lidar's (where it is known) or too small
        for its pixels: a pixel is row * W + col, so any other size moves pixels into other
        rows or the next sample's image."""
        height = check_int("depth image height", height, 1)
        width = check_int("depth image width", width, 1)
        top = int(self.pixel.max()) if len(self.pixel) else -1
        if self.image_size is not None and (height, width) != tuple(self.image_size):
            h, w = self.image_size
            raise InputError(f"depth images of {height} x {width} (H x W) not accepted: the "
                             f"shard's pixels are row * W + col of its lidar's {h} x {w} "
                             f"window (dataset.json lidar height = {h}, width = {w}); "
                             f"accepted: depth_images({h}, {w})")
        if top >= height * width:
            raise InputError(f"depth images of {height} x {width} (H x W) not accepted: the "
                             f"shard holds pixel {top}, outside an image of "
                             f"{height * width} pixels; accepted: the shard's lidar height "
                             "and width (dataset.json lidar)")

    def training_images(self, height: int, width: int, q) -> np.ndarray:
        """The normalised training images Norm(d) (eq. 17), float16 (n, H, W)."""
        return norm(self.depth_images(height, width), q)


def shard_agreement(a: Shard, b: Shard, tol_m: float = 2e-3) -> dict:
    """How two shards of the same samples (e.g. built by two backends) agree: cells (pixels) in
    both / in either, and among the common ones how many ranges lie within ``tol_m``."""
    if not np.array_equal(a.sample_id, b.sample_id):
        raise InputError("shards hold different samples; compare shards of the same plan")
    same = total = within = 0
    worst = 0.0
    for i in range(len(a)):
        xa, xb = slice(a.offsets[i], a.offsets[i + 1]), slice(b.offsets[i], b.offsets[i + 1])
        da = dict(zip(a.pixel[xa].tolist(), a.delta_range_m[xa].astype(float), strict=True))
        db = dict(zip(b.pixel[xb].tolist(), b.delta_range_m[xb].astype(float), strict=True))
        common = da.keys() & db.keys()
        same += len(common)
        total += len(da.keys() | db.keys())
        if common:
            diff = [abs(da[k] - db[k]) for k in common]
            worst = max(worst, max(diff))
            within += sum(x < tol_m for x in diff)
    return {"cells_common": same, "cells_either": total, "ranges_within_tol": within,
            "max_range_diff_m": worst}


def read_header(directory) -> dict:
    path = Path(directory) / "dataset.json"
    if not path.exists():
        raise InputError(f"{directory} is not an APCG dataset (no dataset.json); build one with "
                         "`apcg dataset build --config CFG -o DIR`")
    try:
        head = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path} is corrupt ({exc})") from exc
    missing = [k for k in HEADER_KEYS if k not in head] if isinstance(head, dict) else HEADER_KEYS
    if missing or head.get("format") != "apcg-dataset":
        raise InputError(f"{path} is not an APCG dataset header (missing or wrong: "
                         f"{', '.join(missing) or 'format'}); rebuild the dataset with "
                         "`apcg dataset build`")
    problem = header_problem(head)
    if problem:
        raise InputError(f"{path} is damaged: {problem}; rebuild the dataset with "
                         "`apcg dataset build`")
    return head


DATASET_FORMAT_VERSIONS = (1,)  # the header formats this reader knows
SPLITS = ("train", "test")


def _count(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def header_problem(head: dict) -> str | None:
    """What is wrong with a dataset header's values (every reader relies on them: the lidar,
    the types, the condition space, the shards and their counts), or None."""
    from ..condition import ConditionSpace
    from ..lidar import lidar_from_table
    from ..typetable import TypeTable
    if head["format_version"] not in DATASET_FORMAT_VERSIONS:
        return (f"format_version {head['format_version']!r} is not one this apcg reads "
                f"({', '.join(map(str, DATASET_FORMAT_VERSIONS))})")
    if not isinstance(head["config"], dict):
        return f"config must be the table the dataset was built from, got {head['config']!r}"
    from ..lidar import LIDAR_KEYS
    if isinstance(head["lidar"], dict) and set(head["lidar"]) != set(LIDAR_KEYS):
        return (f"its lidar records {sorted(head['lidar'])}; a dataset records every one of "
                f"{', '.join(LIDAR_KEYS)}")
    try:
        lidar_from_table(head["lidar"], source="its lidar")
        if not isinstance(head["types"], list):
            return f"types must be a list of type entries, got {type(head['types']).__name__}"
        types = TypeTable.from_records(head["types"], "its types")
        space = head["condition_space"]
        if not isinstance(space, dict):
            return f"condition_space must be a table, got {space!r}"
        space = ConditionSpace.from_dict(space)
    except InputError as exc:
        return str(exc)
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        return f"a value of the wrong kind ({type(exc).__name__}: {exc})"
    if space.n_types != len(types):
        return f"condition_space.n_types {space.n_types} but {len(types)} types"
    near = tuple(i for i, r in enumerate(types.records) if r.get("range_band") == "near")
    if "range_band" in types.records[0] and space.drone_types != near:
        return (f"condition_space.drone_types {list(space.drone_types)} but the types in the "
                f"near band are {list(near)}")
    counts = {k: head[k] for k in ("n_samples", "n_train", "n_test") if k in head}
    bad = [f"{k} = {v!r}" for k, v in counts.items() if not _count(v)]
    if bad:
        return f"{', '.join(bad)}: counts are integers >= 0"
    if "n_train" in counts and "n_test" in counts \
            and counts["n_train"] + counts["n_test"] != counts["n_samples"]:
        return (f"n_train {counts['n_train']} + n_test {counts['n_test']} is not n_samples "
                f"{counts['n_samples']}")
    return _shards_problem(head["shards"], head["n_samples"], len(types))


def _shards_problem(shards, n_samples: int, n_types: int) -> str | None:
    if not isinstance(shards, list):
        return f"shards must be a list, got {type(shards).__name__}"
    for i, sh in enumerate(shards):
        if not isinstance(sh, dict):
            return f"shard entry {i} is not a table: {sh!r}"
        missing = [k for k in ("file", "index", "n_samples", "split", "type_code")
                   if k not in sh]
        if missing:
            return f"shard entry {i} lacks {', '.join(missing)}"
        if sh["index"] != i or isinstance(sh["index"], bool):
            return f"shard entry {i} has index {sh['index']!r}"
        f = sh["file"]
        if not isinstance(f, str) or not f or Path(f).is_absolute() or ".." in Path(f).parts:
            return f"shard {i}'s file must be a path inside the dataset, got {f!r}"
        if not _count(sh["n_samples"]):
            return f"shard {i}'s n_samples must be an integer >= 0, got {sh['n_samples']!r}"
        if sh["split"] not in SPLITS:
            return f"shard {i}'s split must be one of {', '.join(SPLITS)}, got {sh['split']!r}"
        code = sh["type_code"]
        if isinstance(code, bool) or not isinstance(code, int) or not 0 <= code < n_types:
            return f"shard {i}'s type_code must be a type code 0..{n_types - 1}, got {code!r}"
    total = sum(sh["n_samples"] for sh in shards)
    if total != n_samples:
        return f"its shards hold {total} samples but n_samples is {n_samples}"
    return None


def read_manifest(directory) -> dict:
    """A finished dataset's manifest.json (each shard's size and hash); ``{"shards": []}``
    while the build has not finished. A damaged one is named."""
    path = Path(directory) / "manifest.json"
    if not path.exists():
        return {"shards": []}
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path} is corrupt ({exc}); delete it and run the same "
                         "`apcg dataset build` again to remake it") from exc
    if not isinstance(manifest, dict) or not isinstance(manifest.get("shards"), list):
        raise InputError(f"{path} is not an APCG manifest (no shard list); delete it and run "
                         "the same `apcg dataset build` again to remake it")
    return manifest


def check_complete(directory, head: dict | None = None) -> dict:
    """A finished dataset, as every reader of one takes it: its header, a manifest.json
    that lists every shard of the header (in its order, each with a hash) and every listed
    shard on disk. Returns the manifest; raises InputError naming what is not so."""
    directory = Path(directory)
    head = head if head is not None else read_header(directory)
    path = directory / "manifest.json"
    if not path.exists():
        raise InputError(f"dataset {directory} is not complete (no manifest.json); finish it "
                         "with the same `apcg dataset build` command first")
    manifest = read_manifest(directory)
    files = [s.get("file") for s in head["shards"] if isinstance(s, dict)]
    listed = [m.get("file") if isinstance(m, dict) else None for m in manifest["shards"]]
    if listed != files or not all(isinstance(m, dict) and isinstance(m.get("sha256"), str)
                                  for m in manifest["shards"]):
        raise InputError(f"{path} is corrupt: it lists {len(listed)} shards where dataset.json "
                         f"has {len(files)} (or not the same files, or without their hashes); "
                         "delete it and run the same `apcg dataset build` again to remake it")
    missing = [f for f in files if not (directory / f).exists()]
    if missing:
        raise InputError(f"dataset {directory} lacks {len(missing)} of its {len(files)} shards "
                         f"({', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''}); run "
                         "the same `apcg dataset build` again to remake them")
    return manifest


# conditions.csv's columns that say where each sample is and what it is
_INDEX_COLUMNS = ("sample_id", "shard", "type_code", "range_m", "elevation_deg", "pitch_deg",
                  "yaw_deg", "roll_deg")


@dataclass
class ConditionIndex:
    """conditions.csv as arrays: each sample's shard, type code and condition (angles in
    radians, as in a shard): what a shard read from the dataset is checked against."""

    shard: np.ndarray  # (N,) int64
    table: np.ndarray  # (N, 6) float64 [type_code, range_m, elevation, pitch, yaw, roll]


def read_condition_index(directory, head: dict) -> ConditionIndex:
    """The dataset's conditions.csv, checked against its header (one row per sample, in
    sample_id order)."""
    from .csv_table import NeedsCare, read_columns, read_csv
    directory = Path(directory)
    path = directory / head.get("conditions_file", "conditions.csv")
    if not path.exists():
        raise InputError(f"dataset {directory} has no {path.name}; run the same `apcg dataset "
                         "build` again to remake it")
    try:
        parts = list(read_columns(path, _INDEX_COLUMNS, numbers=_INDEX_COLUMNS))
        cols = {c: np.concatenate([p[c] for p in parts]) if parts else np.zeros(0)
                for c in _INDEX_COLUMNS}
    except NeedsCare:
        rows = read_csv(path, required=_INDEX_COLUMNS, what="dataset conditions table")
        cols = {c: np.array([r.float(c) for r in rows], np.float64) for c in _INDEX_COLUMNS}
    n = int(head["n_samples"])
    if len(cols["sample_id"]) != n or not np.array_equal(cols["sample_id"], np.arange(n)):
        raise InputError(f"{path} does not list samples 0 .. {n - 1} in order, one a row, as "
                         f"{directory / 'dataset.json'} says (n_samples {n}; found "
                         f"{len(cols['sample_id'])} rows); the two are from different builds: "
                         "build the dataset again")
    deg = np.pi / 180.0
    table = np.stack([cols["type_code"], cols["range_m"], *(cols[c] * deg for c in
                      ("elevation_deg", "pitch_deg", "yaw_deg", "roll_deg"))], axis=1)
    return ConditionIndex(cols["shard"].astype(np.int64), table)


# What a shard's stamp names, in the order a message lists what differs: each a part of the
# header that changes a shard's bytes with the same samples (``dataset_stamp``).
_STAMP_PARTS = ("lidar", "backend", "sensor", "supersample", "quantize", "incidence", "seed")


def _digest(value) -> str:
    return hashlib.sha256(json_bytes(value)).hexdigest()[:16]


def dataset_stamp(head: dict) -> str:
    """What a shard of the dataset whose header is ``head`` records of it (member
    ``STAMP_KEY``): digests of the parts of the header that determine a shard's bytes (the
    lidar, backend, sensor, supersample, quantize, incidence, seed, each named, and
    ``dataset``: the config (but its name and its sensor's name), lidar, condition space,
    sensor, supersample, reflectivity and the types' catalog entries and mesh digests
    together), as compact JSON. The builder stamps each shard with it; ``foreign_shard``
    compares it against the header the shard is read under."""
    cfg = head.get("config") if isinstance(head.get("config"), dict) else {}
    sensor = head.get("sensor")  # the sensor as resolved (none: ideal), not as the config names it
    # as the builder takes it (dataset_builder.build._task)
    supersample = cfg.get("supersample", 4 if sensor is not None else 1)
    # the config but its name (its file's) and its sensor's name: neither changes a byte
    config = {k: v for k, v in cfg.items() if k not in ("name", "sensor")}
    parts = {"lidar": head.get("lidar"), "backend": cfg.get("backend"), "sensor": sensor,
             "supersample": supersample, "quantize": cfg.get("quantize", True),
             "incidence": bool(cfg.get("incidence", False)), "seed": cfg.get("seed", 0),
             "dataset": {"config": config, "lidar": head.get("lidar"), "sensor": sensor,
                         "supersample": supersample,
                         "condition_space": head.get("condition_space"),
                         "reflectivity": head.get("reflectivity"),
                         "types": [_type_stamp(t) for t in head.get("types") or []]}}
    return json.dumps({k: _digest(v) for k, v in parts.items()}, sort_keys=True,
                      separators=(",", ":"))


def _type_stamp(t):
    """A type's part of the stamp: its catalog entry and, where the header records it (since
    stop 54), its mesh's digest; a header without it stamps as it always did."""
    if not isinstance(t, dict):
        return t
    own = [t.get("catalog_index"), t.get("depth_length_m")]
    return own + [t["mesh_sha256"]] if "mesh_sha256" in t else own


def foreign_shard(shard: Shard, head: dict) -> str | None:
    """Why ``shard`` is not of the dataset whose header is ``head`` although it may hold
    that dataset's samples (built with another lidar, backend, sensor, ...), or None. The one
    check of a shard against its header: every reader (``load_shard``) and a resumed build
    (``dataset_builder.build.not_this_shard``) go through it. A stamped shard's stamp must be
    the header's; every shard's content must fit the header (a shard built before shards
    were stamped is told by this alone): each pixel inside the header's W x H image, the
    photon arrays there exactly when the header has a sensor, ``cos_incidence`` exactly when
    the header's config has ``incidence = true``."""
    if shard.dataset is not None:
        try:
            got = json.loads(shard.dataset)
        except json.JSONDecodeError:
            got = None
        if not isinstance(got, dict):
            return f"its {STAMP_KEY} record is damaged"
        want = json.loads(dataset_stamp(head))
        if got != want:
            named = [k for k in _STAMP_PARTS if got.get(k) != want[k]]
            return ("built with another " + "/".join(named) if named
                    else "built from another config")
    lidar = head["lidar"]
    cells = int(lidar["width"]) * int(lidar["height"])
    for k in ("pixel", "target_pixel"):
        pix = getattr(shard, k)
        if pix is not None and len(pix) and int(pix.max()) >= cells:
            return (f"{k} values up to {int(pix.max())} where this dataset's "
                    f"{lidar['width']} x {lidar['height']} lidar has {cells} pixels: built "
                    "with another lidar")
    sensor = head.get("sensor")
    held = [k for k in PHOTON_KEYS if getattr(shard, k) is not None]
    if sensor is None and held:
        return f"photon arrays ({', '.join(held)}) in an ideal dataset: built with a sensor"
    if sensor is not None:
        need = ["label", "count", "target_offsets", "target_pixel", "target_signal_pe"]
        events = isinstance(sensor, dict) and sensor.get("output") == "events"
        if events:
            need.append("pulse")
        if missing := [k for k in need if getattr(shard, k) is None]:
            return (f"no {', '.join(missing)} where this dataset's sensor records them: "
                    "built without this dataset's sensor")
        if not events and shard.pulse is not None:
            return "per-event pulses where this dataset's sensor records points: built with " \
                   "another sensor"
    cfg = head.get("config") if isinstance(head.get("config"), dict) else {}
    if (shard.cos_incidence is not None) != bool(cfg.get("incidence", False)):
        return ("cos_incidence where this dataset has no incidence: built with incidence"
                if shard.cos_incidence is not None else
                "no cos_incidence where this dataset has incidence = true: built without it")
    return None


def load_shard(directory, entry: dict, index: ConditionIndex, head: dict | None = None) \
        -> Shard:
    """The shard of header ``entry`` (dataset.json's ``shards``; ``head`` is dataset.json),
    checked to be that shard of this dataset: its sample count and type code are the
    header's, its samples are the ones conditions.csv places in it, at their conditions, and
    it was built for this header (``foreign_shard``: another lidar, backend, sensor, ...). A
    shard copied over another, or from another dataset, is refused by name instead of being
    read as this one. ``head`` None: read from ``directory``."""
    head = head if head is not None else read_header(directory)
    path = Path(directory) / entry["file"]
    shard = Shard.load(path)
    ids = shard.sample_id.astype(np.int64)
    code = int(entry["type_code"])
    why = None
    if len(shard) != int(entry["n_samples"]):
        why = f"{len(shard)} samples where dataset.json lists {entry['n_samples']}"
    elif len(ids) and (ids.min() < 0 or ids.max() >= len(index.shard)):
        why = f"sample ids outside 0 .. {len(index.shard) - 1}"
    elif not np.all(index.shard[ids] == int(entry["index"])):
        why = f"samples that conditions.csv places in other shards than {entry['index']}"
    elif not (np.all(shard.conditions[:, 0] == code) and np.all(index.table[ids, 0] == code)):
        why = f"samples of another type than code {code}"
    elif not np.allclose(shard.conditions, index.table[ids], rtol=1e-9, atol=1e-9):
        why = "other conditions than conditions.csv lists for its samples"
    if why:
        raise InputError(f"dataset shard {path} is not this dataset's {entry['file']}: it holds "
                         f"{why}; it was copied from another shard or dataset. Delete it and "
                         "run the same `apcg dataset build` again to remake it")
    if (why := foreign_shard(shard, head)) is not None:
        raise InputError(f"dataset shard {path} is not this dataset's {entry['file']}: it "
                         f"belongs to another dataset ({why}). Delete it and run the same "
                         "`apcg dataset build` again to remake it")
    shard.image_size = (int(head["lidar"]["height"]), int(head["lidar"]["width"]))
    return shard


# What every reader of a dataset header relies on (dataset_builder.build.header_of writes it).
HEADER_KEYS = ["format", "format_version", "config", "lidar", "condition_space", "types",
               "n_samples", "shards"]
