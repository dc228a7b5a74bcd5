"""blender_addon (filled in by later issues)."""
