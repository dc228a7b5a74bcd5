"""A scene file (issue 36; docs/SCENES.md): a lidar and several targets, read and checked whole.

```toml
[lidar]                      # optional: the paper's lidar (SPEC section 1) when left out
[pointing]                   # optional: the window's centre and the photon gate's centre
azimuth_deg = 0.0            #   default: the first target's azimuth and elevation at the
elevation_deg = 3.5          #   first frame; range_m (the gate) the first target's range
[scan]                       # optional: how a frame is fired (scan.py); default flash
pattern = "rows"
line_time_s = 0.001
[sequence]                   # optional: `apcg scene sequence`'s frames
frames = 200
frame_rate_hz = 10.0
start_s = 0.0                # default 0

[[target]]                   # one table per target; instance ids 1, 2, ... in this order
type = "A320neo"
range_m = 3000.0
azimuth_deg = 0.0            # default 0: the scene frame's +Z
elevation_deg = 3.5
pitch_deg = 0.0              # defaults 0: SPEC section 2's zero attitude (nose at the lidar)
yaw_deg = 0.0
roll_deg = 0.0
generator = "default"        # optional: its cells from a model (the shipped one, or a model
                             #   directory, relative to this file); false: simulated
[target.trajectory]          # optional: the target moves (trajectory.py's kinds)
kind = "line"
speed_mps = 250.0
heading_deg = 90.0
```

Everything is checked before any work: an unknown key or table, a value of the wrong type or
out of range, an unknown type, a trajectory file with a gap or a time going backwards, a
frame time outside a trajectory: each a one-line error naming the file, the target and the
value. numpy only (types are looked up in the catalog).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.toml_file import read_toml
from ..lidar import DEG, LidarParams, lidar_from_table
from .poses import POSE_RULES, pose_value_problem
from .scan import make_pattern
from .trajectory import Start, Static, Trajectory, make_trajectory

TABLES = ("lidar", "pointing", "scan", "sequence", "target")
POINTING_KEYS = ("azimuth_deg", "elevation_deg", "range_m")
SEQUENCE_KEYS = ("frames", "frame_rate_hz", "start_s")
TARGET_KEYS = ("type", "range_m", "azimuth_deg", "elevation_deg", "pitch_deg", "yaw_deg",
               "roll_deg", "trajectory", "generator")
# a [[target]]'s `generator` (and `apcg scene --generator`): what is accepted
GENERATOR_ACCEPTED = ('"default" (the shipped model), a model directory (a path; in a scene '
                      'file relative to it) or false (simulated)')
# Most targets a scene may hold: beyond this a scene is a dataset, not a picture.
MAX_TARGETS = 64
# Most frames a sequence may hold (a frame file each): an hour at 30 Hz.
MAX_FRAMES = 108_000


@dataclass
class SceneTarget:
    instance: int  # 1-based, the position in the file
    type_name: str
    type_index: int
    category: str
    trajectory: Trajectory
    source: str  # "FILE, target N (TYPE)" for messages
    # a target that is no catalog type (a Blender object made a target): its body-frame mesh,
    # reflectivity and a name for the ray casters' cache; None: the catalog type's
    mesh: object = None
    reflectivity: float | None = None
    key: object = None
    # the model that draws this target instead of the simulator (SPEC section 10): its
    # directory; None: simulated
    generator: Path | None = None

    def poses(self, t):
        return self.trajectory.poses(np.atleast_1d(np.asarray(t, np.float64)))


@dataclass
class Scene:
    lidar: LidarParams
    targets: list
    pattern: object
    pointing_azimuth: float  # rad
    pointing_elevation: float  # rad
    gate_range_m: float | None  # None: the first target's range at each frame
    frames: int
    frame_rate_hz: float
    start_s: float
    # what the file said (+ trajectory files' hashes, user types' mesh digests: the
    # catalog's mesh_record)
    record: dict = field(default_factory=dict)
    source: str = "scene"

    def __post_init__(self) -> None:
        """Every scene, however made (a scene file, the add-on's Scan Animation), is checked
        here: one frame's scan ends before the next frame starts, and every target's
        trajectory holds every time a frame's scan reads (none is extrapolated), and every frame
        has a time of its own."""
        check_scan_fits(self.pattern, self.lidar, self.frames, self.frame_rate_hz, self.source)
        check_frame_times(self.frames, self.frame_rate_hz, self.start_s, self.source)
        span = scan_span(self.pattern, self.lidar, self.frames, self.frame_rate_hz,
                         self.start_s)
        for t in self.targets:
            t.trajectory.check_times(span, t.source)

    def frame_times(self, frames=None) -> np.ndarray:
        k = np.arange(self.frames) if frames is None else np.asarray(frames, np.int64)
        return self.start_s + k / self.frame_rate_hz

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.record, sort_keys=True).encode()).hexdigest()


def check_scan_fits(pattern, lidar: LidarParams, frames: int, rate: float,
                    source: str) -> None:
    """Refuse a scan that takes a frame's time or longer (one frame's last cells would fire
    after the next frame's first): the one check of every sequence, from a scene file or
    from Blender's timeline."""
    duration = pattern.groups(lidar).duration_s
    if frames > 1 and duration >= 1.0 / rate:
        raise InputError(f"{source} [scan]: one frame's scan takes {duration:.6g} s, longer "
                         f"than a frame at {rate:g} Hz ({1.0 / rate:.6g} s); accepted: a scan "
                         "shorter than a frame (lower the frame rate, or the scan's "
                         "line_time_s / cell_time_s)")


# Scene times (s) a sequence may reach: Unix times until the year 2286, where float64 still
# tells apart times 2 us apart. Beyond, frames at another time came out at the same t_s.
MAX_TIME_S = 1e10


def check_frame_times(frames: int, rate: float, start_s: float, source: str) -> None:
    """Refuse a sequence whose frame times leave +-MAX_TIME_S or are not each later than the
    one before in float64 (a start so large that a frame period is below its resolution)."""
    t = start_s + np.arange(frames) / rate
    if abs(float(t[-1])) > MAX_TIME_S:
        raise InputError(f"{source} [sequence]: its last frame is at {float(t[-1]):.6g} s "
                         f"(start_s = {start_s!r}, frames = {frames}, frame_rate_hz = {rate!r})"
                         f"; accepted: frame times within +-{MAX_TIME_S:g} s")
    if frames > 1 and not (np.diff(t) > 0).all():
        k = int(np.argmax(np.diff(t) <= 0))
        raise InputError(f"{source} [sequence]: frames {k} and {k + 1} both fall at "
                         f"{float(t[k]):.17g} s in float64 (start_s = {start_s!r}, "
                         f"frame_rate_hz = {rate!r}); accepted: a start_s small enough, or a "
                         "frame rate low enough, that every frame has its own time")


def scan_span(pattern, lidar: LidarParams, frames: int, rate: float,
              start_s: float) -> np.ndarray:
    """[first, last] scene time a sequence's scans read a pose at (the first frame's first
    cells, the last frame's last)."""
    g = pattern.groups(lidar).time_s
    return np.array([start_s + float(g.min()), start_s + (frames - 1) / rate + float(g.max())])


def _number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _get(table: dict, key: str, where: str, lo=-math.inf, hi=math.inf, accepted="",
         default=None, open_lo=False):
    if key not in table:
        if default is None:
            raise InputError(f"{where}: {key} is missing ({accepted})")
        return default
    v = table[key]
    ok = _number(v) and (v > lo if open_lo else v >= lo) and v <= hi
    if not ok:
        raise InputError(f"{where}: {key} = {v!r} is not accepted: {accepted}")
    return float(v)


def _pose_value(table: dict, key: str, where: str, default=None) -> float:
    """A [[target]]'s pose value by the pose rules (poses.POSE_RULES: a trajectory CSV
    file's columns are checked by the same)."""
    if key not in table:
        if default is None:
            raise InputError(f"{where}: {key} is missing ({POSE_RULES[key].accepted})")
        return default
    why = pose_value_problem(key, table[key])
    if why is not None:
        raise InputError(f"{where}: {key} = {table[key]!r} {why}")
    return float(table[key])


def _keys(table, accepted, where: str) -> dict:
    if not isinstance(table, dict):
        raise InputError(f"{where} must be a table with keys {', '.join(accepted)}, "
                         f"got {table!r}")
    unknown = sorted(set(table) - set(accepted))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; accepted: "
                         f"{', '.join(accepted)}")
    return table


