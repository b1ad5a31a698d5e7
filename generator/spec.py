"""Scene specs: declarative YAML (``configs/scenes/<name>.yaml``) -> validated, frozen :class:`SceneSpec`.

The spec says *what* is in a scene (objects, materials, motion, camera ranges); generator/blender/
only turns it into Blender data. No bpy here, so specs load and validate anywhere (tests, the CLI).
Every object is either a primitive (box, sphere, ...) or a rig (an articulated template from
generator/blender/figure.py); an object with a motion is dynamic, everything else is a static receiver.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lumibench.config import Node, load_yaml
from lumibench.errors import UserError

from . import motion as motion_mod

SCENES_DIR = Path(__file__).resolve().parent.parent / "configs" / "scenes"

PRIMITIVES = ("box", "sphere", "ico_sphere", "cylinder", "cone", "torus", "rig")
TEXTURES = ("none", "checker", "noise", "bricks", "stripes")
TECHNICAL_SCENES = ("calib_sphere", "calib_sphere_glossy")  # not benchmark scenes; for convention tests
# Bump when generator/motion.py or generator/blender/build.py change what a given spec renders.
BUILDER_VERSION = 3  # 2: UV spheres built vertex by vertex (deterministic face-corner order); 3: the dynamic
# mask marks the parts that move during the sequence, not whole moving objects (build.mark_moving_parts)
SCENE_BOX = 1.3  # everything must stay inside [-SCENE_BOX, SCENE_BOX]^3 (the method initialises there)

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class TextureSpec:
    """A procedural pattern mixing ``base_color``/``color2`` (and ``roughness``/``roughness2``)."""

    kind: str = "none"
    color2: Vec3 = (0.0, 0.0, 0.0)
    scale: float = 4.0  # pattern frequency in object-space units
    roughness2: float | None = None  # None: uniform roughness


@dataclass(frozen=True)
class MaterialSpec:
    """Principled BSDF inputs. Colours are linear RGB in [0, 1]; metallic is always 0."""

    base_color: Vec3
    roughness: float
    texture: TextureSpec = field(default_factory=TextureSpec)


@dataclass(frozen=True)
class MotionSpec:
    kind: str
    params: dict[str, Any]  # validated and completed with defaults by generator.motion


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    primitive: str  # one of PRIMITIVES
    size: Vec3  # full extents (box/sphere/...); for rigs (size[2]) is the figure height
    location: Vec3
    rotation_deg: Vec3
    material: MaterialSpec | None  # primitives
    materials: dict[str, MaterialSpec]  # rigs: one per part group of the template
    rig: str | None
    motion: MotionSpec | None
    dynamic: bool


@dataclass(frozen=True)
class CameraSpec:
    radius: float
    target: Vec3
    elevation_deg: tuple[float, float]
    camera_angle_x: float  # radians


@dataclass(frozen=True)
class SceneSpec:
    name: str
    seed: int
    description: str
    frames_full: int
    camera: CameraSpec
    objects: tuple[ObjectSpec, ...]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def spec_hash(self) -> str:
        """sha256 of a canonical JSON of the content (sorted keys, fixed float repr): stable across runs.

        Besides the YAML's content it covers what the YAML refers to: the rig templates it uses and
        BUILDER_VERSION, so a change of a figure's geometry or of motion semantics invalidates old frames.
        """
        content = self.to_dict()
        rigs = sorted({o.rig for o in self.objects if o.rig})
        content["_rig_templates"] = {r: dataclasses.asdict(rig_templates()[r]) for r in rigs}
        content["_builder_version"] = BUILDER_VERSION
        text = json.dumps(_canonical(content), sort_keys=True, separators=(",", ":"), allow_nan=False)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    def dynamic_object_names(self) -> list[str]:
        return [o.name for o in self.objects if o.dynamic]

    def static_object_names(self) -> list[str]:
        return [o.name for o in self.objects if not o.dynamic]

    def object(self, name: str) -> ObjectSpec:
        for o in self.objects:
            if o.name == name:
                return o
        raise UserError(f"scene '{self.name}' has no object '{name}' (objects: {', '.join(o.name for o in self.objects)})")

    def without(self, *object_names: str) -> "SceneSpec":
        """A copy without the named objects (e.g. to measure the shadow an occluder casts)."""
        for n in object_names:
            self.object(n)
        kept = tuple(o for o in self.objects if o.name not in set(object_names))
        return dataclasses.replace(self, objects=kept)


def _canonical(obj: Any) -> Any:
    if isinstance(obj, float):
        return float(repr(obj)) if obj != 0 else 0.0  # -0.0 and 0.0 hash alike
    if isinstance(obj, dict):
        return {str(k): _canonical(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    return obj


# ----------------------------------------------------------------------------------------------------


def rig_templates() -> dict:
    """The articulated templates (pure data; importing them does not import bpy)."""
    from .blender.figure import TEMPLATES

    return TEMPLATES


def available_scenes() -> list[str]:
    """Every scene spec in configs/scenes/, sorted (the five benchmark scenes and the technical ones)."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.yaml"))


