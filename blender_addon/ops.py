"""Operators (bpy.ops.apcg.*). Each is a thin shell over :mod:`.api`: scripts get the same
results by calling the api functions or the operators.

Long work (scan, generate) runs in chunks of one target from a timer when started from the UI
(invoke): a progress bar, Esc cancels and removes what was made. Called from a script or
headless (execute), it runs to the end at once. Errors are reported in Blender's UI.

No `from __future__ import annotations` here: Blender reads the annotations as objects."""

import traceback

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from apcg_core.errors import APCGError

from . import api
from .objects import AXES_KEY, TYPE_KEY, cancelled_leaves_nothing, is_lidar, lidar_of, targets_of

_TYPE_ITEMS = []  # kept alive: Blender does not copy enum items returned by a callback
_OLD_TYPE_ITEMS = []  # earlier lists, kept alive too (a menu may still show them)


def _type_items(self, context):
    from apcg_core.catalog import default_catalog
    cat = default_catalog()  # "Add to Catalog" appends to it: the menu follows
    if [item[0] for item in _TYPE_ITEMS] != cat.names():
        _OLD_TYPE_ITEMS.append(list(_TYPE_ITEMS))
        _TYPE_ITEMS[:] = [(t.name, t.name, f"{t.kind}, {t.category}, {t.length_m:g} m")
                          for t in cat]
    return _TYPE_ITEMS


_AXIS_ITEMS = [(a, a, f"The model's {a} axis (in its world orientation)")
               for a in ("X", "-X", "Y", "-Y", "Z", "-Z")]


def _report_error(op, exc: Exception) -> set:
    if isinstance(exc, APCGError):
        op.report({"ERROR"}, str(exc))
    elif isinstance(exc, OSError):  # the file system's answer, in one line
        where = f" {exc.filename}" if exc.filename else ""
        op.report({"ERROR"}, f"cannot write or read{where}: {exc.strerror or exc}")
    else:
        traceback.print_exc()
        op.report({"ERROR"}, f"{type(exc).__name__}: {exc}")
    return {"CANCELLED"}


def _active_lidar(context, create: bool = False, strict: bool = True):
    """The active object's lidar, else the scene's first (``create``: a new one); ``strict``:
    an active target of no lidar is refused (polls ask with strict=False: they never raise)."""
    obj = context.active_object
    lidar = lidar_of(obj) if obj is not None else None
    if lidar is None and strict and api.is_target(obj):  # not another lidar's targets instead of it
        raise APCGError(f"target {obj.name!r} is not parented to an APCG lidar: parent it to "
                        "one (its lidar is the one it is scanned and generated from)")
    if lidar is None:
        lidar = next((o for o in context.scene.objects if is_lidar(o)), None)
    if lidar is None and create:
        lidar = api.add_lidar()
    return lidar


def _select_only(context, obj) -> None:
    for o in context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj


class APCG_OT_add_lidar(bpy.types.Operator):
    """Add an SPC-Lidar: an Empty looking along its local +Y, carrying the lidar parameters"""
    bl_idname = "apcg.add_lidar"
    bl_label = "Add APCG Lidar"
    bl_options = {"REGISTER", "UNDO"}

    r_alpha_deg: FloatProperty(name="R alpha (deg)", default=0.004, min=1e-6, precision=5)
    r_beta_deg: FloatProperty(name="R beta (deg)", default=0.0076, min=1e-6, precision=5)
    range_resolution_m: FloatProperty(name="R r (m)", default=0.15, min=1e-4, precision=3)
    width: IntProperty(name="W", default=256, min=2, max=16384)
    height: IntProperty(name="H", default=64, min=2, max=16384)

    def execute(self, context):
        from apcg_core.lidar import LidarParams
        try:
            params = LidarParams.from_degrees(round(self.r_alpha_deg, 7),
                                              round(self.r_beta_deg, 7),
                                              round(self.range_resolution_m, 7), self.width,
                                              self.height)
            obj = api.add_lidar(params=params, location=tuple(context.scene.cursor.location))
        except Exception as exc:  # noqa: BLE001 - shown in the UI
            return _report_error(self, exc)
        _select_only(context, obj)
        return {"FINISHED"}


