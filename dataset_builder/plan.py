"""A dataset's plan, fixed by its TOML config and seed: types, conditions, split and shards.

Everything here is deterministic: the same config gives the same plan, whatever machine, worker
count or interruption; the shards are then pure functions of the plan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apcg_core.condition import ConditionSpace
from apcg_core.errors import InputError
from apcg_core.io.toml_file import read_toml
from apcg_core.lidar import DEG, LidarParams
from apcg_core.options import Rule

from .schema import check_config, resolve_sensor

CONFIG_DIR = Path(__file__).with_name("configs")
# The nesting order of a grid's product: it decides which sample gets which id, so it stays as
# it is. It is not an angle order (that is ATTITUDE, SPEC section 3).
GRID_FIELDS = ("elevation", "range_m", "yaw", "pitch", "roll")
_DEFAULT_COUNTS = {"elevation": 5, "range_m": 10, "yaw": 10, "pitch": 5, "roll": 5}
# One config is planned in memory: its table is 48 bytes a sample, but the plan as a whole
# (split, shards, checks) peaks near 200 (a 2 x 10^6-sample grid: 384 MiB peak RSS, stop 50):
# 10^7 samples plan in about 2 GB. Beyond this, split a config into several (other seeds);
# 10^8 ran a 23 GB machine out of memory before its first shard.
MAX_SAMPLES = 10**7


def builtin_configs() -> list[str]:
    return sorted(p.stem for p in CONFIG_DIR.glob("*.toml"))


def config_path(ref: str) -> Path:
    """The file of a config given by path or by the name of a committed one."""
    path = Path(ref)
    if not path.is_file():  # a folder called "demo" in the working directory is not a config
        path = CONFIG_DIR / f"{ref}.toml"
    return path


def load_config(ref: str) -> dict:
    """A config by file path or by the name of a committed one (``demo``, ``paper-table1``...)."""
    path = config_path(ref)
    if not path.is_file():
        raise InputError(f"no dataset config {ref!r}: give a TOML file or one of "
                         f"{', '.join(builtin_configs())}")
    cfg = read_toml(path, f"dataset config {path}")
    sensor = cfg.get("sensor")
    if isinstance(sensor, str) and sensor.strip():
        # a sensor file named relative to the config is found beside it, as a scene file's
        # trajectories are, whatever directory the build runs from
        beside = path.parent / Path(sensor.strip()).expanduser()
        from apcg_core.sensor.params import PRESET_DIR
        from apcg_core.typetable import find_preset
        if find_preset(sensor, PRESET_DIR) is None and beside.is_file():
            cfg["sensor"] = str(beside)
    check_config(cfg, f"dataset config {path}")
    cfg.setdefault("name", path.stem)
    return cfg


@dataclass
class ShardPlan:
    index: int
    split: str
    type_code: int
    rows: np.ndarray  # sample ids (rows of the condition table)

    @property
    def file(self) -> str:
        return f"shards/{self.split}-{self.index:05d}.npz"


@dataclass
class Plan:
    config: dict
    lidar: LidarParams
    space: ConditionSpace
    types: list  # AircraftType, in dataset code order
    table: np.ndarray  # (N, 6) float64 [type_code, range_m, elevation, pitch, yaw, roll] rad
    split: np.ndarray  # (N,) "train" / "test"
    shards: list[ShardPlan]
    values: dict  # the grid values drawn for each parameter (edge units)
    sensor: object = None  # apcg_core.sensor.SensorParams, or None for the ideal lidar

    @property
    def n_samples(self) -> int:
        return len(self.table)

    def n_outside_table1_bands(self) -> int:
        """Rows whose range lies outside their type's Table 1 band (a config may widen the
        ranges; the plausibility warning counts them)."""
        table1 = ConditionSpace()
        codes = self.table[:, 0].astype(np.int64)
        near = self.space.is_drone(codes)
        lo = np.where(near, table1.drone_range_m[0], table1.aircraft_range_m[0])
        hi = np.where(near, table1.drone_range_m[1], table1.aircraft_range_m[1])
        r = self.table[:, 1]
        return int(((r < lo) | (r > hi)).sum())


def _pair(cfg: dict, key: str, default) -> tuple[float, float]:
    v = cfg.get(key, default)  # shape checked by the schema
    return float(v[0]), float(v[1])


def _resolve_types(cfg: dict, catalog, source: str = "dataset config") -> list:
    spec = cfg["types"]  # "all" or a list of names (the schema)
    if spec == "all":
        return [t for t in catalog if t.source == "builtin"]
    types = []
    for name in spec:
        try:
            types.append(catalog.get(name))
        except InputError as exc:
            raise InputError(f"{source}: types: {exc}") from None
    seen: dict = {}
    for name, t in zip(spec, types, strict=True):
        seen.setdefault(t.index, []).append(name)
    dup = {types[[u.index for u in types].index(i)].name: names
           for i, names in seen.items() if len(names) > 1}
    if dup:
        raise InputError(f"{source}: types names one type more than once: " + "; ".join(
            f"{', '.join(repr(n) for n in names)} are all {t!r}" for t, names in dup.items()))
    return types


def _check_size(n: int, what: str) -> None:
    if n > MAX_SAMPLES:
        raise InputError(f"{what} makes {n:,} samples; one config plans at most "
                         f"{MAX_SAMPLES:,}: split it into several configs (other seeds)")


# Each [ranges] key's physical bounds (edge units), as the command line's rules state theirs.
RANGE_BOUNDS = {
    "aircraft_range_m": Rule("metres > 0 and <= 1e6", 0.0, 1e6, lo_open=True),
    "drone_range_m": Rule("metres > 0 and <= 1e6", 0.0, 1e6, lo_open=True),
    "elevation_deg": Rule("degrees between -90 and 90, both excluded (+-90: the target "
                          "overhead)", -90.0, 90.0, lo_open=True, hi_open=True),
    "pitch_deg": Rule("degrees from -90 to 90", -90.0, 90.0),
    "yaw_deg": Rule("degrees from -180 to 180", -180.0, 180.0),
    "roll_deg": Rule("degrees from -180 to 180", -180.0, 180.0),
}


def check_ranges(ranges: dict, source: str = "dataset config") -> None:
    """Every [ranges] pair within its key's physical bounds with lo < hi (nu is scaled over
    it), named with ``source`` and the key: refused before anything is planned or written."""
    for key, rule in RANGE_BOUNDS.items():
        if key not in ranges:
            continue
        a, b = (float(v) for v in ranges[key])
        if not (rule.ok(a) and rule.ok(b) and a < b):
            raise InputError(f"{source}: ranges.{key} = {list(ranges[key])!r} not accepted: "
                             f"[lo, hi] with lo < hi (each condition's vector nu is scaled over "
                             f"it), both in {rule.accepted}")


def check_plan(plan: Plan, catalog, source: str = "dataset config") -> None:
    """Every condition of the plan one the simulator takes (the lidar outside the target's
    bounding sphere, each angle physical), checked before anything is written: the first
    refused names ``source``, the [ranges] key to change and what it accepts."""
    from .rays import bounding_radius, check_conditions, start_margin_m
    codes = plan.table[:, 0].astype(np.int64)
    for code, t in enumerate(plan.types):
        rows = plan.table[codes == code]
        if not len(rows):
            continue
        radius = bounding_radius(catalog.mesh(t).vertices)
        key = "drone_range_m" if plan.space.is_drone(code) else "aircraft_range_m"
        need = radius + 2.0 * start_margin_m(radius)
        if rows[:, 1].min() <= need:
            raise InputError(f"{source}: ranges.{key} reaches {rows[:, 1].min():.6g} m, which "
                             f"puts the lidar inside {t.name}'s bounding sphere (radius "
                             f"{radius:.3f} m); accepted: ranges above {need:.3f} m")
        try:
            check_conditions(rows, radius)
        except InputError as exc:
            raise InputError(f"{source}: {t.name}: {exc}") from None


def make_plan(cfg: dict, catalog, backend: str | None = None,
              sensor: str | None = None, lidar: str | None = None,
              source: str = "dataset config") -> Plan:
    """The plan of a config (see the committed configs for every key, and ``schema``);
    ``backend``, ``sensor`` (a preset or file) and ``lidar`` (a lidar preset or file, whose
    ``[sensor]`` table counts unless ``sensor`` is given) override the config's. The config
    records the tables used, so the dataset's header names its lidar and sensor whole."""
    if lidar is not None:
        from apcg_core.lidar import lidar_from_table, read_lidar_file
        path, doc = read_lidar_file(lidar)
        lidar_from_table(doc["lidar"], source=str(path))  # its own errors name the file
        cfg = {**cfg, "lidar": dict(doc["lidar"])}
        if sensor is None and "sensor" in doc:
            cfg["sensor"] = {"name": path.stem, **doc["sensor"]}
    if sensor is not None:
        resolve_sensor(sensor, "--sensor")  # its errors name the option, not the config
        cfg = {**cfg, "sensor": sensor}
    check_config(cfg)
    seed = cfg.get("seed", 0)
    lidar = LidarParams.from_dict(cfg["lidar"]) if "lidar" in cfg else LidarParams()
    types = _resolve_types(cfg, catalog, source)
    ranges = cfg.get("ranges", {})
    check_ranges(ranges, source)
    space = ConditionSpace(
        n_types=len(types),
        drone_types=tuple(i for i, t in enumerate(types) if t.range_band == "near"),
        aircraft_range_m=_pair(ranges, "aircraft_range_m", (3000.0, 18000.0)),
        drone_range_m=_pair(ranges, "drone_range_m", (100.0, 600.0)),
        elevation=tuple(v * DEG for v in _pair(ranges, "elevation_deg", (3.0, 4.0))),
        pitch=tuple(v * DEG for v in _pair(ranges, "pitch_deg", (1.0, 5.0))),
        yaw=tuple(v * DEG for v in _pair(ranges, "yaw_deg", (-60.0, 60.0))),
        roll=tuple(v * DEG for v in _pair(ranges, "roll_deg", (-5.0, 5.0))),
        counts={**_DEFAULT_COUNTS, **cfg.get("counts", {})})
    rng = np.random.default_rng(seed)
    sampling = cfg.get("sampling", "grid")
    near = np.array([t.range_band == "near" for t in types])
    lo_hi = {"elevation": space.elevation, "yaw": space.yaw, "pitch": space.pitch,
             "roll": space.roll}
    values: dict = {}
    if sampling == "grid":
        # Table 1: each parameter's values drawn uniformly in its range, then the full grid.
        counts = space.counts
        _check_size(len(types) * math.prod(counts[f] for f in GRID_FIELDS), "the grid")
        draws = {}
        for f in GRID_FIELDS:
            if f == "range_m":
                draws["aircraft"] = np.sort(rng.uniform(*space.aircraft_range_m, counts[f]))
                draws["drone"] = np.sort(rng.uniform(*space.drone_range_m, counts[f]))
            else:
                draws[f] = np.sort(rng.uniform(*lo_hi[f], counts[f]))
        # per type, the product in GRID_FIELDS order (the last varying fastest, as
        # itertools.product), built as arrays: 48 bytes a sample, not a tuple of six floats
        parts = []
        for code in range(len(types)):
            r = draws["drone" if near[code] else "aircraft"]
            b, rr, y, p, g = (a.ravel() for a in np.meshgrid(
                draws["elevation"], r, draws["yaw"], draws["pitch"], draws["roll"],
                indexing="ij"))
            parts.append(np.stack([np.full(len(b), float(code)), rr, b, p, y, g], axis=1))
        table = np.concatenate(parts) if parts else np.zeros((0, 6))
        values = {"elevation_deg": (draws["elevation"] / DEG).tolist(),
                  "aircraft_range_m": draws["aircraft"].tolist(),
                  "drone_range_m": draws["drone"].tolist(),
                  "yaw_deg": (draws["yaw"] / DEG).tolist(),
                  "pitch_deg": (draws["pitch"] / DEG).tolist(),
                  "roll_deg": (draws["roll"] / DEG).tolist()}
    else:  # "random", the schema's only other sampling
        per = cfg["samples_per_type"]
        n = per * len(types)
        _check_size(n, "samples_per_type x types")
        code = np.repeat(np.arange(len(types)), per)
        lo, hi = space.range_bounds(code)
        table = np.stack([code, rng.uniform(lo, hi), rng.uniform(*space.elevation, n),
                          rng.uniform(*space.pitch, n), rng.uniform(*space.yaw, n),
                          rng.uniform(*space.roll, n)], axis=1)
    space.check(table)

    # Split 4 : 1 by condition, stratified by type: every type has the same test fraction.
    frac = float(cfg.get("test_fraction", 0.2))
    split = np.full(len(table), "train", dtype="<U5")
    split_rng = np.random.default_rng([seed, 1])
    codes = table[:, 0].astype(np.int64)
    for code in range(len(types)):
        rows_t = np.flatnonzero(codes == code)
        n_test = int(round(frac * len(rows_t)))
        split[split_rng.permutation(rows_t)[:n_test]] = "test"

    shard_size = cfg.get("shard_size", 2500)
    shards = []
    for name in ("train", "test"):
        for code in range(len(types)):
            rows_t = np.flatnonzero((codes == code) & (split == name))
            for start in range(0, len(rows_t), shard_size):
                shards.append(ShardPlan(len(shards), name, code,
                                        rows_t[start:start + shard_size]))
    cfg = dict(cfg)
    if backend:
        cfg["backend"] = backend
    cfg.setdefault("backend", "embree")
    if "fine_cloud_points" in cfg and cfg["backend"] != "points":  # it would be ignored
        raise InputError(f"fine_cloud_points is used by backend = \"points\" only (the point "
                         f"z-buffer's surface samples); this build casts rays "
                         f"({cfg['backend']}): drop the key")
    sensor_params = resolve_sensor(cfg["sensor"]) if "sensor" in cfg else None
    if sensor_params is not None and cfg["backend"] == "points":
        raise InputError("a sensor needs a ray-casting backend (the photon stage takes every "
                         "sub-ray's range and incidence); accepted: embree, blender, "
                         "blender-bvh")
    if sensor_params is not None and cfg.get("quantize") is False:  # as --no-quantize
        raise InputError("quantize = false does not apply with a sensor: a sensor's points sit "
                         "at their time bins' centres (SPEC section 8); drop one of the two")
    if sensor_params is not None:  # its pairing with the lidar, before anything is made
        from apcg_core.sensor.stage import check_sensor_at
        check_sensor_at(sensor_params, lidar)
    if cfg.get("incidence", False):
        if sensor_params is not None:
            raise InputError("incidence = true records each return's cosine of incidence in "
                             "an ideal dataset; a sensor's dataset records the signal per cell "
                             "instead (target_signal_pe): give one or the other")
        if cfg["backend"] == "points":
            raise InputError("incidence = true needs a ray-casting backend (the face each ray "
                             "meets); accepted: embree, blender, blender-bvh")
    return Plan(cfg, lidar, space, types, table, split, shards, values, sensor_params)