def benchmark_scenes() -> list[str]:
    """The dynamic benchmark scenes: all specs except the technical ones (TECHNICAL_SCENES)."""
    return [s for s in available_scenes() if s not in TECHNICAL_SCENES]


def load_scene_spec(name: str, path: str | Path | None = None) -> SceneSpec:
    """Load and validate ``configs/scenes/<name>.yaml`` (or ``path``); any mistake -> one-line UserError."""
    if path is None:
        path = SCENES_DIR / f"{name}.yaml"
        if not path.is_file():
            raise UserError(f"unknown scene '{name}' (known: {', '.join(available_scenes())})")
    path = Path(path)
    src = str(path)
    root = Node(load_yaml(path), src)
    root.reject_unknown(["seed", "description", "frames_full", "camera", "objects"])
    seed = root.get("seed", int, check=lambda v: v >= 0, check_msg="must be >= 0")
    frames_full = root.get("frames_full", int, check=lambda v: v >= 2, check_msg="must be >= 2")
    description = root.get("description", str, "")
    camera = _camera(root.child("camera"))
    nodes = root.children("objects")
    if not nodes:
        raise root.error("objects", "must list at least one object")
    objects = []
    seen: set[str] = set()
    for node in nodes:
        obj = _object(node)
        if obj.name in seen:
            raise node.error("name", f"duplicates another object's name '{obj.name}'")
        seen.add(obj.name)
        objects.append(obj)
    return SceneSpec(
        name=path.stem if name is None else name,
        seed=seed,
        description=description,
        frames_full=frames_full,
        camera=camera,
        objects=tuple(objects),
    )


def _vec(node: Node, key: str, n: int = 3, default: Any = None, check=None, check_msg="is out of range") -> tuple:
    raw = node.get(key, list) if default is None else node.get(key, list, list(default))
    if len(raw) != n:
        raise node.error(key, f"must be a list of {n} numbers, got {raw!r}")
    out = []
    for v in raw:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise node.error(key, f"must be a list of {n} numbers, got {raw!r}")
        out.append(float(v))
    if check is not None and not check(out):
        raise node.error(key, f"{check_msg} (got {raw!r})")
    return tuple(out)


def _unit(v: list[float]) -> bool:
    return all(0.0 <= x <= 1.0 for x in v)