class APCG_OT_add_aircraft(bpy.types.Operator):
    """Add a catalog aircraft or drone as a target of the active lidar, at a pose"""
    bl_idname = "apcg.add_aircraft"
    bl_label = "Add APCG Aircraft"
    bl_options = {"REGISTER", "UNDO"}
    bl_property = "type_name"

    type_name: EnumProperty(name="Type", items=_type_items)
    range_m: FloatProperty(name="Range (m)", default=4500.0, min=1.0, max=100000.0)
    elevation_deg: FloatProperty(name="Elevation (deg)", default=3.4, min=-89.9, max=89.9)
    pitch_deg: FloatProperty(name="Pitch (deg)", default=2.0, min=-90.0, max=90.0)
    yaw_deg: FloatProperty(name="Yaw (deg)", default=0.0, min=-180.0, max=180.0)
    roll_deg: FloatProperty(name="Roll (deg)", default=0.0, min=-180.0, max=180.0)
    azimuth_deg: FloatProperty(name="Azimuth (deg)", default=0.0, min=-180.0, max=180.0)
    use_active_mesh: BoolProperty(
        name="Use the active mesh", default=False,
        description="Make a target of the active mesh object (your own model, its world x the "
                    "nose and z up, at its world size) instead of a catalog type; Make Target "
                    "(apcg.make_target) also guesses or takes other axes")

    def execute(self, context):
        try:
            if self.use_active_mesh:
                model = context.active_object
                if model is None or model.type != "MESH" or api.is_target(model):
                    raise APCGError("select the mesh object of your model first (it must not "
                                    "already be a target)")
                lidar = next((o for o in context.scene.objects if is_lidar(o)), None)
                lidar = lidar or api.add_lidar()
                obj = api.make_target(lidar, model, self.range_m, self.elevation_deg,
                                      self.pitch_deg, self.yaw_deg, self.roll_deg,
                                      self.azimuth_deg, forward="X", up="Z")
            else:
                lidar = _active_lidar(context, create=True)
                obj = api.add_aircraft(lidar, self.type_name, self.range_m, self.elevation_deg,
                                       self.pitch_deg, self.yaw_deg, self.roll_deg,
                                       self.azimuth_deg)
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        warning = (obj.get(AXES_KEY) or {}).get("warning")
        if warning:  # the mesh's x / z contradict its shape: say how to fix it
            self.report({"WARNING"}, warning.replace("Guess axes", "Guess axes in Make Target"))
        _select_only(context, obj)
        return {"FINISHED"}


def _extents(obj) -> list:
    """Length, span, height (m) of a target's body mesh."""
    v = api.body_mesh(obj).vertices
    return [float(e) for e in v.max(axis=0) - v.min(axis=0)]


def _is_plain_mesh(obj) -> bool:
    return (obj is not None and obj.type == "MESH" and not api.is_target(obj)
            and not api.is_cloud(obj))


