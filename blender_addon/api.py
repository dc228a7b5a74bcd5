"""Everything the APCG panel does, as functions for scripts and headless Blender.

    from blender_addon import api          # or: from bl_ext.user_default.apcg import api
    lidar = api.add_lidar()
    jet = api.add_aircraft(lidar, "A320neo", range_m=4500, elevation_deg=3.4, pitch_deg=2.0,
                           yaw_deg=13.2)   # within the default model's ranges
    cloud = api.scan(lidar)[0]             # the lidar's view, by Blender's ray casting
    fake = api.generate(jet, seed=0)       # the same condition through the APCG generator
    api.export_cloud(cloud, "/tmp/a320neo.ply")
    own = api.make_target(lidar, bpy.data.objects["My jet"])  # any mesh; axes guessed
    api.add_to_catalog(own, "aircraft", "business_jet")     # then `apcg catalog list` has it

Scans equal `apcg simulate --backend blender` for the same condition: each target is cast in its
own body frame from its double-precision pose (the lidar tracks the target: its window is
centred on it), then points that other scene geometry hides are removed when ``occlusion`` is
on, by one ray from the lidar per point.
"""

from __future__ import annotations

import math

import numpy as np

from apcg_core.errors import InputError
from apcg_core.options import check_values

from .clouds import (
    checked_path,
    cloud_from_object,
    cloud_object,
    export_cloud,
    import_cloud,
    is_cloud,
    set_point_radius,
)
from .objects import (
    LENGTH_KEY,
    TYPE_KEY,
    add_aircraft,
    add_lidar,
    axes_label,
    body_mesh,
    check_lidar_values,
    check_target_scale,
    checked_body_mesh,
    checked_surface,
    depth_length_of,
    guess_axes,
    is_lidar,
    is_target,
    leaves_nothing_on_error,
    lidar_of,
    lidar_params,
    make_target,
    mesh_key,
    named,
    pose_of,
    require_lidar,
    require_target,
    set_pose,
    simulator_row,
    source_of,
    targets_of,
    triangles_of,
    world_mesh,
)

__all__ = ["add_lidar", "add_aircraft", "make_target", "add_to_catalog", "scan", "scan_target",
           "generate", "import_cloud", "export_cloud", "cloud_from_object", "pose_of",
           "set_pose", "targets_of", "is_lidar", "is_target", "is_cloud", "set_point_radius",
           "load_model", "world_mesh", "guess_axes", "axes_label", "check_model_knows",
           "read_lidar_file", "write_lidar_file", "scan_animation", "import_sequence"]

# Hits this much nearer than a point's range, on other geometry, hide the point.
OCCLUSION_MARGIN_M = 0.5


def _lidar_and_targets(lidar, targets):
    if targets is None:
        targets = targets_of(require_lidar(lidar))
    elif isinstance(targets, (list, tuple)):
        targets = list(targets)
    else:
        raise InputError(f"targets must be a list of APCG targets (or None: the lidar's), "
                         f"got {named(targets)}")
    if not targets:
        raise InputError("no targets to scan: add one with apcg.add_aircraft")
    for t in targets:
        require_target(t)
    return targets


def _pose_meta(pose: dict) -> dict:
    """A pose as the condition block of a cloud file's metadata (degrees, metres)."""
    return {"condition": {"range_m": pose["range_m"], **{
        f"{k}_deg": math.degrees(pose[k]) for k in ("elevation", "pitch", "yaw", "roll")}},
        "azimuth_deg": math.degrees(pose["azimuth"])}


def sensor_of(lidar):
    """The lidar object's sensor (its panel's Sensor: a preset or a TOML file), None for the
    ideal lidar."""
    import bpy

    from apcg_core.sensor import load_sensor
    ref = getattr(getattr(lidar, "apcg_lidar", None), "sensor", "") or "ideal"
    if ref.startswith("//"):  # a file beside the .blend, as Blender's file fields write it
        ref = bpy.path.abspath(ref)
    return load_sensor(ref, lidar_file=True)  # Read Lidar sets a lidar file as the Sensor


