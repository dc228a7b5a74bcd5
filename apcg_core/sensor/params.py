"""The ``[sensor]`` table: what the detector and the link budget need (SPEC section 8).

A sensor is a TOML file with a ``[sensor]`` table, or one of the presets shipped beside this
module (``apcg_core/sensor/presets/*.toml``, each value with its source). ``ideal`` is today's
standard cloud: no photon stage at all. Every value is checked here, once, with a named error.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from numbers import Integral, Real
from pathlib import Path

from ..errors import InputError
from ..io.toml_file import read_toml
from ..typetable import find_preset, odd_characters

PRESET_DIR = Path(__file__).with_name("presets")
OUTPUTS = ("points", "events")
IDEAL = "ideal"


@dataclass(frozen=True)
class SensorParams:
    """One single-photon lidar's detector and link budget. SI units inside the names."""

    name: str
    wavelength_nm: float
    pulse_energy_j: float
    cells_per_pulse: int
    aperture_m: float
    optics_efficiency: float
    detector_efficiency: float
    visibility_km: float
    background_hz: float
    dark_count_hz: float
    pulse_fwhm_ps: float
    jitter_ps: float
    gate_m: float
    dead_time_ns: float
    pulses: int
    threshold: int
    output: str = "points"

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def noise_hz(self) -> float:
        """Detector counts per second that carry no signal (efficiency already included)."""
        return self.background_hz + self.dark_count_hz

    def with_output(self, output: str) -> SensorParams:
        return check_sensor({**self.to_dict(), "output": output})


# name: (kind, lower bound, upper bound, lower bound open?) -- what every value accepts.
_RULES = {
    "wavelength_nm": ("float", 200.0, 20000.0, False),
    "pulse_energy_j": ("float", 0.0, 10.0, True),
    "cells_per_pulse": ("int", 1, 10**8, False),
    "aperture_m": ("float", 0.0, 10.0, True),
    "optics_efficiency": ("float", 0.0, 1.0, True),
    "detector_efficiency": ("float", 0.0, 1.0, True),
    "visibility_km": ("float", 0.05, 1000.0, False),
    "background_hz": ("float", 0.0, 1e10, False),
    "dark_count_hz": ("float", 0.0, 1e10, False),
    "pulse_fwhm_ps": ("float", 0.0, 1e6, False),
    "jitter_ps": ("float", 0.0, 1e6, False),
    "gate_m": ("float", 0.0, 1e5, True),
    "dead_time_ns": ("float", 0.0, 1e7, False),
    "pulses": ("int", 1, 100_000, False),
    "threshold": ("int", 1, 100_000, False),
}
KEYS = tuple(f.name for f in fields(SensorParams) if f.name != "name")
# A sensor's name travels in every cloud file's metadata; a LAS file's record holds 65,535
# bytes at most (LAS 1.4 R15, section 2.5: the VLR's record length is an unsigned short).
MAX_NAME_CHARS = 200


def _check_value(key: str, value, source: str):
    # numpy's scalars (np.int64, np.float32) are the numbers they hold: numbers.Integral /
    # numbers.Real, as Python's int and float are; a bool is not a count
    kind, lo, hi, open_lo = _RULES[key]
    where = f"sensor value {key} in {source}" if source else f"sensor value {key}"
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, Integral):
            raise InputError(f"{where} must be an integer in {lo}..{hi}, got {value!r} of "
                             f"type {type(value).__name__}")
        if not lo <= value <= hi:
            raise InputError(f"{where} must be an integer in {lo}..{hi}, got {value!r}")
        return int(value)
    if isinstance(value, bool) or not isinstance(value, Real):
        raise InputError(f"{where} must be a number, got {value!r} of type "
                         f"{type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{where} must be finite, got {value!r}")
    ok = (lo < v if open_lo else lo <= v) and v <= hi
    if not ok:
        br = "(" if open_lo else "["
        raise InputError(f"{where} = {value!r} is out of range; accepted: {br}{lo!r}, {hi!r}]")
    return v


def check_sensor(table: dict, source: str = "", name: str = "") -> SensorParams:
    """A :class:`SensorParams` from a ``[sensor]`` table, every value checked by name."""
    if not isinstance(table, dict):
        raise InputError(f"the [sensor] table{' in ' + source if source else ''} must be a "
                         f"table of keys, got {table!r}")
    table = dict(table)
    given = table.pop("name", name)
    if not isinstance(given, str):
        raise InputError(f"sensor value name{' in ' + source if source else ''} must be text "
                         f"(a quoted string), got {given!r}")
    if len(given) > MAX_NAME_CHARS:
        raise InputError(f"sensor value name{' in ' + source if source else ''} is "
                         f"{len(given)} characters long ({given[:40]!r}...); accepted: at most "
                         f"{MAX_NAME_CHARS}")
    odd = odd_characters(given)
    if odd:
        raise InputError(f"sensor value name{' in ' + source if source else ''} = {given!r} "
                         f"not accepted: it holds {odd}; give it a name of visible "
                         "characters")
    name = given or "custom"
    unknown = sorted(set(table) - set(KEYS))
    if unknown:
        raise InputError(f"unknown sensor key(s) {', '.join(map(repr, unknown))}"
                         f"{' in ' + source if source else ''}; accepted: {', '.join(KEYS)}")
    missing = [k for k in KEYS if k not in table and k != "output"]
    if missing:
        raise InputError(f"the [sensor] table{' in ' + source if source else ''} lacks "
                         f"{', '.join(missing)}; start from a preset file: "
                         f"{', '.join(preset_names())} ({PRESET_DIR})")
    values = {k: _check_value(k, table[k], source) for k in _RULES}
    output = table.get("output", "points")
    if output not in OUTPUTS:
        raise InputError(f"sensor value output must be one of {', '.join(OUTPUTS)}, "
                         f"got {output!r}")
    return SensorParams(name=name, output=output, **values)