def _camera(node: Node) -> CameraSpec:
    node.reject_unknown(["radius", "target", "elevation_deg", "camera_angle_x"])
    radius = node.get("radius", float, check=lambda v: 1.0 < v < 50.0, check_msg="must be in (1, 50) scene units")
    target = _vec(node, "target", check=lambda v: all(abs(x) <= SCENE_BOX for x in v), check_msg="must lie in the scene box")
    elev = _vec(
        node,
        "elevation_deg",
        2,
        check=lambda v: 0.0 <= v[0] <= v[1] <= 90.0,
        check_msg="must be [lo, hi] with 0 <= lo <= hi <= 90 (upper hemisphere)",
    )
    fov = node.get("camera_angle_x", float, check=lambda v: 0.05 < v < 3.0, check_msg="must be in radians, (0.05, 3)")
    return CameraSpec(radius, target, elev, fov)


def _material(node: Node) -> MaterialSpec:
    node.reject_unknown(["base_color", "roughness", "texture"])
    color = _vec(node, "base_color", check=_unit, check_msg="must be linear RGB in [0, 1]")
    rough = node.get("roughness", float, check=lambda v: 0.0 <= v <= 1.0, check_msg="must be in [0, 1]")
    tex = TextureSpec()
    if node.data.get("texture") is not None:
        tn = node.child("texture")
        tn.reject_unknown(["kind", "color2", "scale", "roughness2"])
        r2 = tn.get("roughness2", float, None, check=lambda v: 0.0 <= v <= 1.0, check_msg="must be in [0, 1]")
        tex = TextureSpec(
            kind=tn.get("kind", str, choices=TEXTURES),
            color2=_vec(tn, "color2", default=color, check=_unit, check_msg="must be linear RGB in [0, 1]"),
            scale=tn.get("scale", float, 4.0, check=lambda v: v > 0, check_msg="must be positive"),
            roughness2=r2,
        )
    return MaterialSpec(color, rough, tex)


def _object(node: Node) -> ObjectSpec:
    node.reject_unknown(["name", "primitive", "rig", "size", "location", "rotation_deg", "material", "materials", "motion"])
    name = node.get("name", str, check=lambda v: v.strip() != "" and "/" not in v, check_msg="must be a non-empty name")
    prim = node.get("primitive", str, choices=PRIMITIVES)
    size = _vec(node, "size", check=lambda v: all(x > 0 for x in v), check_msg="must be positive extents")
    loc = _vec(node, "location", default=(0, 0, 0))
    rot = _vec(node, "rotation_deg", default=(0, 0, 0))
    rig = None
    material = None
    materials: dict[str, MaterialSpec] = {}
    if prim == "rig":
        rig = node.get("rig", str, choices=sorted(rig_templates()))
        if len(set(size)) != 1:
            raise node.error("size", f"must be uniform for a rig (the template's scale), got {list(size)}")
        groups = rig_templates()[rig].groups
        mnode = node.child("materials")
        mnode.reject_unknown(groups)
        for group in groups:
            materials[group] = _material(mnode.child(group))
        if "material" in node.data:
            raise node.error("material", "is for primitives; a rig takes 'materials' (one per part group)")
    else:
        if "rig" in node.data:
            raise node.error("rig", "only applies to primitive: rig")
        if "materials" in node.data:
            raise node.error("materials", "only applies to primitive: rig (use 'material')")
        material = _material(node.child("material"))
    mot = None
    if node.data.get("motion") is not None:
        mn = node.child("motion")
        mn.reject_unknown(["kind", "params"])
        kind = mn.get("kind", str, choices=motion_mod.available_motions())
        mdef = motion_mod.get_motion(kind)
        if mdef.rig is not None and mdef.rig != rig:
            raise mn.error("kind", f"'{kind}' drives a '{mdef.rig}' rig, but this object is {rig or prim}")
        params = mn.get("params", dict, {})
        where = f"{node.source}: key '{mn.where('params')}'"
        mot = MotionSpec(kind, motion_mod.validate_params(kind, params, where))
    return ObjectSpec(
        name=name,
        primitive=prim,
        size=size,
        location=loc,
        rotation_deg=rot,
        material=material,
        materials=materials,
        rig=rig,
        motion=mot,
        dynamic=mot is not None,
    )