def read_lidar_file(lidar, ref):
    """Set the lidar object's parameters from a lidar preset or file (``--lidar``'s: a
    ``[lidar]`` table and optionally a ``[sensor]`` table, which then becomes its Sensor)."""
    from apcg_core.lidar import lidar_from_table
    from apcg_core.lidar import read_lidar_file as read
    require_lidar(lidar)
    path, doc = read(ref)
    params = lidar_from_table(doc["lidar"], source=str(path))
    if "sensor" in doc:
        from apcg_core.sensor import load_sensor
        load_sensor(path, lidar_file=True)  # refused here, named, rather than at the next Scan
    p = lidar.apcg_lidar
    values = {"r_alpha_deg": math.degrees(params.r_alpha),
              "r_beta_deg": math.degrees(params.r_beta),
              "range_resolution_m": params.r_r, "width": params.width, "height": params.height}
    check_lidar_values(lidar, values, str(path))  # Blender would clamp what it cannot hold
    for name, v in values.items():  # every check passed: only now is the object changed
        setattr(p, name, v)
    if "sensor" in doc:
        p.sensor = str(path)
    return lidar


def write_lidar_file(lidar, path) -> None:
    """Write the lidar object as a lidar file that every command's ``--lidar`` reads: its
    ``[lidar]`` table, and its Sensor as a ``[sensor]`` table unless it is ideal. Written
    whole or not at all."""
    from pathlib import Path

    from apcg_core.io.dataset import write_atomic
    from apcg_core.lidar import lidar_file_text
    require_lidar(lidar)
    sensor = sensor_of(lidar)
    text = lidar_file_text(lidar_params(lidar), sensor.to_dict() if sensor else None,
                           comment=f"APCG lidar {lidar.name!r}, written by the Blender add-on")
    write_atomic(Path(path), text.encode())


def reflectivity_of_target(target) -> float:
    """A target's reflectivity: its own ``apcg_reflectivity`` when set, else its catalog
    type's (SPEC section 8), else the default for an unknown category."""
    from apcg_core.sensor.reflectivity import (
        DEFAULT_REFLECTIVITY,
        check_reflectivity,
        reflectivity_of,
    )
    if "apcg_reflectivity" in target:
        return check_reflectivity(target["apcg_reflectivity"],
                                  f"apcg_reflectivity of {target.name!r}")
    from apcg_core.catalog.catalog import default_catalog
    try:
        return reflectivity_of(default_catalog().get(str(target.get(TYPE_KEY, ""))))
    except InputError:
        return DEFAULT_REFLECTIVITY


@leaves_nothing_on_error
def scan_target(target, backend: str = "blender", quantize: bool = True,
                supersample: int | None = None, occlusion: bool = True, simulator=None,
                name: str | None = None, sensor="lidar", seed: int = 0):
    """The lidar's view of one target as a new cloud object (``None`` if nothing is seen).

    ``sensor``: "lidar" (the lidar object's own, default), None / "ideal", a preset, a TOML
    file or a SensorParams; with one, the cloud is what that single-photon lidar records
    (SPEC section 8), its points labelled signal / noise, the draws seeded by ``seed``."""
    from apcg_core.sensor import SensorParams, load_sensor, to_cloud
    from dataset_builder.simulate import SimResult, Simulator
    lidar = lidar_of(require_target(target))
    seed = check_values(seed=seed, supersample=supersample)["seed"]
    params = lidar_params(lidar)
    if isinstance(sensor, str) and sensor == "lidar":
        sensor = sensor_of(lidar)
    elif not isinstance(sensor, SensorParams):
        sensor = load_sensor(sensor)
    mesh = body_mesh(target)
    table = simulator_row(target, mesh)
    pose = pose_of(target)
    length = depth_length_of(target, 0.0)
    own = simulator is None
    k = supersample or (4 if sensor else 1)
    sim = simulator or Simulator(backend, params, quantize=quantize, supersample=k)
    try:
        if sensor is not None:
            cells, clipped, n_rays = sim.photon_cells(
                mesh, table, sensor, reflectivity_of_target(target), seed, key=mesh.key)
            res = SimResult(to_cloud(cells, table[:, 2], params), 1, clipped, n_rays,
                            sim.backend)
        else:
            res = sim.simulate(mesh, table, key=mesh.key)
    finally:
        if own:
            sim.close()
    cloud = res.cloud
    hidden = 0
    if occlusion and len(cloud):
        keep = _unoccluded(lidar, target, cloud.xyz, pose["azimuth"])
        hidden = int((~keep).sum())
        cloud = cloud.select(keep)
    meta = {"type": target.get(TYPE_KEY),
            **_pose_meta(pose), "backend": sim.backend,
            "quantized": sim.quantize, "supersample": sim.supersample,
            "lidar": params.to_dict(), "depth_length_m": length,
            "clipped": bool(res.clipped[0]), "occluded_points": hidden}
    if sensor is not None:
        meta.update(sensor=sensor.to_dict(), seed=seed,
                    reflectivity=reflectivity_of_target(target))
    return cloud_object(cloud, name or f"{target.name} scan", lidar=lidar, source="scan",
                        r0=pose["range_m"], beta0=pose["elevation"], azimuth=pose["azimuth"],
                        meta=meta)


