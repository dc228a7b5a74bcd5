"""Read a model with Blender's own importers, in a Blender process: FBX, .blend, USD, Alembic.

Run as ``python blender_import.py IN OUT.npz [PATTERN]`` in a Python that has ``bpy``, or as
``blender -b --factory-startup --python-exit-code 1 -P blender_import.py -- IN OUT [PATTERN]``.
It imports only bpy and numpy (not the apcg package), because Debian's ``blender`` has its own
Python without it. One process per file (as BlenderProc does): an importer that crashes or
leaks takes only its own process down, and the caller's Blender session is never reset.

Every object whose evaluated form has faces (meshes, curves, text, metaballs; modifiers
applied; collection and particle instances expanded) is triangulated and moved by its world
matrix, in metres: Blender's importers apply the file's unit (FBX, USD metersPerUnit) and a
.blend's unit scale is applied here. Lights, cameras, empties and armatures are skipped and
listed. PATTERN (comma-separated shell patterns) keeps only the objects whose name matches.
"""

import fnmatch
import json
import os
import sys

import numpy as np

SURFACE_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT"}
_USD = (".usd", ".usda", ".usdc", ".usdz")


def _importers():
    """(suffixes, operator module, operator, options, how the unit is found), first found
    wins. FBX: the C++ importer of Blender 4.5+ first (the Python one fails on lights in 5.0).
    bpy is imported here, not at the top, so that apcg_core imports without Blender."""
    import bpy

    return (
        ((".fbx",), bpy.ops.wm, "fbx_import", {}, "FBX unit, applied by Blender's importer"),
        ((".fbx",), bpy.ops.import_scene, "fbx", {}, "FBX unit, applied by Blender's importer"),
        (_USD, bpy.ops.wm, "usd_import", {}, "USD metersPerUnit, applied by Blender's importer"),
        ((".abc",), bpy.ops.wm, "alembic_import", {"as_background_job": False},
         "not declared (Alembic has no unit): metres assumed"),
    )


def _import(path: str) -> str:
    """Import ``path`` into an empty scene; returns how its unit was found."""
    import bpy

    suffix = os.path.splitext(path)[1].lower()
    if suffix == ".blend":
        bpy.ops.wm.open_mainfile(filepath=path, load_ui=False)
        units = bpy.context.scene.unit_settings
        if units.system == "NONE":
            return "not declared (a .blend with unit system None): metres assumed"
        return f".blend scene unit: {units.system.lower()}, unit scale {units.scale_length:g}"
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for suffixes, module, op_name, kwargs, note in _importers():
        if suffix in suffixes:
            if op_name not in dir(module):
                continue  # an older importer below, or none in this build
            getattr(module, op_name)(filepath=path, **kwargs)
            return note
    raise SystemExit(f"blender_import: Blender {bpy.app.version_string} has no importer for "
                     f"{suffix!r} (USD and Alembic need a Blender built with them, e.g. the "
                     "bpy module: pip install 'apcg[blender]')")


def _blend_scale(path: str) -> float:
    import bpy

    units = bpy.context.scene.unit_settings
    if path.lower().endswith(".blend") and units.system != "NONE":
        return float(units.scale_length)
    return 1.0


def main(argv: list[str]) -> int:
    import bpy

    src, out = argv[0], argv[1]
    patterns = [p for p in (argv[2] if len(argv) > 2 else "").split(",") if p]
    unit_note = _import(src)
    scale = _blend_scale(src)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    verts, faces, taken, skipped, offset = [], [], [], [], 0
    for inst in depsgraph.object_instances:
        obj = inst.object
        name = (inst.instance_object.name if inst.is_instance else obj.name)
        if obj.type not in SURFACE_TYPES:
            skipped.append(f"{name} ({obj.type.lower()})")
            continue
        if patterns and not any(fnmatch.fnmatchcase(name, p) for p in patterns):
            skipped.append(f"{name} (not matched)")
            continue
        me = obj.to_mesh()
        try:
            me.calc_loop_triangles()
            n_v, n_t = len(me.vertices), len(me.loop_triangles)
            if n_t == 0:
                skipped.append(f"{name} (no faces)")
                continue
            co = np.empty(n_v * 3, np.float32)
            me.vertices.foreach_get("co", co)
            tri = np.empty(n_t * 3, np.int32)
            me.loop_triangles.foreach_get("vertices", tri)
        finally:
            obj.to_mesh_clear()
        m = np.array(inst.matrix_world, dtype=np.float64)
        co = co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        verts.append(co * scale)
        faces.append(tri.reshape(-1, 3).astype(np.int64) + offset)
        offset += n_v
        taken.append(name)
    if not taken:
        names = ", ".join(skipped) or "none"
        print(f"blender_import: no object with faces to take; objects: {names}",
              file=sys.stderr)
        return 3
    info = {"objects": taken, "skipped": skipped, "unit_note": unit_note,
            "blender": bpy.app.version_string}
    tmp = out + ".part"
    with open(tmp, "wb") as f:
        np.savez(f, vertices=np.concatenate(verts), faces=np.concatenate(faces),
                 info=np.array(json.dumps(info)))
    os.replace(tmp, out)
    return 0


if __name__ == "__main__":
    args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    sys.exit(main(args))
