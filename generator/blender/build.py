"""SceneSpec -> Blender objects, posed for any t in [0, 1] by pure motion functions.

Only geometry, materials (with ground-truth AOVs) and motion live here; world/env map, camera and
Cycles settings are set elsewhere (world.py, camera.py, cycles.py). Meshes are built with bmesh
(no operators, no context), sized in the mesh itself so that Object texture coordinates are in
scene units, and kept low-poly so CPU rendering stays fast.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import bpy  # first: bmesh and mathutils become importable once bpy is loaded
import bmesh  # noqa: E402
from mathutils import Euler, Vector

from generator import motion as motion_mod
from generator.spec import ObjectSpec, SceneSpec

from . import figure
from .materials import AOV_ALBEDO, AOV_DYNAMIC, AOV_ROUGHNESS, MOVING_PROPERTY, make_material, register_aovs

__all__ = ["AOV_ALBEDO", "AOV_DYNAMIC", "AOV_ROUGHNESS", "BuiltScene", "build_scene", "make_mesh", "mark_moving_parts",
           "reset_blender"]

SEGMENTS = 24  # around spheres/cylinders: smooth enough under smooth shading, cheap to render


def reset_blender() -> "bpy.types.Scene":
    """An empty factory scene (no default cube, camera or light)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def make_mesh(name: str, primitive: str, size) -> "bpy.types.Mesh":
    """A closed low-poly mesh centred at the origin whose bounding box has the full extents ``size``."""
    sx, sy, sz = size
    bm = bmesh.new()
    smooth = True
    if primitive == "box":
        bmesh.ops.create_cube(bm, size=1.0)
        smooth = False
    elif primitive == "sphere":
        _uv_sphere(bm, SEGMENTS, SEGMENTS // 2, 0.5)
    elif primitive == "ico_sphere":
        bmesh.ops.create_icosphere(bm, subdivisions=2, radius=0.5)
    elif primitive in ("cylinder", "cone"):
        bmesh.ops.create_cone(bm, cap_ends=True, segments=SEGMENTS, radius1=0.5,
                              radius2=0.5 if primitive == "cylinder" else 0.0, depth=1.0)
    elif primitive == "torus":
        _torus(bm, sx, sy, sz)
        sx = sy = sz = 1.0  # built at its final size
    else:
        raise ValueError(f"unknown primitive {primitive!r}")
    bmesh.ops.scale(bm, vec=Vector((sx, sy, sz)), verts=bm.verts)
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    if smooth:
        mesh.shade_smooth()
        if primitive in ("cylinder", "cone"):
            mesh.set_sharp_from_angle(angle=math.radians(50.0))  # keep the caps' rims crisp
    return mesh


def _uv_sphere(bm, segments: int, rings: int, radius: float) -> None:
    """A UV sphere with poles on z: triangle fans at the poles, quads between ``rings`` latitude bands.

    Built vertex by vertex rather than with ``bmesh.ops.create_uvsphere``: that operator welds its pole
    vertices with a pass whose face-corner order follows memory addresses, so the same call gave meshes
    whose faces start at different corners in different processes; face normals (summed corner by
    corner) then differed in the last bit, and so did every render of a moving sphere.
    """
    top = bm.verts.new((0.0, 0.0, radius))
    bands = []
    for j in range(1, rings):
        polar = math.pi * j / rings
        z, rho = radius * math.cos(polar), radius * math.sin(polar)
        bands.append([bm.verts.new((rho * math.cos(2 * math.pi * i / segments),
                                    rho * math.sin(2 * math.pi * i / segments), z)) for i in range(segments)])
    bottom = bm.verts.new((0.0, 0.0, -radius))
    for i in range(segments):
        k = (i + 1) % segments
        bm.faces.new((top, bands[0][i], bands[0][k]))  # counter-clockwise seen from outside
        for upper, lower in zip(bands, bands[1:]):
            bm.faces.new((upper[i], lower[i], lower[k], upper[k]))
        bm.faces.new((bands[-1][i], bottom, bands[-1][k]))


def _torus(bm, sx: float, sy: float, thickness: float, ring_segments: int = SEGMENTS, tube_segments: int = 10) -> None:
    """A torus in the xy plane: outer extents ``sx`` x ``sy``, a round tube ``thickness`` thick."""
    r = 0.5 * thickness
    rx, ry = max(1e-4, 0.5 * sx - r), max(1e-4, 0.5 * sy - r)
    rows = []
    for i in range(ring_segments):
        u = 2 * math.pi * i / ring_segments
        row = []
        for j in range(tube_segments):
            v = 2 * math.pi * j / tube_segments
            row.append(bm.verts.new(((rx + r * math.cos(v)) * math.cos(u), (ry + r * math.cos(v)) * math.sin(u), r * math.sin(v))))
        rows.append(row)
    for i in range(ring_segments):
        for j in range(tube_segments):
            a, b = rows[i][j], rows[(i + 1) % ring_segments][j]
            c, d = rows[(i + 1) % ring_segments][(j + 1) % tube_segments], rows[i][(j + 1) % tube_segments]
            bm.faces.new((a, b, c, d))


@dataclass
class _Entry:
    spec: ObjectSpec
    obj: "bpy.types.Object"  # the top-level object (a mesh, or a rig's armature)
    meshes: list  # the mesh objects that belong to it (the object itself, or the rig's parts)


@dataclass
class BuiltScene:
    """The Blender objects of one spec. ``set_time(t)`` poses every dynamic object for t in [0, 1]."""

    spec: SceneSpec
    scene: "bpy.types.Scene"
    entries: dict[str, _Entry]
    time: float = 0.0

    @property
    def objects(self) -> dict[str, "bpy.types.Object"]:
        return {name: e.obj for name, e in self.entries.items()}

    @property
    def dynamic_objects(self) -> list["bpy.types.Object"]:
        """Mesh objects that move (a rig's parts, not its armature)."""
        return [m for e in self.entries.values() if e.spec.dynamic for m in e.meshes]

    @property
    def static_objects(self) -> list["bpy.types.Object"]:
        return [m for e in self.entries.values() if not e.spec.dynamic for m in e.meshes]

    def meshes_of(self, name: str) -> list["bpy.types.Object"]:
        return list(self.entries[name].meshes)

    def set_time(self, t: float) -> None:
        t = float(t)
        if not 0.0 <= t <= 1.0:
            raise ValueError(f"t must be in [0, 1], got {t}")
        for e in self.entries.values():
            if e.spec.motion is None:
                continue
            pose = motion_mod.evaluate(e.spec.motion.kind, t, e.spec.motion.params)
            _apply_pose(e, pose)
        self.time = t
        bpy.context.view_layer.update()


def _base_rotation(o: ObjectSpec) -> Euler:
    return Euler(tuple(math.radians(a) for a in o.rotation_deg), "XYZ")


def _apply_pose(e: _Entry, pose: motion_mod.Pose) -> None:
    o = e.spec
    e.obj.location = Vector(o.location) + Vector(pose.location)
    base = _base_rotation(o)
    e.obj.rotation_euler = Euler((base.x + pose.rotation[0], base.y + pose.rotation[1], base.z + pose.rotation[2]), "XYZ")
    if o.primitive == "rig":
        figure.pose_rig(e.obj, pose.root, dict(pose.bones))


def build_scene(bpy_scene, spec: SceneSpec) -> BuiltScene:
    """Create every object of ``spec`` in ``bpy_scene`` (normally an empty factory scene), posed at t = 0."""
    register_aovs(bpy.context.view_layer if bpy_scene == bpy.context.scene else bpy_scene.view_layers[0])
    collection = bpy_scene.collection
    entries: dict[str, _Entry] = {}
    for o in spec.objects:
        if o.primitive == "rig":
            template = figure.TEMPLATES[o.rig]
            mats = {g: make_material(f"{o.name}.{g}", o.materials[g], o.dynamic, spec.seed) for g in template.groups}
            arm, parts = figure.build_rig(o.name, template, mats, make_mesh, collection)
            arm.scale = (o.size[2],) * 3
            arm.location = o.location
            arm.rotation_euler = _base_rotation(o)
            entries[o.name] = _Entry(o, arm, parts)
        else:
            mesh = make_mesh(o.name, o.primitive, o.size)
            mesh.materials.append(make_material(o.name, o.material, o.dynamic, spec.seed))
            ob = bpy.data.objects.new(o.name, mesh)
            collection.objects.link(ob)
            ob.location = o.location
            ob.rotation_euler = _base_rotation(o)
            entries[o.name] = _Entry(o, ob, [ob])
    built = BuiltScene(spec, bpy_scene, entries)
    mark_moving_parts(built)
    built.set_time(0.0)
    return built


MOVING_SAMPLES = 101  # times in [0, 1] at which a part's vertices are compared with t = 0
MOVING_TOLERANCE = 1e-5  # world units: a part whose vertices all stay this close to where they were at t = 0 is static


def mark_moving_parts(built: BuiltScene) -> dict[str, bool]:
    """Set MOVING_PROPERTY on every mesh object: 1 where some vertex leaves its t = 0 position (by more than
    MOVING_TOLERANCE) at one of MOVING_SAMPLES times over the sequence, 0 on the static receivers and on the
    parts of a moving object that never move (standup's planted feet). The dynamic mask reads it: the
    benchmark scores a method's static/dynamic split against it, and a Gaussian on a foot that never moves
    is rightly static. Parts are rigid (bone-parented), so their vertices tell every motion. Returns
    {object name: moves}."""
    import numpy as np

    parts = built.dynamic_objects
    built.set_time(0.0)
    start = {ob.name: world_vertices([ob]) for ob in parts}
    moves = dict.fromkeys(start, False)
    for t in np.linspace(0.0, 1.0, MOVING_SAMPLES)[1:]:
        built.set_time(float(t))
        for ob in parts:
            if not moves[ob.name]:
                moves[ob.name] = bool(np.abs(world_vertices([ob]) - start[ob.name]).max() > MOVING_TOLERANCE)
    for ob in parts:
        ob[MOVING_PROPERTY] = 1.0 if moves[ob.name] else 0.0
    for ob in built.static_objects:
        ob[MOVING_PROPERTY] = 0.0
    return moves


def world_vertices(objects) -> "np.ndarray":
    """World-space vertex positions of mesh objects as one (N, 3) array, in the objects' order (exact for
    rigid, unmodified meshes: the scenes' parts are bone-parented, not deformed)."""
    import numpy as np

    out = []
    for ob in objects:
        m = np.array(ob.matrix_world)
        co = np.empty(len(ob.data.vertices) * 3)
        ob.data.vertices.foreach_get("co", co)
        out.append(co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3])
    return np.concatenate(out) if out else np.zeros((0, 3))