@leaves_nothing_on_error
def scan(lidar, targets=None, backend: str = "blender", quantize: bool = True,
         supersample: int | None = None, occlusion: bool = True, progress=None,
         sensor="lidar", seed: int = 0) -> list:
    """Scan every target of ``lidar`` (or ``targets``): one cloud object per target, with the
    lidar's sensor unless ``sensor`` says otherwise (see :func:`scan_target`).

    ``progress(i, n)`` is called after each target; returning False stops early."""
    from apcg_core.sensor import SensorParams, load_sensor
    from dataset_builder.simulate import Simulator
    targets = _lidar_and_targets(lidar, targets)
    seed = check_values(seed=seed, supersample=supersample)["seed"]
    if isinstance(sensor, str) and sensor == "lidar":
        sensor = sensor_of(lidar_of(targets[0]))
    elif not isinstance(sensor, SensorParams):
        sensor = load_sensor(sensor)
    out = []
    with Simulator(backend, lidar_params(lidar_of(targets[0])), quantize=quantize,
                   supersample=supersample or (4 if sensor else 1)) as sim:
        for i, t in enumerate(targets):
            if lidar_params(lidar_of(t)) != sim.lidar:
                raise InputError("targets of one scan must share a lidar's parameters")
            out.append(scan_target(t, occlusion=occlusion, simulator=sim, sensor=sensor,
                                   seed=seed))
            if progress is not None and progress(i + 1, len(targets)) is False:
                break
    return out


def _unoccluded(lidar, target, xyz_obs: np.ndarray, azimuth: float) -> np.ndarray:
    """True for points no other visible scene geometry hides from the lidar."""
    import bpy
    from mathutils import Vector

    from apcg_core.frames import observation_to_lidar_local
    depsgraph = bpy.context.evaluated_depsgraph_get()
    scene = bpy.context.scene
    world = np.array([list(r) for r in lidar.matrix_world], dtype=np.float64)
    local = observation_to_lidar_local(xyz_obs, azimuth)
    pts = local @ world[:3, :3].T + world[:3, 3]
    origin = Vector(world[:3, 3].tolist())
    # the object a made target was made from is the same aircraft, present in the scan as that
    # target: it hides nothing, of it or of any other target (a lidar that make_target added
    # at the origin may sit inside it)
    own = ({target} | {source_of(o) for o in scene.objects if is_target(o)}) - {None}
    keep = np.ones(len(pts), bool)
    for i, p in enumerate(pts):
        d = p - world[:3, 3]
        dist = float(np.linalg.norm(d))
        limit = dist - OCCLUSION_MARGIN_M
        start = origin
        while limit > 0:  # step past hits on the target itself (its far side can't hide it)
            hit, loc, _n, _f, obj, _m = scene.ray_cast(depsgraph, start, Vector((d / dist)
                                                                                .tolist()),
                                                       distance=limit)
            if not hit:
                break
            if obj is None or obj.original not in own:
                keep[i] = False
                break
            step = (loc - start).length + 1e-3
            start = loc + Vector((d / dist).tolist()) * 1e-3
            limit -= step
    return keep


