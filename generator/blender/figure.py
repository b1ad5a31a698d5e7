"""Articulated figures: rig templates (bones + rigid primitive parts) as plain data, built with bpy.

A template is written in its own units (the humanoid is 1 tall, soles at z = 0, facing -y, its left
at +x; the quadruped faces +x; the crane's pivot is its origin). The rig object is scaled uniformly
by the spec's size, so motion code (generator/motion.py) works in template units. Parts are rigid
primitive meshes parented to bones (bone parenting, not skinning: cheap, exact, and bounding boxes
of the posed parts are just their world matrices applied to their vertices).

This module imports bpy only inside functions, so spec validation can read the templates anywhere.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class BoneDef:
    name: str
    head: Vec3
    tail: Vec3
    parent: str | None = None


@dataclass(frozen=True)
class PartDef:
    name: str
    bone: str
    primitive: str  # box | sphere | cylinder | cone | torus
    center: Vec3
    size: Vec3  # full extents before rotation
    group: str  # material group: the spec gives one material per group
    rotation_deg: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RigTemplate:
    name: str
    bones: tuple[BoneDef, ...]
    parts: tuple[PartDef, ...]

    @property
    def groups(self) -> tuple[str, ...]:
        return tuple(sorted({p.group for p in self.parts}))

    @property
    def bone_names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.bones)


def _along(name: str, bone: str, head: Vec3, tail: Vec3, width: float, group: str, prim: str = "cylinder",
           extend: float = 0.0) -> PartDef:
    """A cylinder (or cone) whose axis runs from ``head`` to ``tail`` (extended by ``extend`` at both ends)."""
    d = [tail[i] - head[i] for i in range(3)]
    length = math.sqrt(sum(v * v for v in d))
    theta = math.degrees(math.acos(max(-1.0, min(1.0, d[2] / length))))
    phi = math.degrees(math.atan2(d[1], d[0])) if abs(d[0]) + abs(d[1]) > 1e-9 else 0.0
    center = tuple((head[i] + tail[i]) / 2 for i in range(3))
    return PartDef(name, bone, prim, center, (width, width, length + 2 * extend), group, (0.0, theta, phi))


def _mirror(parts_or_bones, side_from: str = ".L", side_to: str = ".R"):
    out = []
    for item in parts_or_bones:
        if isinstance(item, BoneDef):
            out.append(BoneDef(item.name.replace(side_from, side_to), (-item.head[0], item.head[1], item.head[2]),
                               (-item.tail[0], item.tail[1], item.tail[2]),
                               item.parent.replace(side_from, side_to) if item.parent else None))
        else:
            c, r = item.center, item.rotation_deg
            out.append(PartDef(item.name.replace(side_from, side_to), item.bone.replace(side_from, side_to),
                               item.primitive, (-c[0], c[1], c[2]), item.size, item.group, (r[0], -r[1], -r[2])))
    return out


# ---------------------------------------------------------------------------------------------------- humanoid
_H_BONES_L = [
    BoneDef("upper_arm.L", (0.15, 0.0, 0.82), (0.15, 0.0, 0.62), "spine"),
    BoneDef("forearm.L", (0.15, 0.0, 0.62), (0.15, 0.0, 0.42), "upper_arm.L"),
    BoneDef("thigh.L", (0.07, 0.0, 0.52), (0.07, 0.0, 0.28), "hips"),
    BoneDef("shin.L", (0.07, 0.0, 0.28), (0.07, 0.0, 0.04), "thigh.L"),
    BoneDef("foot.L", (0.07, 0.0, 0.04), (0.07, -0.11, 0.04), "shin.L"),
]
_H_PARTS_L = [
    PartDef("shoulder.L", "upper_arm.L", "sphere", (0.15, 0.0, 0.81), (0.08, 0.08, 0.08), "shirt"),
    PartDef("upper_arm.L", "upper_arm.L", "cylinder", (0.15, 0.0, 0.715), (0.07, 0.07, 0.19), "shirt"),
    PartDef("elbow.L", "forearm.L", "sphere", (0.15, 0.0, 0.62), (0.066, 0.066, 0.066), "skin"),
    PartDef("forearm.L", "forearm.L", "cylinder", (0.15, 0.0, 0.52), (0.06, 0.06, 0.2), "skin"),
    PartDef("hand.L", "forearm.L", "sphere", (0.15, 0.0, 0.41), (0.07, 0.06, 0.08), "skin"),
    PartDef("thigh.L", "thigh.L", "cylinder", (0.07, 0.0, 0.40), (0.095, 0.095, 0.24), "pants"),
    PartDef("knee.L", "shin.L", "sphere", (0.07, 0.0, 0.28), (0.09, 0.09, 0.09), "pants"),
    PartDef("shin.L", "shin.L", "cylinder", (0.07, 0.0, 0.165), (0.078, 0.078, 0.23), "pants"),
    PartDef("foot.L", "foot.L", "box", (0.07, -0.03, 0.025), (0.085, 0.17, 0.05), "shoes"),
]
HUMANOID = RigTemplate(
    "humanoid",
    bones=tuple(
        [
            BoneDef("hips", (0.0, 0.0, 0.52), (0.0, 0.0, 0.60)),
            BoneDef("spine", (0.0, 0.0, 0.60), (0.0, 0.0, 0.84), "hips"),
            BoneDef("head", (0.0, 0.0, 0.84), (0.0, 0.0, 1.0), "spine"),
        ]
        + _H_BONES_L
        + _mirror(_H_BONES_L)
    ),
    parts=tuple(
        [
            PartDef("pelvis", "hips", "box", (0.0, 0.0, 0.545), (0.23, 0.13, 0.1), "pants"),
            PartDef("torso", "spine", "box", (0.0, 0.0, 0.725), (0.27, 0.15, 0.25), "shirt"),
            PartDef("neck", "head", "cylinder", (0.0, 0.0, 0.86), (0.06, 0.06, 0.05), "skin"),
            PartDef("head", "head", "sphere", (0.0, -0.005, 0.93), (0.15, 0.16, 0.17), "skin"),
        ]
        + _H_PARTS_L
        + _mirror(_H_PARTS_L)
    ),
)

# ---------------------------------------------------------------------------------------------------- quadruped
_Q_LEGS = []
_Q_LEG_PARTS = []
for _tag, _x, _y in (("FL", 0.2, 0.12), ("FR", 0.2, -0.12), ("BL", -0.2, 0.12), ("BR", -0.2, -0.12)):
    _Q_LEGS.append(BoneDef(f"leg.{_tag}", (_x, _y, 0.26), (_x, _y, 0.03), "body"))
    _Q_LEG_PARTS.append(PartDef(f"leg.{_tag}", f"leg.{_tag}", "cylinder", (_x, _y, 0.14), (0.06, 0.06, 0.24), "fur"))
    _Q_LEG_PARTS.append(PartDef(f"paw.{_tag}", f"leg.{_tag}", "sphere", (_x + 0.015, _y, 0.025), (0.09, 0.065, 0.05), "paws"))
QUADRUPED = RigTemplate(
    "quadruped",
    bones=tuple(
        [
            BoneDef("body", (-0.3, 0.0, 0.32), (0.3, 0.0, 0.32)),
            BoneDef("head", (0.3, 0.0, 0.34), (0.55, 0.0, 0.34), "body"),
            BoneDef("tail.1", (-0.34, 0.0, 0.30), (-0.64, 0.0, 0.22), "body"),
            BoneDef("tail.2", (-0.64, 0.0, 0.22), (-0.95, 0.0, 0.24), "tail.1"),
        ]
        + _Q_LEGS
    ),
    parts=tuple(
        [
            PartDef("torso", "body", "sphere", (0.0, 0.0, 0.32), (0.75, 0.36, 0.32), "fur"),
            PartDef("head", "head", "sphere", (0.42, 0.0, 0.37), (0.34, 0.24, 0.22), "fur"),
            PartDef("nose", "head", "sphere", (0.59, 0.0, 0.36), (0.06, 0.06, 0.06), "nose"),
            PartDef("ear.L", "head", "sphere", (0.37, 0.1, 0.5), (0.05, 0.15, 0.15), "ears"),
            PartDef("ear.R", "head", "sphere", (0.37, -0.1, 0.5), (0.05, 0.15, 0.15), "ears"),
            _along("tail.1", "tail.1", (-0.34, 0.0, 0.30), (-0.64, 0.0, 0.22), 0.045, "ears", extend=0.01),
            _along("tail.2", "tail.2", (-0.64, 0.0, 0.22), (-0.95, 0.0, 0.24), 0.035, "ears", prim="cone", extend=0.01),
        ]
        + _Q_LEG_PARTS
    ),
)

# ---------------------------------------------------------------------------------------------------- crane
CRANE = RigTemplate(
    "crane",
    bones=(
        BoneDef("boom", (0.0, 0.0, 0.0), (0.75, 0.0, 0.0)),
        BoneDef("cable", (0.75, 0.0, 0.0), (0.75, 0.0, -0.5), "boom"),
    ),
    parts=(
        PartDef("hub", "boom", "cylinder", (0.0, 0.0, 0.0), (0.16, 0.16, 0.14), "boom"),
        PartDef("boom", "boom", "box", (0.3, 0.0, 0.0), (1.1, 0.08, 0.08), "boom"),
        PartDef("counterweight", "boom", "box", (-0.18, 0.0, -0.05), (0.16, 0.18, 0.16), "weight"),
        PartDef("cable", "cable", "cylinder", (0.75, 0.0, -0.21), (0.016, 0.016, 0.38), "cable"),
        PartDef("hook", "cable", "torus", (0.75, 0.0, -0.44), (0.12, 0.12, 0.03), "cable", (90.0, 0.0, 0.0)),
        PartDef("cargo", "cable", "box", (0.75, 0.0, -0.6), (0.26, 0.26, 0.22), "cargo"),
    ),
)

TEMPLATES: dict[str, RigTemplate] = {t.name: t for t in (HUMANOID, QUADRUPED, CRANE)}


# ---------------------------------------------------------------------------------------------------- bpy


def build_rig(name: str, template: RigTemplate, materials: dict, make_mesh, collection):
    """Create the armature object ``name`` with one mesh object per part, bone-parented.

    ``materials`` maps group -> bpy material; ``make_mesh(name, primitive, size)`` returns a bpy mesh
    centred at its origin. Returns (armature_object, [part objects]).
    """
    import bpy
    from mathutils import Euler, Matrix, Vector

    arm_data = bpy.data.armatures.new(f"{name}.armature")
    arm = bpy.data.objects.new(name, arm_data)
    collection.objects.link(arm)
    view_layer = bpy.context.view_layer
    # edit bones need edit mode on the active object
    for o in view_layer.objects:
        o.select_set(False)
    view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    ebs = {}
    for b in template.bones:
        eb = arm_data.edit_bones.new(b.name)
        eb.head = Vector(b.head)
        eb.tail = Vector(b.tail)
        # a fixed roll convention; motion code does not depend on it (rotations are given in rig axes)
        eb.align_roll(Vector((0.0, -1.0, 0.0)) if abs(b.tail[1] - b.head[1]) < 0.9 * _dist(b.head, b.tail) else Vector((0.0, 0.0, 1.0)))
        if b.parent:
            eb.parent = ebs[b.parent]
            eb.use_connect = False
        ebs[b.name] = eb
    bpy.ops.object.mode_set(mode="OBJECT")
    for pb in arm.pose.bones:
        pb.rotation_mode = "QUATERNION"
    view_layer.update()

    parts = []
    for p in template.parts:
        mesh = make_mesh(f"{name}.{p.name}", p.primitive, p.size)
        mesh.materials.append(materials[p.group])
        ob = bpy.data.objects.new(f"{name}.{p.name}", mesh)
        collection.objects.link(ob)
        ob.parent = arm
        ob.parent_type = "BONE"
        ob.parent_bone = p.bone
        view_layer.update()
        # place the part at its rest position in the rig (Blender solves the bone-relative basis)
        rest = Matrix.Translation(Vector(p.center)) @ Euler(tuple(math.radians(a) for a in p.rotation_deg), "XYZ").to_matrix().to_4x4()
        ob.matrix_world = arm.matrix_world @ rest
        parts.append(ob)
    view_layer.update()
    return arm, parts


def _dist(a: Vec3, b: Vec3) -> float:
    return math.sqrt(sum((a[i] - b[i]) ** 2 for i in range(3)))


def pose_rig(arm, root: Vec3, bones: dict) -> None:
    """Set pose-bone transforms from rig-axis rotations (XYZ Euler, radians) and a root translation."""
    from mathutils import Euler, Vector

    names = {pb.name for pb in arm.pose.bones}
    for bone_name in bones:
        if bone_name not in names:
            raise ValueError(f"rig '{arm.name}' has no bone '{bone_name}'")
    for pb in arm.pose.bones:
        rest = pb.bone.matrix_local.to_3x3()  # bone axes in rig space, at rest
        angles = bones.get(pb.name, (0.0, 0.0, 0.0))
        r_rig = Euler(angles, "XYZ").to_matrix()
        pb.rotation_quaternion = (rest.transposed() @ r_rig @ rest).to_quaternion()
        if pb.parent is None:
            pb.location = rest.transposed() @ Vector(root)
        else:
            pb.location = (0.0, 0.0, 0.0)