def check_own_name(sensor: SensorParams, source: str) -> SensorParams:
    """A user's sensor (a file's) under a preset's name (in any spelling) must be that preset:
    else every output would call it the preset. Refused in one line; the ``output`` may
    differ (it is recorded beside the name, as ``--photon-output`` sets it)."""
    preset = find_preset(sensor.name, PRESET_DIR)
    if preset is None:
        return sensor
    own = load_sensor(preset)
    same = own is not None and all(getattr(own, k) == getattr(sensor, k)
                                   for k in KEYS if k != "output")
    if not same:
        differ = ("it is no photon sensor" if own is None else ", ".join(
            f"{k} = {getattr(sensor, k)!r} (the preset's {getattr(own, k)!r})"
            for k in KEYS if k != "output" and getattr(own, k) != getattr(sensor, k)))
        raise InputError(f"{source}: the sensor is named {sensor.name!r}, the preset "
                         f"{preset.stem!r}, but its values are not the preset's ({differ}); "
                         "give your sensor its own name (name = \"...\"), or drop name to "
                         "take the file's name")
    return sensor


MIN_GATE_BINS = 2  # the shortest gate that always holds r0 (check_gate)


def check_gate(sensor: SensorParams, r_r_m: float) -> int:
    """Bins of the range gate at this lidar's range resolution; a gate shorter than two bins
    is refused: its first bin is the one holding r0 - gate_m / 2 (SPEC section 8), so a
    shorter one can end before the target's own range r0 and miss it (a one-bin gate did for
    half of all r0: probe, stop 55); from two bins on it always holds r0."""
    if sensor.gate_m < MIN_GATE_BINS * r_r_m:
        raise InputError(f"sensor value gate_m = {sensor.gate_m!r} m is shorter than two range "
                         f"bins of the lidar (r_r_m = {r_r_m!r} m); accepted: gate_m >= "
                         f"{MIN_GATE_BINS * r_r_m!r} (a shorter gate, opening at the bin of "
                         "r0 - gate_m / 2, can close before the target's range r0)")
    return int(math.ceil(sensor.gate_m / r_r_m - 1e-9))


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def load_sensor(ref: str | Path | None, lidar_file: bool = False) -> SensorParams | None:
    """A sensor from a preset name or a TOML file (its ``[sensor]`` table); None for the ideal
    lidar (no ``ref``, ``ideal``, or a file whose table says ``model = "ideal"``). The file
    holds nothing else (another table is refused, not ignored), unless ``lidar_file``: a
    ``--lidar`` file, whose own reader has checked its ``[lidar]`` table and its others."""
    if ref is None:
        return None
    ref_s = str(ref).strip()
    path = find_preset(ref_s, PRESET_DIR)  # a preset's name, in any spelling
    preset = path is not None
    if not preset:
        path = Path(ref_s).expanduser()
        if ref_s and path.is_dir():
            raise InputError(f"sensor {ref_s!r} is a directory; give a preset or a TOML file "
                             "with a [sensor] table")
        if not path.is_file():
            raise InputError(f"unknown sensor {ref_s!r}: not a preset and no such file; "
                             f"presets: {', '.join(preset_names())}, or a TOML file with a "
                             f"[sensor] table")
    doc = read_toml(path)
    if "sensor" not in doc:
        raise InputError(f"{path} has no [sensor] table; see the presets in {PRESET_DIR}")
    others = [k for k in doc if k != "sensor" and not (lidar_file and k == "lidar")]
    if "lidar" in others:
        raise InputError(f"{path} holds a [lidar] table, which a sensor file does not take: "
                         f"give the file to --lidar (it reads its [lidar] and [sensor] tables) "
                         "instead of --sensor")
    if others:
        raise InputError(f"{path}: {', '.join(_toml_key(k, doc[k]) for k in others)} unknown "
                         "in a sensor file; accepted: the [sensor] table alone")
    sensor = sensor_from_table(doc["sensor"], source=str(path), name=path.stem)
    if sensor is not None and not (preset or path.resolve().parent == PRESET_DIR.resolve()):
        check_own_name(sensor, str(path))
    return sensor


def _toml_key(key: str, value) -> str:
    return f"table [{key}]" if isinstance(value, dict) else f"key {key!r}"


def sensor_from_table(table, source: str = "", name: str = "") -> SensorParams | None:
    """A ``[sensor]`` table (a config's, a file's, a dataset manifest's) as a sensor, None when
    it describes the ideal lidar."""
    if isinstance(table, dict) and table.get("model") == IDEAL:
        if set(table) - {"model", "name"}:
            raise InputError(f"the ideal sensor{' in ' + source if source else ''} takes no "
                             f"other key, got {sorted(set(table) - {'model', 'name'})}")
        return None
    if isinstance(table, dict) and "model" in table:
        if (m := table["model"]) != "photon":
            raise InputError(f"sensor model must be 'ideal' or 'photon', got {m!r}")
        table = {k: v for k, v in table.items() if k != "model"}
    return check_sensor(table, source, name)