def load_model(path=None, runtime: str = "auto"):
    """The model in ``path`` (default: the shipped one), whatever its family."""
    from apcg_core.families import load_model as load
    return load(path, runtime=runtime)


# The most samples one Generate makes (the panel's Samples field takes no more).
MAX_GENERATE_COUNT = 10_000


@leaves_nothing_on_error
def generate(target, model=None, count: int = 1, seed: int = 0, runtime: str = "auto",
             name: str | None = None):
    """APCG point clouds for a target's condition (the default model unless ``model``, a model
    directory or a loaded model of any family, is given): one object, ``count`` samples
    (attribute ``sample``). The target's type reaches the model by its catalog name.
    """
    from apcg_core.families import ModelTypes
    require_target(target, lidar=False)
    checked = check_values(count=count, seed=seed)
    count, seed = checked["count"], checked["seed"]
    if count > MAX_GENERATE_COUNT:
        raise InputError(f"count = {count!r} not accepted: at most {MAX_GENERATE_COUNT} "
                         "samples a call (the Generate panel's limit); call again for more")
    if not isinstance(model, ModelTypes):
        model = load_model(model, runtime=runtime)
    pose = pose_of(target)
    name_of_type = check_model_knows(model, target)
    owner = lidar_of(target)
    if owner is not None:  # at the lidar object's cells (issue 33)
        try:  # a family that draws at its training lidar only is refused at another, as
            model.use_lidar(lidar_params(owner))  # `apcg generate --lidar` refuses it
        except InputError as exc:
            raise InputError(f"target {target.name!r} of lidar {owner.name!r}: {exc}") from None
    try:
        cond = model.condition(name_of_type, pose["range_m"], pose["elevation"],
                               pose["pitch"], pose["yaw"], pose["roll"])
    except InputError as exc:  # which target, which model: the condition alone names neither
        raise InputError(f"target {target.name!r} ({name_of_type}) for the model "
                         f"{model.directory}: {exc}") from None
    res = model.generate(cond, count=count, seed=seed)
    meta = {"model": str(model.directory), "family": model.family,
            "runtime": getattr(model, "runtime", None), "seed": seed,
            "count": count, "type": name_of_type,
            **_pose_meta(pose), "tau": getattr(model, "tau", None),
            "lidar": model.lidar.to_dict()}
    return cloud_object(res.cloud, name or f"{target.name} APCG", lidar=lidar_of(target),
                        source="generated", r0=pose["range_m"], beta0=pose["elevation"],
                        azimuth=pose["azimuth"], meta=meta)


def lidar_fit_warning(model, lidar) -> str | None:
    """One line when ``model`` does not hold at the lidar object ``lidar``: a family that draws
    at its training lidar only, asked for another, or a lidar outside those the model was
    measured on (its model.json; SPEC section 1)."""
    params = lidar_params(lidar)
    if not model.ANY_LIDAR:
        if params == model.trained_lidar:
            return None
        return (f"the {model.family} model draws at the lidar it was trained on "
                f"({model.trained_lidar.describe()}), not at {lidar.name}'s "
                f"({params.describe()}); an apcg-plus model draws at any lidar")
    return model.lidar_warning(params)


def check_model_knows(model, target) -> str:
    """The target's type name when ``model`` knows it; else an InputError that names the type
    and how to teach it to the model."""
    import shlex
    name = str(target.get(TYPE_KEY, target.name))
    if name in model.types or name.strip().isdigit():  # digits: a catalog index
        return name
    raise InputError(
        f"the model {model.directory} does not know the type {name!r} (target "
        f"{target.name!r}), so it cannot generate it: add the target to the catalog (Add to "
        f"Catalog), then teach the model the type: apcg teach --model {model.directory} "
        f"--type {shlex.quote(name)} -o NEW_MODEL_DIR, and generate with NEW_MODEL_DIR; or "
        "make the target with the name of a catalog type the model knows")