class APCG_OT_make_target(bpy.types.Operator):
    """Make a target of the active mesh object (left as it is): modifiers applied, at its size
    in the scene, its axes guessed or stated, centred at its centre of mass, placed in front
    of the active lidar"""
    bl_idname = "apcg.make_target"
    bl_label = "Make APCG Target"
    bl_options = {"REGISTER", "UNDO"}

    guess_axes: BoolProperty(name="Guess axes", default=True,
                             description="Guess the model's nose and up axes from its shape "
                                         "(untick to state them)")
    forward: EnumProperty(name="Forward", items=_AXIS_ITEMS, default="X",
                          description="The model's nose axis, in its world orientation")
    up: EnumProperty(name="Up", items=_AXIS_ITEMS, default="Z",
                     description="The model's up axis, in its world orientation")
    type_name: StringProperty(
        name="Type", default="",
        description="The target's type: a catalog name (e.g. A320neo) lets Generate use a "
                    "model that knows it; empty: the object's name")
    range_m: FloatProperty(name="Range (m)", default=0.0, min=0.0, max=100000.0,
                           description="0: 4500 m, or 300 m for an object under 5 m")
    elevation_deg: FloatProperty(name="Elevation (deg)", default=3.4, min=-89.9, max=89.9)
    pitch_deg: FloatProperty(name="Pitch (deg)", default=2.0, min=-90.0, max=90.0)
    yaw_deg: FloatProperty(name="Yaw (deg)", default=0.0, min=-180.0, max=180.0)
    roll_deg: FloatProperty(name="Roll (deg)", default=0.0, min=-180.0, max=180.0)
    azimuth_deg: FloatProperty(name="Azimuth (deg)", default=0.0, min=-180.0, max=180.0)
    axes_note: StringProperty(options={"HIDDEN", "SKIP_SAVE"})

    @classmethod
    def poll(cls, context):
        return _is_plain_mesh(context.active_object)

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "guess_axes")
        row = layout.row(align=True)
        row.enabled = not self.guess_axes
        row.prop(self, "forward")
        row.prop(self, "up")
        if self.axes_note:
            layout.label(text=self.axes_note)
        layout.prop(self, "type_name")
        col = layout.column(align=True)
        for name in ("range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg",
                     "azimuth_deg"):
            col.prop(self, name)

    def execute(self, context):
        source = context.active_object
        try:
            if not _is_plain_mesh(source):
                raise APCGError("select the mesh object of your model first (it must not "
                                "already be a target or a cloud)")
            lidar = _active_lidar(context, create=True)
            stated = not self.guess_axes
            obj = api.make_target(lidar, source, self.range_m or None, self.elevation_deg,
                                  self.pitch_deg, self.yaw_deg, self.roll_deg,
                                  self.azimuth_deg, forward=self.forward if stated else None,
                                  up=self.up if stated else None,
                                  type_name=self.type_name or None)
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        axes = obj[AXES_KEY]
        self.forward, self.up = axes["forward"], axes["up"]  # the redo panel shows the guess
        self.range_m = obj.apcg_target.range_m
        self.axes_note = f"axes: {api.axes_label(obj)}"
        _select_only(context, obj)
        ext = _extents(obj)
        self.report({"INFO"}, f"{obj.name}: axes {api.axes_label(obj)}; length {ext[0]:.3g} m, "
                              f"span {ext[1]:.3g} m, height {ext[2]:.3g} m; type "
                              f"{obj[TYPE_KEY]!r}")
        if axes.get("warning"):  # stated axes the shape contradicts, with the fix
            self.report({"WARNING"}, axes["warning"])
        if not axes.get("confident", True) and self.guess_axes:
            self.report({"WARNING"}, "the axes guess is unsure (the shape looks alike from "
                                     "several sides): check the target, or untick Guess axes "
                                     "and state Forward and Up")
        return {"FINISHED"}


