"""Principled-BSDF materials from MaterialSpec, with shader AOVs that carry the exact ground truth.

The "albedo" AOV is wired from the very socket that feeds the BSDF's Base Color, and "roughness" from
the one that feeds Roughness, so ground truth equals what the shader used (Blender's Diffuse Color pass
does not). "dynamic" is 1 on the parts of moving objects that move during the sequence and 0 elsewhere: the
mask of what moves. A moving object's material reads it from its part's object property MOVING_PROPERTY
(set by build.mark_moving_parts), so a part that never moves (a standing figure's planted foot) is static
although its object moves.
Procedural patterns use Object coordinates, so textures stick to moving objects.
"""
from __future__ import annotations

import hashlib
import random

from generator.spec import MaterialSpec

AOV_ALBEDO = "albedo"
AOV_ROUGHNESS = "roughness"
AOV_DYNAMIC = "dynamic"
MOVING_PROPERTY = "lumibench_moving"  # per mesh object: 1.0 if it moves at some time of the sequence, else 0.0


def register_aovs(view_layer) -> None:
    """Declare the three AOVs on the view layer (idempotent) so Cycles renders them as passes."""
    have = {a.name for a in view_layer.aovs}
    for name, kind in ((AOV_ALBEDO, "COLOR"), (AOV_ROUGHNESS, "VALUE"), (AOV_DYNAMIC, "VALUE")):
        if name not in have:
            aov = view_layer.aovs.add()
            aov.name = name
            aov.type = kind


def _sock(sockets, identifier: str):
    """A socket by identifier (the Mix node has several sockets with the same display name)."""
    for s in sockets:
        if s.identifier == identifier:
            return s
    raise KeyError(identifier)


def _stable_rng(*keys) -> random.Random:
    digest = hashlib.sha256("/".join(map(str, keys)).encode()).digest()
    return random.Random(int.from_bytes(digest[:8], "little"))


def make_material(name: str, spec: MaterialSpec, dynamic: bool, seed: int):
    """A new bpy material ``name`` realising ``spec``; deterministic given (seed, name)."""
    import bpy

    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    nodes, links = nt.nodes, nt.links
    bsdf = nodes.get("Principled BSDF")
    out = nodes.get("Material Output")
    if bsdf is None or out is None:  # defensive: a factory without the default tree
        nodes.clear()
        bsdf = nodes.new("ShaderNodeBsdfPrincipled")
        out = nodes.new("ShaderNodeOutputMaterial")
        links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    bsdf.inputs["Metallic"].default_value = 0.0

    color_socket, rough_socket = _pattern(nt, spec, _stable_rng(seed, name))
    rgba = (*spec.base_color, 1.0)
    if color_socket is None:
        rgb = nodes.new("ShaderNodeRGB")
        rgb.outputs[0].default_value = rgba
        color_socket = rgb.outputs[0]
    if rough_socket is None:
        val = nodes.new("ShaderNodeValue")
        val.outputs[0].default_value = spec.roughness
        rough_socket = val.outputs[0]
    links.new(color_socket, bsdf.inputs["Base Color"])
    links.new(rough_socket, bsdf.inputs["Roughness"])

    aov_a = nodes.new("ShaderNodeOutputAOV")
    aov_a.aov_name = AOV_ALBEDO
    links.new(color_socket, aov_a.inputs["Color"])
    aov_r = nodes.new("ShaderNodeOutputAOV")
    aov_r.aov_name = AOV_ROUGHNESS
    links.new(rough_socket, aov_r.inputs["Value"])
    aov_d = nodes.new("ShaderNodeOutputAOV")
    aov_d.aov_name = AOV_DYNAMIC
    aov_d.inputs["Value"].default_value = 0.0
    if dynamic:  # one material may dress several parts of a rig: each part says whether it moves
        moving = nodes.new("ShaderNodeAttribute")
        moving.attribute_type = "OBJECT"
        moving.attribute_name = MOVING_PROPERTY
        links.new(moving.outputs["Fac"], aov_d.inputs["Value"])
    return mat