@leaves_nothing_on_error
def add_to_catalog(target, kind: str = "aircraft", category: str = "user",
                   name: str | None = None, force: bool = False, catalog=None,
                   reflectivity: float | None = None):
    """Save a target's body mesh as a new type of the user catalog (``apcg catalog list`` shows
    it; the command line finds it under the same APCG_DATA_DIR). ``name`` defaults to the
    target's type name. A size implausible for ``kind`` ("aircraft" or "drone") is refused
    (InputError, naming the likely unit) unless ``force``. The target then carries the new
    type's name. ``reflectivity`` (at the lidar's wavelength, in (0, 1]) defaults to the
    target's own ``apcg_reflectivity`` when it has one, else the category's (SPEC section 8).
    Returns the new catalog type (apcg_core.catalog.AircraftType)."""
    import bpy

    from apcg_core.catalog import default_catalog
    require_target(target, lidar=False)
    check_target_scale(target)  # a scaled target is not the mesh that would be added
    catalog = catalog or default_catalog()
    name = (name or str(target.get(TYPE_KEY, target.name))).strip()
    body = body_mesh(target)
    # what `apcg catalog add` stores of a file: checked, its zero-area triangles dropped
    mesh = checked_surface(f"target {target.name!r}", body.vertices, body.faces, flat_ok=False)
    src = source_of(target)
    where = bpy.data.filepath or "an unsaved .blend"
    source = f"Blender object {(src or target).name!r} in {where}"
    if reflectivity is None and "apcg_reflectivity" in target:
        reflectivity = float(target["apcg_reflectivity"])
    t = catalog.add_user_type(name, mesh, kind, category,
                              source=source, force=force, reflectivity=reflectivity)
    if reflectivity is not None:
        target["apcg_reflectivity"] = float(t.reflectivity)
    target[TYPE_KEY] = t.name
    target[LENGTH_KEY] = float(catalog.depth_length_m(t))
    return t


# --- animations: several targets, frame by frame (issue 36; docs/SCENES.md) ---------------------
def _pose_in_lidar(lidar, target) -> dict:
    """The target's pose at the current frame as the lidar sees it: its placement (keyframes,
    parents, constraints such as Follow Path all included), as a Scan reads it."""
    return pose_of(target, lidar)


