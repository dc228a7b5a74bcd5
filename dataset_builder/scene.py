"""Scanning scenes (issue 36; docs/SCENES.md): a lidar and several targets, static or moving,
on the simulator's own ray casters.

One frame: the scan pattern (``apcg_core.scene.scan``) divides the window into groups of cells
fired together; each target is placed where its trajectory has it at each group's time, turned
into the window's frame (the pointing azimuth), and cast through the simulator's ray machinery
(``Simulator.posed_cells``: the same rays, float32 casters, float64 bin decisions as
``apcg simulate``), its cell box cut to the group's cells. Per cell the nearest surface of all
targets wins (occlusion between aircraft); each point is labelled with its target's instance
(1-based, the [[target]] order) and type. With a sensor, every sub-ray's nearest hit of all
targets goes to the photon stage (``apcg_core.sensor``) as one window, gated around the
pointing range, seeded by (seed, frame).

A target may be **generated** instead (its ``generator``: a model, ``apcg_core.families``): for
each group its pose at the group's time, relative to its own line of sight, is the model's
condition; the model draws it at the centre of a window, and its cells are moved by the
target's offset from the window's centre in whole cells (SPEC section 10), cut to the group's
cells and composited with the other targets by range. A pose outside the model's condition
space is simulated instead in that frame, and the frame says so (its ``generated`` array and
``meta``).

A sequence (:func:`build_sequence`) is one frame file per frame, written whole, by tasks that
any of the dataset builder's engines runs (``engine.py``); killed and run again it finishes the
same bytes. Its format and loader: ``apcg_core.scene.sequence``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from apcg_core.cloud import PointCloud
from apcg_core.errors import InputError
from apcg_core.frames import cartesian_to_spherical, spherical_to_cartesian
from apcg_core.lidar import DEG
from apcg_core.scene.poses import angles_of_poses, turn
from apcg_core.scene.sequence import (
    FORMAT,
    FORMAT_VERSION,
    frame_arrays,
    frame_file,
    poses_csv_bytes,
    read_frame,
)
from apcg_core.scene.spec import Scene, load_scene
from apcg_core.scene.trajectory import Static

from .rays import AngularBoxes, angular_boxes, bounding_radius, start_margin_m
from .simulate import Simulator

# The farthest a target may be at any frame: the bound of a target's range_m and of every
# command's --range-m (apcg_core/options.py), so that a speed or start time cannot carry it
# to 2e7 m or to infinity, where no lidar of this project sees anything.
MAX_RANGE_M = 1e6


@dataclass
class FrameScan:
    """One scanned frame: the cloud in the scene frame with per-point ``instance`` (0: a noise
    point of the photon stage) and the targets' poses at the frame's start time."""

    frame: int
    t_s: float
    cloud: PointCloud
    instance: np.ndarray  # (P,) int32
    type_names: list  # per instance (index instance - 1)
    position: np.ndarray  # (T, 3) scene frame
    rotation: np.ndarray  # (T, 3, 3) body -> scene
    in_window: np.ndarray  # (T,) bool: some of its cells lie in the window
    clipped: np.ndarray  # (T,) bool: its box reaches beyond the window
    # (T,) bool: its points in this frame came from its generator (it met the window and
    # its model drew it: False where simulated, by the fallback rule too, and where it is
    # not in the window); None: the scene generates no target
    generated: np.ndarray | None = None
    fallback: dict = field(default_factory=dict)  # instance -> why its model could not draw it

    def points_of(self) -> np.ndarray:
        return np.bincount(self.instance, minlength=len(self.type_names) + 1)[1:].astype(
            np.int32)


class SceneScanner:
    """Scans the frames of a scene with one simulator (``backend``, ``supersample``,
    ``quantize``) and optionally a sensor (SensorParams) seeded by ``seed``."""

    def __init__(self, scene: Scene, backend: str = "embree", supersample: int = 1,
                 quantize: bool = True, sensor=None, seed: int = 0, catalog=None) -> None:
        from apcg_core.catalog.catalog import default_catalog
        self.scene = scene
        self.catalog = catalog or default_catalog()
        self.sim = Simulator(backend, scene.lidar, quantize=quantize, supersample=supersample)
        if self.sim.backend == "points":
            raise InputError("a scene needs a ray-casting backend (several targets share one "
                             "window, nearest surface first); accepted: embree, blender, "
                             "blender-bvh")
        self.sensor = sensor
        self.seed = int(seed)
        self.groups = scene.pattern.groups(scene.lidar)
        self.meshes = [t.mesh if t.mesh is not None else self.catalog.mesh(t.type_index)
                       for t in scene.targets]
        self.keys = [t.key if t.key is not None else ("type", t.type_index)
                     for t in scene.targets]
        self.radii = [bounding_radius(m.vertices) for m in self.meshes]
        self.models = self._open_models()
        if sensor is not None:
            from apcg_core.sensor import reflectivity_of
            self.reflectivity = np.array([
                t.reflectivity if t.reflectivity is not None
                else reflectivity_of(self.catalog.get(t.type_index)) for t in scene.targets])

    def close(self) -> None:
        self.sim.close()

    def _open_models(self) -> list:
        """Each target's generator model (None: simulated), one per directory."""
        from apcg_core.families import load_model
        scene, opened, out = self.scene, {}, []
        for t in scene.targets:
            if t.generator is None:
                out.append(None)
                continue
            if self.sensor is not None:
                raise InputError(f"{t.source}: a generated target cannot feed the photon stage "
                                 "(--sensor takes every sub-ray's hit and incidence, which a "
                                 "model does not draw); accepted: no --sensor, or generator = "
                                 "false for this target")
            if t.generator not in opened:
                model = load_model(t.generator)
                if not model.ANY_LIDAR:  # draws at its training lidar only: refused elsewhere
                    model.use_lidar(scene.lidar)
                opened[t.generator] = model
            out.append(opened[t.generator])
        return out

    # --- geometry ------------------------------------------------------------------------------
    def _geometry(self, i: int, t0, per_frame: bool = False):
        """Target i at each group's time: table rows, window-frame maps and centres, boxes cut
        to the groups' cells (groups the target does not reach dropped), clipped flag.
        ``per_frame``: ``t0`` holds several frames' start times; only whether the target meets
        the window in each is returned (one batch of boxes for all of them)."""
        scene, lidar, g = self.scene, self.scene.lidar, self.groups
        target = scene.targets[i]
        times = (np.atleast_1d(np.asarray(t0, np.float64))[:, None] + g.time_s[None, :]).ravel()
        m, c, rng = self._posed(i, times)
        table = np.zeros((len(times), 6))
        table[:, 0] = target.type_index
        table[:, 1] = rng
        table[:, 2] = scene.pointing_elevation
        boxes = angular_boxes(self.meshes[i].vertices, table, lidar, m, c)
        reps = len(times) // len(g)
        gw_lo, gw_hi, gh_lo, gh_hi = (np.tile(a, reps) for a in (g.w_lo, g.w_hi, g.h_lo, g.h_hi))
        cut = AngularBoxes(np.maximum(boxes.w_lo, gw_lo), np.minimum(boxes.w_hi, gw_hi),
                           np.maximum(boxes.h_lo, gh_lo), np.minimum(boxes.h_hi, gh_hi),
                           boxes.clipped, boxes.outside)
        keep = (cut.w_hi >= cut.w_lo) & (cut.h_hi >= cut.h_lo) & ~boxes.outside
        # A target not wholly in front of the lidar (its bounding sphere reaching z <= 0 in the
        # window's frame): its vertices' azimuths wrap at +-180 deg, so their least and
        # greatest (the box) span the whole window; whether it can meet the window is then
        # its sphere's answer (no ray of the window reaches behind the lidar).
        behind = c[:, 2] <= self.radii[i]
        if behind.any():
            keep &= ~behind | self._sphere_meets(i, c)
        if per_frame:
            return keep.reshape(-1, len(g)).any(axis=1)
        return (table[keep], m[keep], c[keep], cut[keep], bool(keep.any()),
                bool(boxes.clipped[keep].any()) if keep.any() else False,
                np.flatnonzero(keep) % len(g))

    def _posed(self, i: int, times: np.ndarray):
        """Target i at ``times``: body -> window-frame maps, centres in the window's frame and
        ranges; refused where the lidar would sit inside it (every frame's times pass here
        before a scan or a sequence writes anything: :func:`check_targets_seen`)."""
        scene, target = self.scene, self.scene.targets[i]
        p, b = target.poses(times)
        rng = target.trajectory.ranges(p)
        radius = self.radii[i]
        need = radius + 2.0 * start_margin_m(radius)
        bad = ~(rng > need)  # NaN too
        if bad.any():
            j = int(np.argmax(bad))
            raise InputError(f"{target.source}: at t = {times[j]:.6g} s its range "
                             f"{rng[j]:.6g} m puts the lidar inside it (bounding radius "
                             f"{radius:.3f} m); accepted: a range > {need:.3f} m")
        far = ~(rng <= MAX_RANGE_M)  # inf and NaN too: a speed or start time run away
        if far.any():
            j = int(np.argmax(far))
            raise InputError(f"{target.source}: at t = {times[j]:.6g} s its range is "
                             f"{rng[j]:.6g} m; accepted: a range <= {MAX_RANGE_M:g} m at every "
                             "frame (a target's range_m has the same bound): check its speed "
                             "and the sequence's start_s")
        return turn(-scene.pointing_azimuth, b), turn(-scene.pointing_azimuth, p), rng

    def _sphere_meets(self, i: int, c: np.ndarray) -> np.ndarray:
        """Whether target i's bounding sphere, centred at ``c`` (N, 3, the window's frame),
        can reach the window's cells: never False where a ray of the window can hit it."""
        lidar, el0 = self.scene.lidar, self.scene.pointing_elevation
        a_lo, a_hi = (lidar.w_min - 0.5) * lidar.r_alpha, (-lidar.w_min + 0.5) * lidar.r_alpha
        b_lo = el0 + (lidar.h_min - 0.5) * lidar.r_beta
        b_hi = el0 + (-lidar.h_min + 0.5) * lidar.r_beta
        az, el, r = cartesian_to_spherical(c)
        rho = np.arcsin(np.minimum(1.0, self.radii[i] / r))
        rho_az = np.minimum(np.pi, rho / np.maximum(np.cos(np.abs(el) + rho), 1e-9))
        return ((az + rho_az >= a_lo) & (az - rho_az <= a_hi) & (el + rho >= b_lo)
                & (el - rho <= b_hi))

    # --- one frame -----------------------------------------------------------------------------
    def scan(self, frame: int) -> FrameScan:
        scene = self.scene
        t0 = float(scene.frame_times([frame])[0])
        n = len(scene.targets)
        in_window, clipped = np.zeros(n, bool), np.zeros(n, bool)
        generated = np.zeros(n, bool)  # True only where its model draws it in this frame
        fallback = {}
        parts = []
        for i in range(len(scene.targets)):
            table, m, c, boxes, inside, cl, groups = self._geometry(i, t0)
            in_window[i], clipped[i] = inside, cl
            if not len(table):
                continue
            key = self.keys[i]
            if self.models[i] is not None:
                drawn, why = self._generated(i, frame, t0, groups)
                if drawn is not None:
                    parts.append(drawn)
                    generated[i] = True
                    continue
                fallback[i + 1] = why
            if self.sensor is None:
                s, w, h, r = self.sim.posed_cells(self.meshes[i], table, (m, c, boxes), key)
                parts.append((np.full(len(w), i + 1, np.int32), w, h, r,
                              np.ones(len(w), bool)))
            else:
                hits, sub = self.sim.sub_ray_hits(self.meshes[i], table, key, (m, c, boxes),
                                                  sub_index=True)
                parts.append((np.full(len(hits.w), i + 1, np.int32), hits.w, hits.h,
                              hits.range_m, hits.cos, sub))
        if self.sensor is None:
            cloud, inst = self._ideal(parts)
        else:
            cloud, inst = self._photons(parts, frame, t0)
        if scene.pointing_azimuth != 0.0:
            cloud.xyz = turn(scene.pointing_azimuth, cloud.xyz)
        p, b = zip(*(t.poses(t0) for t in scene.targets), strict=True)
        return FrameScan(frame, t0, cloud, inst, [t.type_name for t in scene.targets],
                         np.concatenate(p), np.concatenate(b), in_window, clipped,
                         generated if any(mo is not None for mo in self.models) else None,
                         fallback)

    # --- a generated target --------------------------------------------------------------------
    def _generated(self, i: int, frame: int, t0: float, groups: np.ndarray):
        """Target i drawn by its model in the groups ``groups`` (those its box reaches):
        ((instance, w, h, range, False) in the window's cells, None), or (None, why) when a
        group's pose lies outside the model's condition space (it is simulated instead).

        The model draws a target on its own line of sight, at the centre of a window (SPEC
        section 10): the pose relative to that line of sight is the condition, and the cells
        are then moved by the target's offset from the window's centre, rounded to whole
        cells (at most half a cell of azimuth and of elevation off; none for a target at the
        window's centre, `apcg generate`'s cloud). Its ranges are the model's (its own
        quantization), not quantized again."""
        scene, lidar, g = self.scene, self.scene.lidar, self.groups
        target, model = scene.targets[i], self.models[i]
        if isinstance(target.trajectory, Static):  # the pose as given, bit for bit
            s = target.trajectory.start
            ang = np.tile([s.range_m, s.azimuth, s.elevation, *s.attitude], (len(groups), 1))
        else:
            ang = angles_of_poses(*target.poses(t0 + g.time_s[groups]))
        table = np.empty((len(groups), 6))
        table[:, 0] = model.types.code(target.type_name)
        table[:, 1:] = ang[:, [0, 2, 3, 4, 5]]
        why = _outside_space(model.space, table)
        if why is not None:
            return None, why
        turn_a = np.mod(ang[:, 1] - scene.pointing_azimuth + np.pi, 2 * np.pi) - np.pi
        dw = np.rint(turn_a / lidar.r_alpha).astype(np.int64)
        dh = np.rint((ang[:, 2] - scene.pointing_elevation) / lidar.r_beta).astype(np.int64)
        if model.ANY_LIDAR:
            # the target's own window, wide enough to reach every cell of the scene's from
            # its offset (the same cells, read at the same coordinates, never clipped short)
            model.use_lidar(replace(lidar,
                                    width=2 * (lidar.width // 2 + int(np.abs(dw).max()) + 1),
                                    height=2 * (lidar.height // 2 + int(np.abs(dh).max()) + 1)))
        from apcg_core.typetable import Conditions
        seed = int(np.random.SeedSequence([self.seed % 2**63, frame, i + 1]).generate_state(1)[0])
        # groups that see the target in the same pose (a static target, a flash) share one
        # drawing: each distinct (condition, offset) is generated once, in first-seen order
        key = np.column_stack([table, dw, dh])
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        inverse = rank[np.ravel(inverse)]
        cloud = model.generate(Conditions(model.types, table[first[order]]), count=1,
                               seed=seed).cloud
        drawn = np.argsort(cloud.sample, kind="stable")  # each drawing's cells together
        c_w, c_h, c_r = (np.asarray(a)[drawn] for a in (cloud.cell_w, cloud.cell_h,
                                                         cloud.range_m))
        # every group's cells: its drawing's cells, moved by the offset, cut to the group
        per = np.bincount(cloud.sample, minlength=len(order))
        starts = np.concatenate([[0], np.cumsum(per)[:-1]])
        pos = np.repeat(np.arange(len(groups)), per[inverse])  # group position of each cell
        idx = np.arange(len(pos)) - np.repeat(np.cumsum(per[inverse]) - per[inverse],
                                              per[inverse]) + starts[inverse][pos]
        w = c_w.astype(np.int64)[idx] + dw[pos]
        h = c_h.astype(np.int64)[idx] + dh[pos]
        k = groups[pos]
        keep = (w >= g.w_lo[k]) & (w <= g.w_hi[k]) & (h >= g.h_lo[k]) & (h <= g.h_hi[k])
        n = int(keep.sum())
        return (np.full(n, i + 1, np.int32), w[keep], h[keep],
                c_r.astype(np.float64)[idx][keep], np.zeros(n, bool)), None

    def _ideal(self, parts):
        lidar, el = self.scene.lidar, self.scene.pointing_elevation
        inst, w, h, r, sim = _concat(parts, 5, (np.int32, np.int32, np.int32, np.float64, bool))
        # per cell the nearest surface of every target; a tie goes to the first target
        order = np.lexsort((inst, r, w, h))
        inst, w, h, r, sim = inst[order], w[order], h[order], r[order], sim[order]
        first = np.ones(len(w), bool)
        first[1:] = (w[1:] != w[:-1]) | (h[1:] != h[:-1])
        inst, w, h, r, sim = inst[first], w[first], h[first], r[first], sim[first]
        if self.sim.quantize:  # a simulated range to its bin; a generated one is the model's
            r = np.where(sim, lidar.quantize_range(r), r)
        alpha, beta = lidar.cell_centre_angles(w, h, el)
        return PointCloud(spherical_to_cartesian(alpha, beta, r), r, w, h,
                          np.zeros(len(w), np.int64)), inst

    def _photons(self, parts, frame: int, t0: float):
        from apcg_core.sensor import SubRayHits, photon_cloud, to_cloud
        scene, lidar = self.scene, self.scene.lidar
        inst, w, h, r, cos, sub = _concat(parts, 6, (np.int32, np.int32, np.int32, np.float64,
                                                     np.float64, np.int64))
        # per sub-ray the nearest surface of every target, in the simulator's hit order
        order = np.lexsort((inst, r, sub, w, h))
        inst, w, h, r, cos, sub = (a[order] for a in (inst, w, h, r, cos, sub))
        first = np.ones(len(w), bool)
        first[1:] = (w[1:] != w[:-1]) | (h[1:] != h[:-1]) | (sub[1:] != sub[:-1])
        inst, w, h, r, cos = (a[first] for a in (inst, w, h, r, cos))
        hits = SubRayHits(np.zeros(len(w), np.int64), w, h, r, cos, 1,
                          self.sim.supersample**2)
        gate = scene.gate_range_m
        if gate is None:
            gate = float(scene.targets[0].trajectory.ranges(scene.targets[0].poses(t0)[0])[0])
        rho = self.reflectivity[inst - 1] if len(inst) else np.zeros(0)
        cells = photon_cloud(hits, np.array([gate]), rho, self.sensor, lidar, self.seed,
                             np.array([frame], np.int64))
        cloud = to_cloud(cells, np.array([scene.pointing_elevation]), lidar)
        # a signal point belongs to the target whose hit in its cell is nearest its range
        label = np.zeros(len(cloud), np.int32)
        sig = np.flatnonzero(cloud.label == 1)
        if len(sig) and len(w):
            ck = (h.astype(np.int64) - lidar.h_min) * lidar.width + (w - lidar.w_min)
            pk = ((cloud.cell_h[sig].astype(np.int64) - lidar.h_min) * lidar.width
                  + (cloud.cell_w[sig] - lidar.w_min))
            o = np.lexsort((inst, ck))
            ck_s, r_s, inst_s = ck[o], r[o], inst[o]
            lo = np.searchsorted(ck_s, pk, side="left")
            hi = np.searchsorted(ck_s, pk, side="right")
            for j, (a, z) in enumerate(zip(lo, hi, strict=True)):
                if z > a:
                    d = np.abs(r_s[a:z] - cloud.range_m[sig[j]])
                    label[sig[j]] = inst_s[a + int(np.argmin(d))]
        return cloud, label


def _outside_space(space, table: np.ndarray) -> str | None:
    """Why condition rows lie outside a model's condition space (the first value out), or
    None (``ConditionSpace.check``'s bounds and slack)."""
    from apcg_core.condition import FIELDS
    lo, hi = space.bounds(table)
    slack = 1e-12 * np.maximum(np.abs(lo), np.abs(hi))
    out = (table < lo - slack) | (table > hi + slack)
    if not out.any():
        return None
    row, col = np.argwhere(out)[0]
    f = 1.0 if col == 1 else 1.0 / DEG
    unit = " m" if col == 1 else " deg"
    name = FIELDS[col] + ("" if col == 1 else "_deg")
    return (f"{name} {table[row, col] * f:.4g}{unit} outside the model's "
            f"{lo[row, col] * f:.4g} .. {hi[row, col] * f:.4g}{unit}")


def _concat(parts, k, dtypes):
    if not parts:
        return tuple(np.zeros(0, d) for d in dtypes)
    return tuple(np.concatenate([p[j] for p in parts]).astype(dtypes[j], copy=False)
                 for j in range(k))


# --- files -------------------------------------------------------------------------------------
def scan_meta(scene: Scene, scanner: SceneScanner, frame: int, scan=None) -> dict:
    """What a frame file's ``meta`` says (the same for a scan and a sequence's frame); with
    generated targets, ``generator`` (track id -> the model, as the scene's record names it)
    and ``fallback`` (track id -> why its model could not draw it in this frame)."""
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "frame": int(frame),
            "scene_sha256": scene.digest(), "backend": scanner.sim.backend,
            "supersample": scanner.sim.supersample, "quantized": scanner.sim.quantize,
            "lidar": scene.lidar.to_dict(),
            "types": [t.type_name for t in scene.targets]}
    if scanner.sensor is not None:
        meta.update(sensor=scanner.sensor.to_dict(), seed=scanner.seed)
    meshes = mesh_stamps(scene)
    if meshes:  # only with a user type: a built-in scene's frames as before
        meta["mesh_sha256"] = meshes
    if any(m is not None for m in scanner.models):
        meta["generator"] = {str(t.instance): scene.record["targets"][k]["generator"]
                             for k, t in enumerate(scene.targets) if t.generator is not None}
        meta["fallback"] = {str(k): v for k, v in sorted(scan.fallback.items())} \
            if scan is not None else {}
    return meta


def frame_npz(scanner: SceneScanner, frame: int) -> tuple[bytes, FrameScan]:
    """One frame file's bytes (``apcg_core.scene.sequence``) and the scan it holds."""
    from apcg_core.io.dataset import npz_bytes
    scan = scanner.scan(frame)
    angles = angles_of_poses(scan.position, scan.rotation)
    return npz_bytes(frame_arrays(scan, angles, scan_meta(scanner.scene, scanner, frame,
                                                          scan))), \
        scan


def window_presence(scanner: SceneScanner, frames) -> np.ndarray:
    """(F, T) bool: whether each target has cells in the window in each frame (boxes only,
    no ray is cast)."""
    t0 = scanner.scene.frame_times(frames)
    out = np.zeros((len(frames), len(scanner.scene.targets)), bool)
    step = max(1, 4096 // len(scanner.groups))  # frames per batch of boxes: bounded memory
    for i in range(len(scanner.scene.targets)):
        for a in range(0, len(frames), step):
            out[a:a + step, i] = scanner._geometry(i, t0[a:a + step], per_frame=True)
    return out


# Poses computed at once by the checks before a sequence (frames x groups at most): bounded
# memory whatever the pattern (a cells raster has W x H groups a frame).
POSES_PER_BATCH = 65536


def _frame_batches(scanner: SceneScanner, frames):
    """(first row, scan times) of batches of whole frames: each frame's groups' times."""
    g = scanner.groups
    t0 = scanner.scene.frame_times(frames)
    step = max(1, POSES_PER_BATCH // len(g))
    for a in range(0, len(frames), step):
        yield a, (t0[a:a + step, None] + g.time_s[None, :]).ravel()


def sphere_presence(scanner: SceneScanner, frames) -> np.ndarray:
    """(F, T) bool: whether each target's bounding sphere can reach the window in each frame
    (at any of its groups' times). Never False where :func:`window_presence` is True: a quick
    screen (a 200-frame sequence's in milliseconds, its boxes' in seconds). The lidar inside
    a target at any of these times is refused (``SceneScanner._posed``)."""
    out = np.zeros((len(frames), len(scanner.scene.targets)), bool)
    ng = len(scanner.groups)
    for i in range(len(scanner.scene.targets)):
        for a, times in _frame_batches(scanner, frames):
            _, c, _ = scanner._posed(i, times)
            meets = scanner._sphere_meets(i, c)
            out[a:a + len(times) // ng, i] = meets.reshape(-1, ng).any(axis=1)
    return out


def _outside_message(scanner: SceneScanner, i: int, t0: float, when: str) -> str:
    scene, lidar = scanner.scene, scanner.scene.lidar
    target = scene.targets[i]
    p, _ = target.poses(t0)
    az, el, _ = cartesian_to_spherical(p[0])
    half_w = lidar.width / 2 * lidar.r_alpha / DEG
    half_h = lidar.height / 2 * lidar.r_beta / DEG
    return (f"{target.source} lies outside the lidar's window {when}: it is at azimuth "
            f"{az / DEG:.6g} deg, elevation {el / DEG:.6g} deg; the window spans "
            f"azimuth {scene.pointing_azimuth / DEG:.6g} +- {half_w:.4g} deg and elevation "
            f"{scene.pointing_elevation / DEG:.6g} +- {half_h:.4g} deg ([pointing], [lidar])")


def check_targets_seen(scanner: SceneScanner, frames, every_frame: bool) -> np.ndarray:
    """Refuse a target outside the window: a scan's (``every_frame``) by its exact cell box in
    its frame; a sequence's when its bounding sphere reaches the window in none of its frames
    (the boxes of every frame would cost as much as the scan: a target whose sphere reaches
    the window but whose box never does is recorded as never ``in_window``, not refused).
    Both read every target's pose at every group's time of every frame through
    ``SceneScanner._posed``, which refuses the lidar inside a target: called before anything
    is written, nothing is written before such a refusal. Returns the presence table."""
    seen = (window_presence if every_frame else sphere_presence)(scanner, frames)
    for i in range(seen.shape[1]):
        bad = ~seen[:, i] if every_frame else (None if seen[:, i].any() else ~seen[:, i])
        if bad is not None and bad.any():
            k = int(np.argmax(bad))
            t0 = float(scanner.scene.frame_times([frames[k]])[0])
            when = (f"at t = {t0:.6g} s" if every_frame
                    else f"in every frame ({len(frames)} frames)")
            raise InputError(_outside_message(scanner, i, t0, when))
    return seen


# Centres closer than this share of the smaller target's bounding radius: bodies that pass
# through each other (two aircraft flying in formation keep their centres at least a span
# apart, about twice the bounding radius).
OVERLAP_SHARE = 0.5


def overlap_warnings(scanner: SceneScanner, frames) -> list[str]:
    """One warning per pair of targets whose centres come within OVERLAP_SHARE of the smaller
    one's bounding radius at some frame's start: the scan is made (each cell takes whichever
    surface is nearer), but two bodies in one place are rarely what was meant."""
    scene = scanner.scene
    n = len(scene.targets)
    if n < 2:
        return []
    t0 = scene.frame_times(frames)
    radii = np.asarray(scanner.radii, np.float64)
    hits = {}  # (i, j) -> [frames, first time, distance then]
    for a in range(0, len(t0), 4096):  # bounded memory at 10^5 frames
        tt = t0[a:a + 4096]
        pos = np.stack([t.poses(tt)[0] for t in scene.targets])  # (T, n, 3)
        for i in range(n - 1):
            d = np.sqrt(((pos[i + 1:] - pos[i][None]) ** 2).sum(-1))  # (T - i - 1, n)
            close = d < OVERLAP_SHARE * np.minimum(radii[i], radii[i + 1:])[:, None]
            for j in np.flatnonzero(close.any(axis=1)):
                k = int(np.argmax(close[j]))
                h = hits.setdefault((i, i + 1 + int(j)), [0, float(tt[k]), float(d[j, k])])
                h[0] += int(close[j].sum())
    out = []
    for (i, j), (count, t, d) in sorted(hits.items()):
        a, b = scene.targets[i], scene.targets[j]
        out.append(f"{a.source} and {b.source} overlap: their centres are {d:.4g} m apart at "
                   f"t = {t:.6g} s ({count} of {len(frames)} frame(s)), less than half the "
                   f"smaller one's bounding radius ({min(radii[i], radii[j]):.4g} m), so their "
                   "bodies pass through each other and each cell takes the nearer surface")
    return out


def frame_warnings(scene: Scene, facts, sensor) -> list[str]:
    """Per target, over frames ``facts`` ((t_s, position (T, 3), points (T,), in_window (T,),
    clipped (T,)) each): the frames where its cloud is cut at the window's edge, and, with a
    sensor, those where it is in the window but none of its returns was recorded (outside
    the photon gate, or hidden), naming the target, the frames and the first time."""
    facts = list(facts)
    out = []
    for i, target in enumerate(scene.targets):
        cut = [f for f in facts if f[4][i]]
        if cut:
            out.append(f"{target.source} reaches beyond the lidar's window in {len(cut)} of "
                       f"{len(facts)} frame(s) (first at t = {cut[0][0]:.6g} s): its cloud is "
                       "cut at the window's edge")
        if sensor is None:
            continue
        empty = [f for f in facts if f[3][i] and f[2][i] == 0]
        if not empty:
            continue
        t, pos = empty[0][0], empty[0][1]
        r = float(np.sqrt((pos[i] ** 2).sum()))
        gate = (scene.gate_range_m if scene.gate_range_m is not None
                else float(np.sqrt((pos[0] ** 2).sum())))
        why = (f"its range {r:.6g} m lies outside the photon gate ({gate:.6g} +- "
               f"{sensor.gate_m / 2:.6g} m: [pointing] range_m, else the first target's range, "
               "and the sensor's gate_m)" if abs(r - gate) > sensor.gate_m / 2
               else "hidden behind another target, or too few photons return from it")
        out.append(f"{target.source} is in the window but the sensor recorded none of its "
                   f"returns in {len(empty)} of {len(facts)} frame(s) (first at t = {t:.6g} "
                   f"s): {why}")
    return out


def scan_scene(scene_path, output, backend: str = "embree", supersample: int | None = None,
               quantize: bool = True, sensor=None, seed: int = 0, lidar=None,
               generator: str | None = None, warnings: list | None = None) -> dict:
    """`apcg scene scan`: the scene's first frame (its [sequence] start_s) to one NPZ file.
    ``generator``: `--generator`, the model of every target that does not name its own.
    ``warnings``: a list the scan's warnings are appended to (overlapping targets, a cloud
    cut at the window's edge or emptied by the sensor)."""
    from apcg_core.io.dataset import write_atomic
    scene = load_scene(scene_path, lidar=lidar, generator=generator)
    k = supersample or (4 if sensor else 1)  # as `apcg simulate`: 4 rays a side feed a sensor
    scanner = SceneScanner(scene, backend, k, quantize, sensor, seed)
    try:
        check_targets_seen(scanner, [0], every_frame=True)
        data, scan = frame_npz(scanner, 0)
        found = overlap_warnings(scanner, [0]) + frame_warnings(
            scene, [(scan.t_s, scan.position, scan.points_of(), scan.in_window,
                     scan.clipped)], sensor)
    finally:
        scanner.close()
    write_atomic(Path(output), data)
    if warnings is not None:
        warnings += found
    summary = {"output": str(output), "points": len(scan.cloud),
               "points_per_target": scan.points_of().tolist(),
               "clipped": scan.clipped.tolist()}
    if sensor is not None:
        summary.update(signal=int((scan.cloud.label == 1).sum()),
                       noise=int((scan.cloud.label == 0).sum()))
    if scan.generated is not None:
        stats = generator_stats(scene.record, [(0, scan.generated, scan.in_window,
                                                scan.fallback)])
        summary["generator"] = stats
    return summary


def generator_stats(record: dict, frames) -> dict:
    """Per generated track, over ``frames`` ((frame, generated, in_window, fallback) each):
    the model, the frames in the window its model drew and those it could not (simulated
    instead: the fallback rule, SPEC section 10), with the first one's reason."""
    out = {}
    for f, generated, in_window, fallback in frames:
        for k, entry in enumerate(record["targets"]):
            if not entry.get("generator"):
                continue
            tid = str(k + 1)
            row = out.setdefault(tid, {"type": entry["type"],
                                       "model": entry["generator"]["model"],
                                       "model_sha256": entry["generator"]["sha256"],
                                       "generated_frames": 0, "fallback_frames": []})
            if not in_window[k]:
                continue
            if generated[k]:
                row["generated_frames"] += 1
            else:
                row["fallback_frames"].append(int(f))
                why = fallback.get(tid, fallback.get(k + 1))
                row.setdefault("first_fallback", f"frame {f}: {why}")
    return out


def fallback_warning(stats: dict) -> str | None:
    """One line naming each generated target its model could not draw in some frames."""
    bad = [(tid, row) for tid, row in stats.items() if row["fallback_frames"]]
    if not bad:
        return None
    parts = [f"target {tid} ({row['type']}) in {len(row['fallback_frames'])} of "
             f"{len(row['fallback_frames']) + row['generated_frames']} frames (first: "
             f"{row['first_fallback']})" for tid, row in bad]
    return ("the generator cannot draw every pose, so the simulator scanned "
            + "; ".join(parts) + ' (recorded under "generator")')


# --- sequences ---------------------------------------------------------------------------------
# Frames per task handed to an engine: small enough that a pool keeps its workers busy and a
# kill loses little, large enough that a task's overhead (a scene file read) vanishes.
FRAMES_PER_TASK = 8


@dataclass
class SequenceTask:
    """Frames of one sequence for one worker (small and picklable)."""

    index: int  # the task's number (an engine names its work by it)
    scene_path: str
    scene_sha256: str
    lidar: dict | None  # a command-line lidar overriding the file's; None: the file's
    frames: tuple
    directory: str
    backend: str
    supersample: int
    quantize: bool
    sensor: dict | None
    seed: int
    generator: str | None = None  # --generator ("default" or an absolute model directory)


_SCANNERS: dict = {}


def _scanner(task: SequenceTask) -> SceneScanner:
    from apcg_core.lidar import LidarParams
    key = (task.scene_path, task.scene_sha256, str(task.lidar), task.backend, task.supersample,
           task.quantize, str(task.sensor), task.seed, task.generator)
    if key not in _SCANNERS:
        for old in _SCANNERS.values():
            old.close()
        _SCANNERS.clear()
        lidar = LidarParams.from_dict(task.lidar) if task.lidar else None
        scene = load_scene(task.scene_path, lidar=lidar, generator=task.generator)
        if scene.digest() != task.scene_sha256:
            raise InputError(f"{task.scene_path} (or a trajectory file it names, or the mesh "
                             "of a user catalog type it names) changed while its sequence was "
                             "being built; run the command again")
        sensor = None
        if task.sensor is not None:
            from apcg_core.sensor import sensor_from_table
            sensor = sensor_from_table(task.sensor, source="sequence header [sensor]")
        _SCANNERS[key] = SceneScanner(scene, task.backend, task.supersample, task.quantize,
                                      sensor, task.seed)
    return _SCANNERS[key]


def run_sequence_task(task: SequenceTask) -> tuple[int, int]:
    """Compute and write the frames of ``task`` not yet written (each file whole); returns
    (frames written, frames in the task)."""
    from apcg_core.io.dataset import write_atomic
    from apcg_core.testpoints import wait_point

    from .shards import part_suffix
    scanner = _scanner(task)
    done = 0
    for f in task.frames:
        path = Path(task.directory) / frame_file(f)
        if path.exists():
            continue
        data, _ = frame_npz(scanner, f)
        wait_point("scene.frame-computed")
        write_atomic(path, data, part_suffix=part_suffix())
        done += 1
    return done, len(task.frames)


def sequence_header(scene: Scene, scanner: SceneScanner) -> dict:
    head = {"format": FORMAT, "version": FORMAT_VERSION, "scene": scene.record,
            "scene_sha256": scene.digest(), "frames": scene.frames,
            "frame_rate_hz": scene.frame_rate_hz, "start_s": scene.start_s,
            "frame_files": "frames/{frame:06d}.npz", "backend": scanner.sim.backend,
            "supersample": scanner.sim.supersample, "quantized": scanner.sim.quantize,
            "tracks": [{"track_id": t.instance, "type": t.type_name,
                        "catalog_index": t.type_index} | _mesh_of(scene, k)
                       for k, t in enumerate(scene.targets)],
            "sensor": None, "seed": scanner.seed}
    if scanner.sensor is not None:
        head["sensor"] = scanner.sensor.to_dict()
    return head


def build_sequence(scene_path, out_dir, backend: str = "embree", supersample: int | None = None,
                   quantize: bool = True, sensor=None, seed: int = 0, lidar=None,
                   workers: int = 1, engine: str = "local", address: str | None = None,
                   connect_timeout_s: float | None = None, progress: bool = True,
                   generator: str | None = None, warnings: list | None = None) -> dict:
    """`apcg scene sequence`: every frame of the scene's [sequence] into ``out_dir``
    (``apcg_core.scene.sequence``'s format); resumes where a killed run stopped, the same
    bytes whatever the engine and the number of workers. ``generator``: `--generator`.
    ``warnings``: a list the sequence's warnings are appended to (as :func:`scan_scene`)."""
    from apcg_core.io.dataset import json_bytes, write_atomic
    from apcg_core.lock import ProcessLock
    from apcg_core.progress import Progress
    from apcg_core.scene.sequence import HEADER

    from .build import BuildInterrupted, _remove_dead_parts, _say
    from .engine import RunSettings, get_engine
    from .shards import part_suffix
    scene = load_scene(scene_path, lidar=lidar, generator=generator)
    if generator not in (None, "default"):  # every worker reads the same directory
        generator = str(Path(generator).expanduser().resolve())
    k = supersample or (4 if sensor else 1)
    scanner = SceneScanner(scene, backend, k, quantize, sensor, seed)
    out = Path(out_dir)
    runner = get_engine(engine)
    settings = RunSettings(workers=workers, address=address, output=str(out.resolve()),
                           connect_timeout_s=connect_timeout_s, record=HEADER)
    runner.check(settings)
    frames = list(range(scene.frames))
    try:
        check_targets_seen(scanner, frames, every_frame=False)
        found = overlap_warnings(scanner, frames)
        header = json_bytes(sequence_header(scene, scanner))
        # what each frame file of this sequence says of itself (its own frame index aside)
        ours = {k: v for k, v in scan_meta(scene, scanner, 0).items()
                if k not in ("frame", "fallback")}
    finally:
        scanner.close()
    check_sequence_directory(out, header)  # stray frames, others' files: refused, named
    (out / "frames").mkdir(parents=True, exist_ok=True)
    lock = ProcessLock(out / SEQUENCE_LOCK, f"scene sequence into {out}")
    lock.acquire()
    try:
        head = out / HEADER
        if not check_sequence_directory(out, header):  # again: another run may have begun
            write_atomic(head, header, part_suffix=part_suffix())
        todo = []
        for f in frames:  # a frame is done only when it is this sequence's, whole
            path = out / frame_file(f)
            if path.exists() and (why := not_this_frame(path, f, ours)) is not None:
                _say(f"{path} is not this sequence's ({why}): made again",
                     "apcg scene sequence")
                path.unlink()
            if not path.exists():
                todo.append(f)
        tasks = [SequenceTask(i // FRAMES_PER_TASK, str(Path(scene_path).resolve()),
                              scene.digest(),
                              lidar.to_dict() if lidar is not None else None,
                              tuple(todo[i:i + FRAMES_PER_TASK]), str(out.resolve()), backend,
                              k, quantize, sensor.to_dict() if sensor is not None else None,
                              int(seed), generator)
                 for i in range(0, len(todo), FRAMES_PER_TASK)]
        bar = Progress(len(frames), "frame", progress, done=len(frames) - len(todo))
        t0 = time.perf_counter()
        try:
            if tasks:
                with runner.start(settings) as run:
                    for n, _ in run(run_sequence_task, tasks):
                        bar.update(n)
        except KeyboardInterrupt:  # as a dataset build: say how far it got, nothing half-made
            if settings.writers_are_local:
                _remove_dead_parts(out / "frames")
                _remove_dead_parts(out)
            done = sum((out / frame_file(f)).exists() for f in frames)
            raise BuildInterrupted(f"interrupted: {done} of {len(frames)} frames are done in "
                                   f"{out}; run the same command again to resume (finished "
                                   "frames are kept)") from None
        finally:
            for s in _SCANNERS.values():
                s.close()
            _SCANNERS.clear()
            bar.close()
        elapsed = time.perf_counter() - t0
        _remove_dead_parts(out / "frames")
        _remove_dead_parts(out)
        facts = []
        stats = finish_sequence(out, frames, facts)
    finally:
        lock.release()
    if warnings is not None:
        warnings += found + frame_warnings(scene, facts, sensor)
    summary = {"directory": str(out), "frames": len(frames), "built_frames": len(todo),
               "skipped_frames": len(frames) - len(todo), "seconds": round(elapsed, 3),
               "complete": True}
    if stats is not None:
        summary["generator"] = stats
    return summary


def not_this_frame(path: Path, frame: int, ours: dict) -> str | None:
    """Why the frame file ``path`` is not frame ``frame`` of the sequence whose frames say
    ``ours`` of themselves (:func:`scan_meta`, its frame index and fallbacks aside), read
    whole; None when it is."""
    import json
    try:
        meta = dict(read_frame(path).meta)
    except InputError as exc:
        return f"unreadable: {exc}"
    meta.pop("fallback", None)
    want = json.loads(json.dumps({**ours, "frame": int(frame)}))
    if json.loads(json.dumps(meta, default=str)) != want:
        return "another scene's or other options' frame"
    return None


def check_sequence_directory(out: Path, header: bytes) -> bool:
    """Whether ``out`` already holds this sequence (its header, byte for byte: True) or none
    yet (False: it is new or empty); refused when it holds a different one (another scene,
    other options, another Blender timeline), whose frames would otherwise be mixed with these
    or left stale beside them, when it holds anything else (someone's files: written over or
    mixed with the sequence's) and when it is a file. Every sequence writer (`apcg scene
    sequence`, the add-on's Scan Animation) asks here before it writes."""
    from apcg_core.scene.sequence import HEADER
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} is a file; a sequence is written into a directory (a new one, "
                         "or one holding this same sequence)")
    head = out / HEADER
    if not head.exists():
        _refuse_foreign_files(out)
        return False
    if not head.is_file() or (old := head.read_bytes()) != header:
        why = mesh_difference(old, header) if head.is_file() else None
        raise InputError(f"{out} already holds a different sequence ("
                         + (why or f"its {HEADER} differs from this scene and these options")
                         + "); write into a new directory or delete it")
    return True


def _mesh_of(scene: Scene, k: int) -> dict:
    """Target k's geometry stamp as the scene's record holds it (the catalog's mesh_record:
    a user type's ``{"mesh_sha256": ...}``, ``{}`` for a built-in type or a target of no
    scene file)."""
    entries = scene.record.get("targets") or []
    entry = entries[k] if k < len(entries) else {}
    return {"mesh_sha256": entry["mesh_sha256"]} if "mesh_sha256" in entry else {}


def mesh_stamps(scene: Scene) -> dict:
    """Track id -> mesh sha256 of the targets whose record has one (user catalog types)."""
    return {str(t.instance): m["mesh_sha256"] for k, t in enumerate(scene.targets)
            if (m := _mesh_of(scene, k))}


def mesh_difference(old: bytes, new: bytes) -> str | None:
    """Which targets of two sequence headers are the same catalog type cast from another
    mesh (a user type replaced by `apcg catalog add --force`), in words; None when no target
    differs so."""
    import json
    try:
        a = json.loads(old)["scene"]["targets"]
        b = json.loads(new)["scene"]["targets"]
    except (ValueError, KeyError, TypeError):
        return None
    if not isinstance(a, list) or not isinstance(b, list):
        return None
    out = []
    for k, (x, y) in enumerate(zip(a, b, strict=False), start=1):
        if not isinstance(x, dict) or not isinstance(y, dict) or x.get("type") != y.get("type"):
            continue
        was, now = x.get("mesh_sha256"), y.get("mesh_sha256")
        if was == now:
            continue
        if was is None:
            said = ("its sequence records no mesh for it: made before sequences recorded a "
                    "user type's mesh")
        elif now is None:
            said = f"mesh_sha256 {str(was)[:12]}... there, none now"
        else:
            said = f"mesh_sha256 {str(was)[:12]}... there, {str(now)[:12]}... now"
        out.append(f"target {k} ({y.get('type')}): its mesh changed since the directory was "
                   f"made, {said}; `apcg catalog add --force` replaces a user type's mesh")
    return "; ".join(out) or None


# A sequence writer's lock: with its drafts, all a writer leaves before its header (and an
# empty frames folder).
SEQUENCE_LOCK = ".sequence.lock"


def _refuse_foreign_files(out: Path) -> None:
    """Refuse a directory without a sequence header that holds anything but what a writer
    makes before its header, naming what is there."""
    from apcg_core.lock import is_lock_file
    from apcg_core.scene.sequence import HEADER
    if not out.is_dir():
        return
    frames = out / "frames"
    stray = sorted(frames.glob("*.npz")) if frames.is_dir() else []
    if stray:
        raise InputError(f"{frames} holds {len(stray)} frame file(s) ({stray[0].name}"
                         f"{', ...' if len(stray) > 1 else ''}) but {out} has no {HEADER}, so "
                         "nothing says which sequence made them; write into a new directory, "
                         "or delete them")
    there = sorted(p.name + ("/" if p.is_dir() else "") for p in out.iterdir()
                   if not is_lock_file(p.name, SEQUENCE_LOCK)
                   and not (p == frames and p.is_dir() and not any(p.iterdir())))
    if there:
        listed = ", ".join(there[:5]) + (f" and {len(there) - 5} more" if len(there) > 5 else "")
        raise InputError(f"{out} holds other files ({listed}) and no sequence (no {HEADER}); "
                         "a sequence is written into a new or empty directory, or one holding "
                         "this same sequence: choose another directory, or empty it")


def finish_sequence(out: Path, frames, facts: list | None = None) -> dict | None:
    """poses.csv from every frame file, then the manifest (last: the sequence is complete);
    with generated targets the manifest's ``generator`` counts, per track, the frames its
    model drew and those it could not (:func:`generator_stats`), which are returned.
    ``facts``: a list each frame's (t_s, position, points, in_window, clipped) is appended to
    (:func:`frame_warnings`)."""
    from apcg_core.io.dataset import json_bytes, sha256_file, write_atomic
    from apcg_core.scene.sequence import HEADER, MANIFEST, POSES

    from .shards import part_suffix
    seen = []

    def read(f):
        fr = read_frame(out / frame_file(f))
        if facts is not None:
            facts.append((fr.t_s, fr.position, fr.points, fr.in_window, fr.clipped))
        if fr.generated is not None:
            seen.append((f, fr.generated, fr.in_window, fr.meta.get("fallback", {})))
        return fr

    write_atomic(out / POSES, poses_csv_bytes(read(f) for f in frames),
                 part_suffix=part_suffix())
    manifest = {"complete": True, "frames": [
        {"file": frame_file(f), "sha256": sha256_file(out / frame_file(f))} for f in frames]}
    stats = None
    if seen:
        import json
        record = json.loads((out / HEADER).read_text())["scene"]
        stats = manifest["generator"] = generator_stats(record, seen)
    write_atomic(out / MANIFEST, json_bytes(manifest), part_suffix=part_suffix())
    return stats


def write_sequence(scanner: SceneScanner, out_dir, header_extra: dict | None = None,
                   progress=None) -> Path:
    """Every frame of ``scanner``'s scene into ``out_dir`` in this process (the add-on's Scan
    Animation: a scene made of Blender objects, not of a file), the same format as
    `apcg scene sequence`. ``progress(i, n)`` after each frame; returning False stops (the
    frames written are kept, no manifest)."""
    from apcg_core.io.dataset import json_bytes, write_atomic
    from apcg_core.scene.sequence import HEADER, MANIFEST
    scene = scanner.scene
    out = Path(out_dir)
    frames = list(range(scene.frames))
    check_targets_seen(scanner, frames, every_frame=False)
    header = json_bytes({**sequence_header(scene, scanner), **(header_extra or {})})
    if check_sequence_directory(out, header):
        # the same sequence again: every frame is scanned anew (the animation may have
        # changed), so the directory is not complete until the new manifest is written
        (out / MANIFEST).unlink(missing_ok=True)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    write_atomic(out / HEADER, header)
    for f in frames:
        data, _ = frame_npz(scanner, f)
        write_atomic(out / frame_file(f), data)
        if progress is not None and progress(f + 1, len(frames)) is False:
            return out
    finish_sequence(out, frames)
    return out


def sequence_warnings(scene_path, lidar=None, generator: str | None = None) -> list[str]:
    """Trajectories beyond their types; a generator's model used at a lidar it was not
    measured on."""
    from apcg_core.families.base import ModelTypes
    from apcg_core.scene.spec import scene_warnings
    scene = load_scene(scene_path, lidar=lidar, generator=generator)
    out = scene_warnings(scene)
    for d in dict.fromkeys(t.generator for t in scene.targets if t.generator is not None):
        w = ModelTypes(d).lidar_warning(scene.lidar)
        if w:
            out.append(w)
    return out