def _pattern(nt, spec: MaterialSpec, rng: random.Random):
    """Return (colour socket, roughness socket) of the procedural pattern, or (None, None) if uniform."""
    tex = spec.texture
    if tex.kind == "none":
        return None, None
    nodes, links = nt.nodes, nt.links
    coord = nodes.new("ShaderNodeTexCoord")
    mapping = nodes.new("ShaderNodeMapping")
    # a seeded offset so that two objects with the same pattern do not look copy-pasted
    mapping.inputs["Location"].default_value = tuple(rng.uniform(0.0, 10.0) for _ in range(3))
    links.new(coord.outputs["Object"], mapping.inputs["Vector"])
    vec = mapping.outputs["Vector"]

    if tex.kind == "checker":
        node = nodes.new("ShaderNodeTexChecker")
        node.inputs["Scale"].default_value = tex.scale
        links.new(vec, node.inputs["Vector"])
        fac = node.outputs["Factor"]  # 1 on Color1 squares
        invert = True
    elif tex.kind == "noise":
        node = nodes.new("ShaderNodeTexNoise")
        node.inputs["Scale"].default_value = tex.scale
        node.inputs["Detail"].default_value = 3.0
        links.new(vec, node.inputs["Vector"])
        stretch = nodes.new("ShaderNodeMapRange")  # noise sits near 0.5: stretch it to use the full range
        stretch.clamp = True
        stretch.inputs["From Min"].default_value = 0.3
        stretch.inputs["From Max"].default_value = 0.7
        links.new(node.outputs["Factor"], stretch.inputs["Value"])
        fac = stretch.outputs["Result"]
        invert = False
    elif tex.kind == "bricks":
        node = nodes.new("ShaderNodeTexBrick")
        node.inputs["Scale"].default_value = tex.scale
        node.inputs["Mortar Size"].default_value = 0.03
        links.new(vec, node.inputs["Vector"])
        fac = node.outputs["Factor"]  # 1 in the mortar
        invert = False
    elif tex.kind == "stripes":
        node = nodes.new("ShaderNodeTexWave")
        node.inputs["Scale"].default_value = tex.scale
        node.inputs["Distortion"].default_value = 0.0
        links.new(vec, node.inputs["Vector"])
        sharpen = nodes.new("ShaderNodeMapRange")
        sharpen.clamp = True
        sharpen.inputs["From Min"].default_value = 0.45
        sharpen.inputs["From Max"].default_value = 0.55
        links.new(node.outputs["Factor"], sharpen.inputs["Value"])
        fac = sharpen.outputs["Result"]
        invert = False
    else:  # spec validation rejects other kinds
        raise ValueError(f"unknown texture kind {tex.kind!r}")

    if invert:
        inv = nodes.new("ShaderNodeMath")
        inv.operation = "SUBTRACT"
        inv.inputs[0].default_value = 1.0
        links.new(fac, inv.inputs[1])
        fac = inv.outputs[0]

    # fac = 0 -> base_color / roughness, fac = 1 -> color2 / roughness2
    mix = nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    _sock(mix.inputs, "A_Color").default_value = (*spec.base_color, 1.0)
    _sock(mix.inputs, "B_Color").default_value = (*tex.color2, 1.0)
    links.new(fac, _sock(mix.inputs, "Factor_Float"))
    color = _sock(mix.outputs, "Result_Color")
    rough = None
    if tex.roughness2 is not None:
        rmix = nodes.new("ShaderNodeMix")
        rmix.data_type = "FLOAT"
        _sock(rmix.inputs, "A_Float").default_value = spec.roughness
        _sock(rmix.inputs, "B_Float").default_value = tex.roughness2
        links.new(fac, _sock(rmix.inputs, "Factor_Float"))
        rough = _sock(rmix.outputs, "Result_Float")
    return color, rough