def scan_animation(lidar, directory, targets=None, frame_start: int | None = None,
                   frame_end: int | None = None, backend: str = "blender", scan=None,
                   quantize: bool = True, supersample: int | None = None, sensor="lidar",
                   seed: int = 0, progress=None):
    """Scan Animation: every frame of the scene's timeline (``frame_start`` .. ``frame_end``,
    default the scene's) as one scene of all of ``lidar``'s targets (or ``targets``), nearest
    surface first, written to ``directory`` as `apcg scene sequence` writes it (frame files
    with instance and type labels, poses, track ids: docs/SCENES.md). Each target moves as
    Blender animates it (keyframes, parents, constraints: Follow Path...), its pose read at
    every frame and interpolated between frames for a scan that takes time (``scan``: a
    ``[scan]`` table as a dict, default flash). Its shape is Blender's at each frame too
    (keyframed modifiers, shape keys, armatures): a target whose evaluated mesh changes is
    cast as it is at that frame's start. The window looks where the first target is at
    the first frame. Returns the directory."""
    from pathlib import Path

    import bpy

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.scene.poses import poses_from_angles
    from apcg_core.scene.scan import make_pattern
    from apcg_core.scene.spec import Scene, SceneTarget, check_scan_fits, default_pointing
    from apcg_core.scene.trajectory import Sampled
    from apcg_core.sensor import SensorParams, load_sensor
    from dataset_builder.scene import SceneScanner, write_sequence
    targets = _lidar_and_targets(lidar, targets)
    seed = check_values(seed=seed, supersample=supersample)["seed"]
    directory = checked_path(directory, "directory", "the directory to write the sequence "
                             "into (a new or empty one, or one holding this same sequence)")
    scene = bpy.context.scene
    start = scene.frame_start if frame_start is None else _frame("frame_start", frame_start)
    end = scene.frame_end if frame_end is None else _frame("frame_end", frame_end)
    if end < start:
        raise InputError(f"frame_end {end} is before frame_start {start}")
    fps = scene.render.fps / scene.render.fps_base
    pattern = make_pattern(scan, "Scan Animation")
    params = lidar_params(lidar)
    # the scene file's check (Scene makes it again), before the timeline is read; a timeline
    # of one frame has a frame rate too, and its scan must end before the next frame
    check_scan_fits(pattern, params, max(end - start + 1, 2), fps, "Scan Animation")
    # one Blender frame past the end when a frame's scan takes time: its last rows fire then
    last = end + (1 if pattern.groups(params).duration_s > 0 else 0)
    blender_frames = list(range(start, last + 1))
    now = scene.frame_current
    poses = [[] for _ in targets]  # by the object itself: names need not be unique
    # each target's shape at each frame (a keyframed modifier, shape key, armature...): its
    # first frame's mesh, then each frame's key and bounding radius; a frame's mesh is read
    # again when it is scanned (_FrameShapes), so memory holds one shape per target
    first_meshes, keys, radii = [None] * len(targets), [[] for _ in targets], \
        [[] for _ in targets]
    try:
        for f in blender_frames:
            scene.frame_set(f)
            for k, t in enumerate(targets, start=1):
                try:
                    poses[k - 1].append(_pose_in_lidar(lidar, t))
                    v, fc = triangles_of(t)
                    key = mesh_key(t, v, fc)
                    if not keys[k - 1] or key != keys[k - 1][-1]:  # a shape not yet checked
                        mesh = checked_body_mesh(t, v, fc, key)
                        radius = _bounding_radius(v)
                except (ValueError, InputError) as exc:  # ValueError: on the lidar
                    raise InputError(f"Blender target {k} ({t.name}): at frame {f}: {exc}"
                                     ) from None
                if first_meshes[k - 1] is None:
                    first_meshes[k - 1] = mesh
                keys[k - 1].append(key)
                radii[k - 1].append(radius)
    finally:
        scene.frame_set(now)
    times = (np.array(blender_frames) - start) / fps
    cat = default_catalog()
    scene_targets = []
    for i, (t, ps) in enumerate(zip(targets, poses, strict=True), start=1):
        pos, _ = poses_from_angles([p["range_m"] for p in ps], [p["azimuth"] for p in ps],
                                   [p["elevation"] for p in ps], 0.0, 0.0, 0.0)
        att = [[p["pitch"], p["yaw"], p["roll"]] for p in ps]
        type_name = str(t.get(TYPE_KEY, "") or t.name)
        try:
            ty = cat.get(type_name)
            index, category = ty.index, ty.category
        except InputError:  # a made target of no catalog type
            index, category = -1, ""
        mesh = first_meshes[i - 1]
        scene_targets.append(SceneTarget(
            i, type_name, index, category, Sampled(times, pos, att),
            f"Blender target {i} ({t.name})", mesh=mesh,
            reflectivity=reflectivity_of_target(t), key=mesh.key))
    az, el = default_pointing(scene_targets, 0.0)
    record = {"blender": {"lidar": lidar.name, "targets": [t.name for t in targets],
                          "frame_start": start, "frame_end": end, "fps": fps},
              "lidar": params.to_dict(), "scan": pattern.to_dict()}
    sc = Scene(params, scene_targets, pattern, az, el, None, end - start + 1, fps, 0.0,
               record, "Blender scene")
    if isinstance(sensor, str) and sensor == "lidar":
        sensor = sensor_of(lidar)
    elif not isinstance(sensor, SensorParams):
        sensor = load_sensor(sensor)
    k = supersample or (4 if sensor else 1)
    scanner = _frame_shapes(SceneScanner)(sc, backend, k, quantize, sensor, seed, catalog=cat)
    scanner.shapes = (targets, start, keys, radii)
    # the checks made before any frame is written take each target at its largest
    scanner.radii = [max(r) for r in radii]
    try:
        return write_sequence(scanner, Path(directory), {"blender": record["blender"]},
                              progress)
    finally:
        scanner.close()
        if scene.frame_current != now:
            scene.frame_set(now)


