"""What a dataset config (TOML) may hold: one table of keys, their types and accepted values.

A config is checked whole before anything is planned: an unknown key (a typo), a value of the
wrong type, a key the chosen sampling ignores, or an empty file is refused with a message that
names the key, the value and what is accepted. Nothing is filled in here: defaults are applied
where they are used, so a config is recorded in the dataset header exactly as it was written.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from apcg_core.errors import InputError
from apcg_core.options import MAX_PER_TYPE, PER_TYPE

from .backends import BACKENDS


def _number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _integer(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _int_in(lo: int, hi: float = math.inf) -> Callable:
    return lambda v: _integer(v) and lo <= v <= hi


def _text(v) -> bool:
    return isinstance(v, str) and v.strip() != ""


def _pair(v) -> bool:
    return isinstance(v, list) and len(v) == 2 and all(map(_number, v)) and v[0] < v[1]


def _types(v) -> bool:
    return v == "all" or (isinstance(v, list) and len(v) > 0 and all(map(_text, v)))


@dataclass(frozen=True)
class Key:
    accepted: str
    ok: Callable
    sampling: str | None = None  # only meaningful with this sampling


@dataclass(frozen=True)
class Table:
    """A TOML table: its own keys, each with its rule."""
    keys: dict
    sampling: str | None = None  # only meaningful with this sampling


_POSITIVE = Key("a finite number > 0", lambda v: _number(v) and v > 0)
_EVEN = Key("an even integer from 2 to 65536", lambda v: _int_in(2, 65536)(v) and v % 2 == 0)
# lo < hi: each condition's nu is scaled over [lo, hi] (plan.check_ranges says the same)
_PAIR = Key("[lo, hi], two finite numbers with lo < hi", _pair)
_COUNT = Key("an integer from 1 to 10000", _int_in(1, 10**4))

SCHEMA: dict = {
    "name": Key("a non-empty string", _text),
    "description": Key("a string", lambda v: isinstance(v, str)),
    "seed": Key("an integer from 0 to 4294967295", _int_in(0, 2**32 - 1)),
    "backend": Key(f"one of {', '.join(BACKENDS)}", lambda v: v in BACKENDS),
    "shard_size": Key("an integer from 1 to 1000000", _int_in(1, 10**6)),
    "test_fraction": Key("a number from 0 to 1, 1 excluded", lambda v: _number(v) and 0 <= v < 1),
    "quantize": Key("true or false", lambda v: isinstance(v, bool)),
    "supersample": Key("an integer from 1 to 16", _int_in(1, 16)),
    "sampling": Key('"grid" or "random"', lambda v: v in ("grid", "random")),
    "samples_per_type": Key(PER_TYPE.accepted, _int_in(1, MAX_PER_TYPE), "random"),
    "types": Key('"all" or a non-empty list of catalog type names', _types),
    "fine_cloud_points": Key("an integer from 100 to 10000000", _int_in(100, 10**7)),
    # a preset name, a TOML file, or the [sensor] table itself: apcg_core.sensor checks it
    "sensor": Key("a sensor preset name, a TOML file or a [sensor] table (docs/SPEC.md "
                  "section 8)", lambda v: _text(v) or isinstance(v, dict)),
    # each return's cosine of incidence in the shards (cos_incidence): what an incidence
    # output learns from (training.families.plus_incidence); ideal ray-cast datasets only
    "incidence": Key("true or false", lambda v: isinstance(v, bool)),
    "lidar": Table({"r_alpha_deg": _POSITIVE, "r_beta_deg": _POSITIVE, "r_r_m": _POSITIVE,
                    "width": _EVEN, "height": _EVEN}),
    "ranges": Table({k: _PAIR for k in ("aircraft_range_m", "drone_range_m", "elevation_deg",
                                        "pitch_deg", "yaw_deg", "roll_deg")}),
    # `counts` shapes the grid only; a random config carrying it would silently ignore it.
    "counts": Table({k: _COUNT for k in ("elevation", "range_m", "yaw", "pitch", "roll")},
                    "grid"),
}
REQUIRED = ("types",)


def resolve_sensor(value, source: str = "dataset config"):
    """A config's ``sensor`` (preset, file or table) as a SensorParams, None for the ideal
    lidar; every value checked by the sensor module, named with the config it came from."""
    from apcg_core.sensor import load_sensor, sensor_from_table
    from apcg_core.sensor.params import check_own_name
    try:
        if isinstance(value, dict):
            sensor = sensor_from_table(value, source=f"{source} [sensor]")
            if sensor is not None and "name" in value:  # a preset's name is the preset's
                check_own_name(sensor, f"{source} [sensor]")
            return sensor
        return load_sensor(value)
    except InputError as exc:
        msg = str(exc)
        raise InputError(msg if source in msg else f"{source}: {msg}") from None


def accepted_keys() -> str:
    return ", ".join(SCHEMA)


def check_config(cfg: dict, source: str = "dataset config") -> None:
    """Refuse, naming the key, anything in ``cfg`` the schema does not accept."""
    if not cfg:
        raise InputError(f"{source} is empty; it needs at least `types` (\"all\" or a list of "
                         f"catalog names). Accepted keys: {accepted_keys()}")
    unknown = sorted(set(cfg) - set(SCHEMA))
    if unknown:
        raise InputError(f"{source}: unknown keys {unknown}; accepted: {accepted_keys()}")
    missing = [k for k in REQUIRED if k not in cfg]
    if missing:
        raise InputError(f"{source}: missing {missing}; `types` is \"all\" or a list of "
                         "catalog type names (`apcg catalog list`)")
    sampling = cfg.get("sampling", "grid")
    for key, rule in SCHEMA.items():
        if key not in cfg:
            continue
        _check(source, key, cfg[key], rule)
        if rule.sampling and sampling != rule.sampling:  # it would be silently ignored
            raise InputError(f"{source}: {key} is used by sampling = \"{rule.sampling}\" only "
                             f"(this config samples {sampling!r})")
    if "sensor" in cfg:
        resolve_sensor(cfg["sensor"], source)
    if sampling == "random" and "samples_per_type" not in cfg:
        raise InputError(f"{source}: sampling = \"random\" needs samples_per_type "
                         f"({SCHEMA['samples_per_type'].accepted})")


def _check(source: str, key: str, value, rule) -> None:
    if isinstance(rule, Key):
        if not rule.ok(value):
            raise InputError(f"{source}: {key} = {value!r} not accepted: {rule.accepted}")
        return
    if not isinstance(value, dict):
        raise InputError(f"{source}: {key} must be a table [{key}] with keys "
                         f"{', '.join(rule.keys)}, got {value!r}")
    unknown = sorted(set(value) - set(rule.keys))
    if unknown:
        raise InputError(f"{source}: unknown keys {unknown} in [{key}]; accepted: "
                         f"{', '.join(rule.keys)}")
    for k, v in value.items():
        _check(source, f"{key}.{k}", v, rule.keys[k])
