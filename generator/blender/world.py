"""Light the world with an equirectangular map, texel for texel (no rotation, nearest lookup)."""
from __future__ import annotations

from pathlib import Path

import bpy

WORLD_NAME = "LumiBenchWorld"


def _linear_colorspace(image) -> None:
    """Treat the file's values as scene-linear Rec.709 radiance (what .hdr/.exr store)."""
    for name in ("Linear Rec.709", "scene_linear", "Non-Color"):
        try:
            image.colorspace_settings.name = name
            return
        except TypeError:
            continue


def set_environment(bpy_scene, hdr_path, strength: float = 1.0):
    """World = Environment Texture (equirectangular, 'Closest') -> Background(strength) -> World Output.

    'Closest' makes the world exactly the piecewise-constant map (32 x 16, or the light's own resolution)
    that the method looks up texel for texel; the texture's default vector is the world direction, i.e. the
    mapping of generator.envmap.direction_to_uv. Any map size works the same way.
    """
    path = Path(hdr_path).resolve()
    if not path.is_file():
        raise FileNotFoundError(f"environment map not found: {path}")
    world = bpy_scene.world
    if world is None:
        world = bpy.data.worlds.get(WORLD_NAME) or bpy.data.worlds.new(WORLD_NAME)
        bpy_scene.world = world
    if world.node_tree is None:  # Blender 5 creates the tree with the world; use_nodes is deprecated
        world.use_nodes = True
    tree = world.node_tree
    tree.nodes.clear()
    image = None
    for img in bpy.data.images:
        if img.filepath and Path(bpy.path.abspath(img.filepath)).resolve() == path:
            image = img
            image.reload()  # the pipeline may have rewritten the file since it was loaded
            break
    if image is None:
        image = bpy.data.images.load(str(path), check_existing=False)
    _linear_colorspace(image)
    tex = tree.nodes.new("ShaderNodeTexEnvironment")
    tex.image = image
    tex.projection = "EQUIRECTANGULAR"
    tex.interpolation = "Closest"
    bg = tree.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = float(strength)
    out = tree.nodes.new("ShaderNodeOutputWorld")
    out.target = "ALL"
    tree.links.new(tex.outputs["Color"], bg.inputs["Color"])
    tree.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return world


def environment_width(world) -> int:
    """Width in texels of the map the world's Environment Texture shows (0 when it has none)."""
    for node in world.node_tree.nodes:
        if node.bl_idname == "ShaderNodeTexEnvironment" and node.image is not None:
            return int(node.image.size[0])
    return 0