class APCG_OT_add_to_catalog(bpy.types.Operator):
    """Save the active target's mesh as a new type of your catalog: the command line
    (apcg catalog list, simulate, build, teach) then knows it by its name"""
    bl_idname = "apcg.add_to_catalog"
    bl_label = "Add to APCG Catalog"
    bl_options = {"REGISTER", "UNDO"}

    type_name: StringProperty(name="Name", default="",
                              description="The new type's name (empty: the target's type)")
    kind: EnumProperty(name="Kind", items=[
        ("aircraft", "Aircraft", "Largest extent 1-100 m"),
        ("drone", "Drone", "Largest extent 0.02-10 m")])
    category: StringProperty(name="Category", default="user",
                             description="A built-in type's category (e.g. "
                                         "airliner_narrowbody, business_jet, fighter, "
                                         "helicopter, light_GA, multirotor_drone) or user")
    force: BoolProperty(name="Force", default=False,
                        description="Add it even when its size is implausible for its kind")
    reflectivity: FloatProperty(name="Reflectivity", default=0.0, min=0.0, max=1.0,
                                description="Diffuse reflectivity at the lidar's wavelength, "
                                            "for sensor scans (0: the category's default)")

    @classmethod
    def poll(cls, context):
        return api.is_target(context.active_object)

    def invoke(self, context, event):
        obj = context.active_object
        if not self.type_name:
            self.type_name = str(obj.get(TYPE_KEY, obj.name))
        if not self.properties.is_property_set("kind"):
            self.kind = "drone" if max(_extents(obj)) < 2.0 else "aircraft"
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        from apcg_core.catalog.checks import size_problem
        from apcg_core.errors import InputError
        obj = context.active_object
        try:
            t = api.add_to_catalog(obj, self.kind, self.category or "user",
                                   name=self.type_name or None, force=self.force,
                                   reflectivity=self.reflectivity or None)
        except InputError as exc:
            msg = str(exc)
            if "implausible" in msg:
                msg += (" (in Blender: scale the source object by that factor and make the "
                        "target again, or tick Force)")
            self.report({"ERROR"}, msg)
            return {"CANCELLED"}
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        problem = size_problem((t.length_m, t.span_m, t.height_m), t.kind)
        if problem:
            self.report({"WARNING"}, f"{t.name!r} added although {problem.split(';')[0]}")
        self.report({"INFO"}, f"{t.name!r} is in the catalog (index {t.index}, {t.kind}, "
                              f"{t.length_m:.3g} x {t.span_m:.3g} x {t.height_m:.3g} m): "
                              "`apcg catalog list` shows it")
        return {"FINISHED"}


class _ChunkedOperator:
    """Runs ``self._work`` (a list of callables, one per chunk) from a timer with progress."""

    _timer = None

    def _prepare(self, context) -> list:  # pragma: no cover - overridden
        raise NotImplementedError

    _closers: list = []  # what _prepare opened (a simulator's private scene), closed at the end

    def _close(self) -> None:
        for close in self._closers:
            close()
        self._closers = []

    def execute(self, context):
        try:
            self._made = []
            for job in self._prepare(context):
                self._made.append(job())
        except Exception as exc:  # noqa: BLE001
            self._cleanup()
            return _report_error(self, exc)
        finally:
            self._close()
        self._report_made()
        return {"FINISHED"}

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        try:
            self._jobs = self._prepare(context)
        except Exception as exc:  # noqa: BLE001
            self._close()
            return _report_error(self, exc)
        self._made, self._done = [], 0
        wm = context.window_manager
        wm.progress_begin(0, len(self._jobs))
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        wm = context.window_manager
        if event.type == "ESC":
            self._finish(context)
            self._cleanup()
            self.report({"WARNING"}, f"{self.bl_label} cancelled")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            self._made.append(self._jobs[self._done]())
        except Exception as exc:  # noqa: BLE001
            self._finish(context)
            self._cleanup()
            return _report_error(self, exc)
        self._done += 1
        wm.progress_update(self._done)
        if context.area is not None:
            context.area.header_text_set(f"{self.bl_label}: {self._done}/{len(self._jobs)} "
                                         "(Esc cancels)")
        if self._done < len(self._jobs):
            return {"RUNNING_MODAL"}
        self._finish(context)
        self._report_made()
        return {"FINISHED"}

    def _finish(self, context) -> None:
        self._close()
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if context.area is not None:
            context.area.header_text_set(None)

    def _report_made(self) -> None:
        from apcg_core.plausibility import sparse_cloud_warning
        self.report({"INFO"}, f"{self.bl_label}: {len(self._made)} point cloud(s)")
        for obj in filter(None, self._made):
            warning = sparse_cloud_warning(len(obj.data.vertices), f"the cloud {obj.name!r}")
            if warning:
                self.report({"WARNING"}, warning)

    def _cleanup(self) -> None:
        for obj in getattr(self, "_made", []):
            if obj is not None:
                data = obj.data
                bpy.data.objects.remove(obj)
                if data is not None and data.users == 0:
                    bpy.data.meshes.remove(data)
        self._made = []