def load_scene(path, catalog=None, lidar: LidarParams | None = None,
               generator: str | None = None) -> Scene:
    """Read and check the scene file ``path``. ``lidar`` (a command's lidar option) overrides
    the file's ``[lidar]`` table; ``generator`` (a command's ``--generator``: "default" or a
    model directory) draws every target whose table has no ``generator`` key."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"scene file {path} does not exist")
    doc = read_toml(path)
    return scene_from_dict(doc, str(path), path.parent, catalog, lidar, generator)


def scene_from_dict(doc: dict, source: str = "scene", base_dir: Path | None = None,
                    catalog=None, lidar: LidarParams | None = None,
                    generator: str | None = None) -> Scene:
    if catalog is None:
        from ..catalog.catalog import default_catalog
        catalog = default_catalog()
    unknown = sorted(set(doc) - set(TABLES))
    if unknown:
        raise InputError(f"{source}: unknown table(s) or key(s) {', '.join(unknown)}; a scene "
                         f"holds {', '.join(f'[{t}]' for t in TABLES[:-1])} and [[target]]")
    if lidar is None:  # the [lidar] table of the dataset configs and lidar files
        lidar = lidar_from_table(doc.get("lidar", {}), source=source)
    targets_doc = doc.get("target")
    if isinstance(targets_doc, dict):  # `[target]`: one table, not an array of tables
        raise InputError(f"{source}: found [target] (single brackets); targets are written "
                         "[[target]] (double brackets), one [[target]] table per target "
                         "(and [target.trajectory] under it)")
    if not isinstance(targets_doc, list) or not targets_doc:
        raise InputError(f"{source}: no [[target]] table; a scene needs at least one target "
                         "(type, range_m, elevation_deg, ...)")
    if len(targets_doc) > MAX_TARGETS:
        raise InputError(f"{source}: {len(targets_doc)} targets; accepted: at most "
                         f"{MAX_TARGETS}")
    seq = _keys(doc.get("sequence", {}), SEQUENCE_KEYS, f"{source} [sequence]")
    frames = seq.get("frames", 1)
    if isinstance(frames, bool) or not isinstance(frames, int) or not 1 <= frames <= MAX_FRAMES:
        raise InputError(f"{source} [sequence]: frames = {frames!r} is not accepted: an "
                         f"integer from 1 to {MAX_FRAMES}")
    # 10 Hz when left out: a one-frame scan never uses it; the rate of the scanning
    # lidars of driving datasets (KITTI's HDL-64E, nuScenes' HDL-32E at 20 Hz: 10 is the lower).
    rate = _get(seq, "frame_rate_hz", f"{source} [sequence]", 0, 1e6,
                "a frame rate in Hz > 0 and <= 1e6", default=10.0, open_lo=True)
    start_s = _get(seq, "start_s", f"{source} [sequence]", -MAX_TIME_S, MAX_TIME_S,
                   f"a time in seconds from {-MAX_TIME_S:g} to {MAX_TIME_S:g}", default=0.0)
    pattern = make_pattern(doc.get("scan"), source)
    check_scan_fits(pattern, lidar, frames, rate, source)
    check_frame_times(frames, rate, start_s, source)
    record = {"lidar": lidar.to_dict(), "scan": pattern.to_dict(),
              "sequence": {"frames": frames, "frame_rate_hz": rate, "start_s": start_s},
              "targets": []}
    scan_t = scan_span(pattern, lidar, frames, rate, start_s)
    models: dict = {}  # a model directory's types, read once
    if generator is not None:
        given = _generator_value(generator, "--generator", models, Path.cwd(), absolute=True)
    targets = []
    for i, t in enumerate(targets_doc, start=1):
        target = _target(t, i, source, base_dir, catalog, scan_t, record)
        entry = record["targets"][-1]
        if "generator" in t:
            value = _generator_value(t["generator"], f"{target.source}: generator", models,
                                     base_dir or Path.cwd())
        else:
            value = given if generator is not None else None
        if value is not None:
            entry["generator"] = value[0]
            target.generator = value[1]
            if value[1] is not None:
                _check_model_type(target, models[value[1]][0])
        targets.append(target)
    az0, el0 = default_pointing(targets, start_s)
    pt = _keys(doc.get("pointing", {}), POINTING_KEYS, f"{source} [pointing]")
    az = _get(pt, "azimuth_deg", f"{source} [pointing]", -360, 360,
              "an azimuth in degrees from -360 to 360", default=az0 / DEG) * DEG \
        if "azimuth_deg" in pt else az0
    el = _get(pt, "elevation_deg", f"{source} [pointing]", -90, 90,
              "an elevation in degrees between -90 and 90", open_lo=True,
              default=el0 / DEG) * DEG if "elevation_deg" in pt else el0
    if abs(el) >= math.pi / 2 - (lidar.height / 2) * lidar.r_beta:
        raise InputError(f"{source} [pointing]: elevation {el / DEG:.6g} deg puts the window "
                         "over the zenith; accepted: a window wholly below +-90 deg")
    gate = _get(pt, "range_m", f"{source} [pointing]", 0, 1e6, "a range in m > 0",
                default=-1.0, open_lo=True) if "range_m" in pt else None
    record["pointing"] = {"azimuth_deg": az / DEG, "elevation_deg": el / DEG,
                          "range_m": gate}
    return Scene(lidar, targets, pattern, az, el, gate, frames, rate, start_s, record, source)


def _generator_value(v, where: str, models: dict, base: Path, absolute: bool = False):
    """A ``generator`` value: (what the scene's record keeps, the model directory or None).
    The record names the model as given ("default", or the path; from the command line made
    absolute, so that every worker reads the same one) with the sha256 of its files, so that
    a sequence made with another model is not resumed with this one."""
    if v is False:
        return False, None
    if not isinstance(v, str) or not v.strip():
        raise InputError(f"{where} = {v!r} is not accepted: {GENERATOR_ACCEPTED}")
    from ..families.base import ModelTypes, default_model_dir
    name = v.strip()
    if name == "default":
        d = default_model_dir().resolve()
    else:
        d = Path(name).expanduser()
        d = (d if d.is_absolute() else base / d).resolve()
        if absolute:
            name = str(d)
    if d not in models:
        try:
            models[d] = ModelTypes(d), _model_digest(d)
        except InputError as exc:
            raise InputError(f"{where} = {v!r}: {exc}; accepted: {GENERATOR_ACCEPTED}") from None
    return {"model": name, "sha256": models[d][1]}, d


def _model_digest(d: Path) -> str:
    """sha256 over a model directory's files (names and contents, top level, sorted)."""
    h = hashlib.sha256()
    for f in sorted(p for p in d.iterdir() if p.is_file()):
        h.update(f.name.encode() + b"\0")
        h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()


def _check_model_type(target: SceneTarget, model) -> None:
    try:
        model.types.code(target.type_name)
    except InputError as exc:
        raise InputError(f"{target.source}: generator: {exc} (or generator = false: "
                         "simulated)") from None


def default_pointing(targets, t0: float) -> tuple[float, float]:
    """The window's centre when [pointing] does not say: the first target's azimuth and
    elevation at ``t0`` (a static target's as given, bit for bit: `apcg simulate`'s)."""
    first = targets[0]
    if isinstance(first.trajectory, Static):
        return first.trajectory.start.azimuth, first.trajectory.start.elevation
    from ..frames import cartesian_to_spherical
    p0, _ = first.poses(t0)
    az, el, _ = cartesian_to_spherical(p0[0])
    return float(az), float(el)


def _target(t, i: int, source: str, base_dir, catalog, scan_t, record) -> SceneTarget:
    where = f"{source}, target {i}"
    _keys(t, TARGET_KEYS, where)
    if "type" not in t or not isinstance(t["type"], str):
        raise InputError(f"{where}: type is missing or not a name (a catalog type: "
                         "`apcg catalog list`)")
    try:
        ty = catalog.get(t["type"])
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    where = f"{source}, target {i} ({ty.name})"
    traj = t.get("trajectory")
    csv = isinstance(traj, dict) and traj.get("kind") == "csv"
    if csv:
        given = [k for k in TARGET_KEYS[1:7] if k in t]
        if given:
            raise InputError(f"{where}: {', '.join(given)} come from its trajectory CSV file; "
                             "leave them out of the [[target]] table")
        start = None
    else:
        r = _pose_value(t, "range_m", where)
        az = _pose_value(t, "azimuth_deg", where, default=0.0)
        el = _pose_value(t, "elevation_deg", where)
        att = [_pose_value(t, k, where, default=0.0) for k in ("pitch_deg", "yaw_deg", "roll_deg")]
        if traj is not None and any(k in t for k in ("pitch_deg", "yaw_deg", "roll_deg")):
            raise InputError(f"{where}: pitch_deg, yaw_deg and roll_deg come from its "
                             f"{traj.get('kind') if isinstance(traj, dict) else ''} "
                             "trajectory (nose along the motion); leave them out")
        start = Start(r, az * DEG, el * DEG, tuple(a * DEG for a in att))
    trajectory = make_trajectory(traj, start, where, base_dir)
    trajectory.check_times(scan_t, where)
    entry = {k: v for k, v in t.items() if k != "trajectory"}
    entry["type"] = ty.name
    # the geometry cast: a user type's mesh digest (`catalog add --force` may replace its
    # mesh under the same name), so that a sequence of another mesh is another sequence;
    # nothing for a built-in type (its record and digest as before). Its reflectivity too,
    # which --force may replace with the mesh kept and which a --sensor scan's photons use
    stamp = catalog.mesh_record(ty)
    if stamp:
        stamp["reflectivity"] = ty.effective_reflectivity
    entry.update(stamp)
    if traj is not None:
        entry["trajectory"] = dict(traj)
        if csv:
            entry["trajectory"]["sha256"] = hashlib.sha256(
                trajectory.path.read_bytes()).hexdigest()
    record["targets"].append(entry)
    return SceneTarget(i, ty.name, ty.index, ty.category, trajectory, where)


def scene_warnings(scene: Scene) -> list[str]:
    """Trajectories beyond what their type flies (speed, turn): warnings, not errors."""
    out = []
    for t in scene.targets:
        out += t.trajectory.warnings(t.category, f"{t.source}: ")
    return out
