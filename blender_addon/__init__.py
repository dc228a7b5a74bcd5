"""APCG for Blender: place an SPC-Lidar and aircraft, scan them with Blender's ray casting,
generate clouds with the APCG generator, import and export point clouds.

An extension for Blender 4.2+ (blender_manifest.toml; its Python dependencies come as wheels)
and a legacy add-on (bl_info) for older Blender. Scripts use :mod:`.api`."""

bl_info = {
    "name": "APCG: aircraft lidar point clouds",
    "author": "APCG project",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "3D Viewport > Sidebar (N) > APCG",
    "description": "Place a single-photon lidar and aircraft, scan, generate, import clouds",
    "category": "Object",
}


def _modules():
    from . import ops, props, ui
    return props, ops, ui


def _sync_moved_targets(scene, depsgraph=None):
    """Keeps a target's stored pose in step when the user moves it in the viewport."""
    from .objects import is_target, sync_pose
    for update in getattr(depsgraph, "updates", ()):
        ob = getattr(update.id, "original", None)
        if update.is_updated_transform and is_target(ob):
            sync_pose(ob, depsgraph)


def register() -> None:
    import bpy
    for m in _modules():
        m.register()
    if _sync_moved_targets not in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.append(_sync_moved_targets)


def unregister() -> None:
    import bpy
    if _sync_moved_targets in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.remove(_sync_moved_targets)
    for m in reversed(_modules()):
        m.unregister()