def _targets(context, lidar, selected_only: bool):
    if lidar is None:
        raise APCGError("no APCG lidar in the scene: add one with Add APCG Lidar")
    ts = targets_of(lidar, selected_only=selected_only)
    if not ts and selected_only and targets_of(lidar):
        raise APCGError(f"none of lidar {lidar.name!r}'s targets is selected: select the "
                        "targets to use, or untick Selected targets only")
    if not ts:
        raise APCGError(f"lidar {lidar.name!r} has no targets: add one with Add APCG "
                        "Aircraft")
    return ts


class APCG_OT_scan(_ChunkedOperator, bpy.types.Operator):
    """Simulate the lidar on its targets with Blender's ray casting: one cloud per target"""
    bl_idname = "apcg.scan"
    bl_label = "APCG Scan"
    bl_options = {"REGISTER", "UNDO"}

    selected_only: BoolProperty(name="Selected targets only", default=False)
    occlusion: BoolProperty(name="Occlusion by other objects", default=True)
    quantize: BoolProperty(name="Quantize ranges", default=True)
    supersample: IntProperty(name="Rays per cell (k x k)", default=0, min=0, max=8,
                             description="0: 1, or 4 when the lidar has a sensor (its photon "
                                         "stage takes every sub-ray)")
    backend: EnumProperty(name="Ray casting", items=[
        ("blender", "Geometry Nodes", "One Geometry Nodes Raycast evaluation per target"),
        ("blender-bvh", "BVH tree", "mathutils BVHTree.ray_cast, one ray at a time")])

    def _prepare(self, context):
        from dataset_builder.simulate import Simulator

        from .objects import lidar_params
        lidar = _active_lidar(context)
        ts = _targets(context, lidar, self.selected_only)
        sensor = api.sensor_of(lidar)  # the panel's Sensor: ideal, a preset or a file
        sim = Simulator(self.backend, lidar_params(lidar), quantize=self.quantize,
                        supersample=self.supersample or (4 if sensor else 1))
        self._closers = [sim.close]
        seed = lidar.apcg_lidar.seed
        return [(lambda t=t: api.scan_target(t, occlusion=self.occlusion, simulator=sim,
                                             sensor=sensor, seed=seed))
                for t in ts]


class APCG_OT_generate(_ChunkedOperator, bpy.types.Operator):
    """Generate point clouds for the targets' conditions with the APCG generator"""
    bl_idname = "apcg.generate"
    bl_label = "APCG Generate"
    bl_options = {"REGISTER", "UNDO"}

    model_dir: StringProperty(name="Model", subtype="DIR_PATH", default="",
                              description="A model directory (empty: the default model)")
    count: IntProperty(name="Samples", default=1, min=1, max=api.MAX_GENERATE_COUNT)
    seed: IntProperty(name="Seed", default=0, min=0)
    selected_only: BoolProperty(name="Selected targets only", default=True)
    runtime: EnumProperty(name="Runtime", items=[
        ("auto", "Auto", "torch when installed, else onnxruntime"),
        ("onnx", "onnxruntime", ""), ("torch", "torch", "")])

    def _prepare(self, context):
        lidar = _active_lidar(context)
        ts = _targets(context, lidar, self.selected_only)
        model = api.load_model(bpy.path.abspath(self.model_dir) or None, self.runtime)
        for t in ts:  # a type the model does not know is refused before any work
            api.check_model_knows(model, t)
        if lidar is not None and not model.ANY_LIDAR:
            # a family that draws at its training lidar only is refused at another, before any
            # work, as `apcg generate --lidar` refuses it (api.generate refuses it too)
            model.use_lidar(api.lidar_params(lidar))
        warning = api.lidar_fit_warning(model, lidar) if lidar is not None else None
        if warning:  # a lidar the model was not measured on: generated all the same, with this
            self.report({"WARNING"}, warning)  # one line, as `apcg generate --lidar` warns
        return [(lambda t=t: api.generate(t, model, self.count, self.seed)) for t in ts]


