"""The 3D viewport's N-panel "APCG"."""

import bpy

from apcg_core.errors import InputError

from .clouds import cloud_info, is_cloud
from .objects import AXES_KEY, TYPE_KEY, axes_label, is_lidar, is_target, lidar_of, source_of


class APCG_PT_panel(bpy.types.Panel):
    bl_label = "APCG Lidar"
    bl_idname = "APCG_PT_panel"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "APCG"

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        lidar = lidar_of(obj) if obj is not None else None
        col = layout.column(align=True)
        col.operator("apcg.add_lidar", icon="OUTLINER_OB_EMPTY")
        col.operator_menu_enum("apcg.add_aircraft", "type_name", text="Add Aircraft",
                               icon="ADD")
        if obj is not None and obj.type == "MESH" and not is_target(obj) and not is_cloud(obj):
            col.operator("apcg.make_target", text=f"Make Target of {obj.name}",
                         icon="OBJECT_DATA")
        if lidar is not None:
            box = layout.box()
            box.label(text=f"Lidar: {lidar.name}", icon="LIGHT_SPOT")
            p = lidar.apcg_lidar
            col = box.column(align=True)
            col.prop(p, "r_alpha_deg")
            col.prop(p, "r_beta_deg")
            col.prop(p, "range_resolution_m")
            row = box.row(align=True)
            row.prop(p, "width")
            row.prop(p, "height")
            row = box.row(align=True)
            row.prop(p, "sensor")
            row.prop(p, "seed", text="Seed")
            row = box.row(align=True)
            row.operator("apcg.read_lidar", text="Read", icon="FILE_FOLDER")
            row.operator("apcg.write_lidar", text="Write", icon="FILE_TICK")
        if is_target(obj):
            box = layout.box()
            type_name = str(obj.get(TYPE_KEY, obj.name))
            box.label(text=f"Target: {type_name}", icon="OBJECT_DATA")
            axes = axes_label(obj)
            if axes:  # made from a scene object
                src = source_of(obj)
                if src is not None:
                    box.label(text=f"from: {src.name}")
                head, _, how = axes.partition(" (")  # two short lines for a narrow sidebar
                box.label(text=f"axes: {head}")
                box.label(text=f"({how}")
                ext = obj[AXES_KEY].get("extents_m")
                if ext is not None:  # length (x), span (y), height (z)
                    box.label(text=f"size: {ext[0]:.3g} x {ext[1]:.3g} x {ext[2]:.3g} m")
                if not _in_catalog(type_name):
                    box.operator("apcg.add_to_catalog", icon="ADD")
            t = obj.apcg_target
            for name in ("range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg",
                         "azimuth_deg"):
                box.prop(t, name)
        elif is_cloud(obj):
            box = layout.box()
            try:
                source = cloud_info(obj)["source"]
            except InputError:  # a damaged record: Export names it; the panel still draws
                source = "damaged record"
            box.label(text=f"Cloud: {len(obj.data.vertices)} points ({source})",
                      icon="POINTCLOUD_DATA")
        col = layout.column(align=True)
        col.enabled = lidar is not None or is_lidar(obj)
        col.operator("apcg.scan", icon="LIGHT_SUN")
        col.operator("apcg.scan_animation", icon="RENDER_ANIMATION")
        col.operator("apcg.generate", icon="MOD_PARTICLES")
        row = layout.row(align=True)
        row.operator("apcg.import_cloud", icon="IMPORT", text="Import")
        row.operator("apcg.export_cloud", icon="EXPORT", text="Export")
        layout.operator("apcg.import_sequence", icon="SEQUENCE", text="Import Sequence")


def _in_catalog(name: str) -> bool:
    from apcg_core.catalog import default_catalog
    from apcg_core.typetable import name_key
    return name_key(name) in {name_key(n) for n in default_catalog().names()}


CLASSES = (APCG_PT_panel,)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
