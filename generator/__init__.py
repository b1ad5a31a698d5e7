"""Scene specs -> Blender renders with exact ground truth. Only generator/blender/ imports bpy."""