# Blender 4.1+ warns when a file path without this flag is given "//" (a path beside the
# .blend): these operators resolve it (bpy.path.abspath), so they say they take one
_BLEND_RELATIVE = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 1, 0) else set()


def _file_path(what: str, hidden: bool):
    """ImportHelper's / ExportHelper's filepath, taking a blend-relative "//" path."""
    return StringProperty(name="File Path", description=f"Filepath used for {what} the file",
                          maxlen=1024, subtype="FILE_PATH",
                          options=({"SKIP_PRESET", "HIDDEN"} if hidden else set())
                          | _BLEND_RELATIVE)


class APCG_OT_import_cloud(bpy.types.Operator, ImportHelper):
    """Import a point cloud (PLY, NPZ, LAS, LAZ) and its attributes under the active lidar"""
    bl_idname = "apcg.import_cloud"
    bl_label = "Import APCG Cloud"
    bl_options = {"REGISTER", "UNDO"}

    filepath: _file_path("importing", True)
    filter_glob: StringProperty(default="*.ply;*.npz;*.las;*.laz", options={"HIDDEN"})

    def execute(self, context):
        from .clouds import cloud_info
        try:
            obj = api.import_cloud(bpy.path.abspath(self.filepath),
                                   lidar=_active_lidar(context))
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        _select_only(context, obj)
        names = cloud_info(obj).get("attributes") or []
        self.report({"INFO"}, f"read {len(obj.data.vertices)} points; other attributes: "
                              f"{', '.join(names) if names else 'none'}")
        return {"FINISHED"}