def _bounding_radius(vertices) -> float:
    from dataset_builder.rays import bounding_radius
    return bounding_radius(vertices)


def _frame_shapes(scanner_class):
    """A SceneScanner that casts each target's shape at each frame: ``shapes`` = (the Blender
    targets, the first Blender frame, each target's mesh key at each frame). Before a frame
    is scanned, a target whose shape differs from the one it holds is read again, at that
    frame (Blender's evaluated mesh); one that keeps its shape costs nothing more. (A frame
    whose scan takes time casts the shape of the frame's start.)"""
    class FrameShapes(scanner_class):
        shapes = None

        def scan(self, frame: int):
            import bpy
            targets, start, keys, radii = self.shapes
            scene = bpy.context.scene
            for i, t in enumerate(targets):
                self.radii[i] = radii[i][frame]
                if keys[i][frame] == self.keys[i]:
                    continue
                if scene.frame_current != start + frame:
                    scene.frame_set(start + frame)
                mesh = body_mesh(t)
                self.meshes[i], self.keys[i] = mesh, mesh.key
            return super().scan(frame)

    return FrameShapes


def _frame(name: str, value) -> int:
    """A timeline frame number given to the API: an integer Blender's timeline holds (what
    frame_set would clamp or refuse is refused here, named)."""
    import bpy
    limits = bpy.types.Scene.bl_rna.properties["frame_current"]
    try:
        ok = not isinstance(value, (bool, str)) and float(value) == int(value)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok or not limits.hard_min <= int(value) <= limits.hard_max:
        raise InputError(f"{name} = {value!r} not accepted: a frame number (an integer from "
                         f"{limits.hard_min} to {limits.hard_max}, Blender's timeline)")
    return int(value)


VISIBILITY = ("hide_viewport", "hide_render")


@leaves_nothing_on_error
def import_sequence(directory, lidar=None, name: str | None = None):
    """A sequence directory (`apcg scene sequence`'s or Scan Animation's) as an animated point
    cloud: one cloud object per frame, in a collection of its own, each shown on its own
    timeline frame only (keyframed visibility), with ``instance`` and, for a photon cloud,
    ``label`` point attributes. A Scan Animation's frames land on the frames they were scanned
    at; another sequence's from the scene's frame_start. Returns the collection."""
    from pathlib import Path

    import bpy

    from apcg_core.cloud import PointCloud
    from apcg_core.scene.sequence import load_sequence

    from .clouds import _add_attr
    directory = checked_path(directory, "directory", "a sequence directory (apcg scene "
                             "sequence's or Scan Animation's)")
    seq = load_sequence(directory)
    blender = seq.header.get("blender") or {}
    first = blender.get("frame_start", bpy.context.scene.frame_start) if isinstance(
        blender, dict) else None
    first = _frame(f"{directory}: sequence.json's blender.frame_start", first)
    coll = bpy.data.collections.new(name or f"APCG sequence {Path(directory).name}")
    bpy.context.scene.collection.children.link(coll)
    for f in seq:
        cloud = PointCloud(f.xyz, f.range_m, f.cell_w, f.cell_h, None, f.label, f.count,
                           f.pulse)
        obj = cloud_object(cloud, f"{coll.name} {f.frame:04d}", lidar=lidar, source="scan",
                           azimuth=0.0, meta={"frame": f.frame, "t_s": f.t_s,
                                              "types": [str(t) for t in f.track_type]},
                           collection=coll)
        _add_attr(obj.data, "instance", "INT", f.instance.astype(np.int32))
        at = int(first) + f.frame
        for attr in VISIBILITY:
            for frame, hidden in ((at - 1, True), (at, False), (at + 1, True)):
                setattr(obj, attr, hidden)
                obj.keyframe_insert(attr, frame=frame)
    bpy.context.scene.frame_set(bpy.context.scene.frame_current)
    return coll