class APCG_OT_export_cloud(bpy.types.Operator, ExportHelper):
    """Export the active point cloud (observation frame, float64) as PLY, NPZ or LAS"""
    bl_idname = "apcg.export_cloud"
    bl_label = "Export APCG Cloud"

    filename_ext = ".ply"
    check_extension = False  # .npz and .las are accepted too
    filepath: _file_path("exporting", False)
    filter_glob: StringProperty(default="*.ply;*.npz;*.las", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return api.is_cloud(context.active_object)

    def execute(self, context):
        import warnings
        path = bpy.path.abspath(self.filepath)  # "//": beside the .blend, as Generate reads
        try:
            with warnings.catch_warnings(record=True) as said:
                warnings.simplefilter("always")
                api.export_cloud(context.active_object, path)
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        for w in said:  # a file attribute the format cannot carry
            self.report({"WARNING"}, str(w.message))
        self.report({"INFO"}, f"wrote {path}")
        return {"FINISHED"}


class APCG_OT_read_lidar(bpy.types.Operator, ImportHelper):
    """Set the active lidar from a lidar file (the [lidar] table every command's --lidar reads,
    and its [sensor] table when it has one)"""
    bl_idname = "apcg.read_lidar"
    bl_label = "Read Lidar File"
    bl_options = {"REGISTER", "UNDO"}

    filepath: _file_path("importing", True)
    filter_glob: StringProperty(default="*.toml", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return _active_lidar(context, strict=False) is not None

    def execute(self, context):
        try:
            api.read_lidar_file(_active_lidar(context), bpy.path.abspath(self.filepath))
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        self.report({"INFO"}, f"read {bpy.path.abspath(self.filepath)}")
        return {"FINISHED"}


class APCG_OT_write_lidar(bpy.types.Operator, ExportHelper):
    """Write the active lidar as a lidar file that every command's --lidar reads"""
    bl_idname = "apcg.write_lidar"
    bl_label = "Write Lidar File"

    filename_ext = ".toml"
    filepath: _file_path("exporting", False)
    filter_glob: StringProperty(default="*.toml", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return _active_lidar(context, strict=False) is not None

    def execute(self, context):
        try:
            api.write_lidar_file(_active_lidar(context), bpy.path.abspath(self.filepath))
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        self.report({"INFO"}, f"wrote {bpy.path.abspath(self.filepath)}")
        return {"FINISHED"}


class APCG_OT_scan_animation(bpy.types.Operator):
    """Scan every frame of the timeline as one scene of all the lidar's targets (nearest
    surface first, points labelled by target), write the sequence (docs/SCENES.md) into a
    directory and play it back as a point cloud on the timeline"""
    bl_idname = "apcg.scan_animation"
    bl_label = "Scan Animation"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Sequence directory", subtype="DIR_PATH")
    pattern: EnumProperty(name="Scan", items=[
        ("flash", "Flash", "Every cell of a frame at once"),
        ("rows", "Row by row", "Rows fired from the top, Line time apart: a fast target is "
                               "drawn where it was when its rows fired"),
        ("columns", "Column by column", "Columns fired from the left, Line time apart")])
    line_time_s: FloatProperty(name="Line time (s)", default=0.0, min=0.0, max=1.0,
                               precision=6, description="0: a frame's time shared by its "
                               "lines (rows: H, columns: W), so the scan fits the frame")
    backend: EnumProperty(name="Ray casting", items=[
        ("blender", "Geometry Nodes", "One Geometry Nodes Raycast evaluation per group of "
                                      "cells"),
        ("blender-bvh", "BVH tree", "mathutils BVHTree.ray_cast, one ray at a time")])
    import_after: BoolProperty(name="Play it on the timeline", default=True)

    @classmethod
    def poll(cls, context):
        return _active_lidar(context, strict=False) is not None

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        wm = context.window_manager
        try:
            lidar = _active_lidar(context)
            scan = None if self.pattern == "flash" else {
                "pattern": self.pattern, "line_time_s": self.line_time_s or _fitting_line_time(
                    context.scene, lidar, self.pattern)}
            wm.progress_begin(0, 1)
            out = api.scan_animation(lidar, bpy.path.abspath(self.directory),
                                     backend=self.backend, scan=scan,
                                     seed=lidar.apcg_lidar.seed,
                                     progress=lambda i, n: wm.progress_update(i / n))
            if self.import_after:
                api.import_sequence(out, lidar=lidar)
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        finally:
            wm.progress_end()
        self.report({"INFO"}, f"wrote the sequence to {out}")
        return {"FINISHED"}


def _fitting_line_time(scene, lidar, pattern: str) -> float:
    """The line time that spreads a frame's lines over the frame (the last line fires one
    line time before the next frame's first)."""
    from .objects import lidar_params
    params = lidar_params(lidar)
    lines = params.height if pattern == "rows" else params.width
    return scene.render.fps_base / scene.render.fps / lines


class APCG_OT_import_sequence(bpy.types.Operator):
    """Import a scene sequence directory (apcg scene sequence, Scan Animation) as a point cloud
    that plays on the timeline: one cloud object per frame"""
    bl_idname = "apcg.import_sequence"
    bl_label = "Import APCG Sequence"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Sequence directory", subtype="DIR_PATH")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        try:
            coll = api.import_sequence(bpy.path.abspath(self.directory),
                                       lidar=_active_lidar(context))
        except Exception as exc:  # noqa: BLE001
            return _report_error(self, exc)
        self.report({"INFO"}, f"imported {len(coll.objects)} frames into {coll.name}")
        return {"FINISHED"}


CLASSES = (APCG_OT_add_lidar, APCG_OT_add_aircraft, APCG_OT_make_target,
           APCG_OT_add_to_catalog, APCG_OT_scan, APCG_OT_generate, APCG_OT_import_cloud,
           APCG_OT_export_cloud, APCG_OT_read_lidar, APCG_OT_write_lidar,
           APCG_OT_scan_animation, APCG_OT_import_sequence)

for _cls in CLASSES:  # a cancelled operator leaves the scene as it found it
    if "execute" in _cls.__dict__:
        _cls.execute = cancelled_leaves_nothing(_cls.execute)
_ChunkedOperator.execute = cancelled_leaves_nothing(_ChunkedOperator.execute)

register, unregister = bpy.utils.register_classes_factory(CLASSES)


__all__ = ["register", "unregister"]
