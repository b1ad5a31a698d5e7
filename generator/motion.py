"""Motion as pure functions of normalised time: ``(t, params) -> Pose``, no keyframes, no bpy.

Every scene's animation is one of these functions evaluated at ``t`` in [0, 1] (t = 0 is the first frame),
so a frame can be rendered on its own, in any order, by any worker, and always gives the same pose.

A :class:`Pose` holds
  * ``location``: an offset (world units) added to the object's base location;
  * ``rotation``: XYZ Euler angles (radians) added to the object's base rotation;
  * ``root``: for rigs, a translation of the rig's root bone in the figure's rest axes, in figure units
    (a rig object is scaled by its size, so a hop of 0.1 means a tenth of the figure's height);
  * ``bones``: for rigs, per-bone XYZ Euler angles (radians) about the bone's head, expressed in the
    figure's rest axes (x = figure's left, y = back, z = up) and relative to the parent bone, so motion
    code never depends on bone rolls.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from lumibench.errors import UserError

Vec3 = tuple[float, float, float]
ZERO: Vec3 = (0.0, 0.0, 0.0)
REQUIRED = object()


@dataclass(frozen=True)
class Pose:
    location: Vec3 = ZERO
    rotation: Vec3 = ZERO
    root: Vec3 = ZERO
    bones: Mapping[str, Vec3] = field(default_factory=dict)


@dataclass(frozen=True)
class Param:
    kind: str  # "float" | "int" | "vec3" | "path" (list of >= 2 vec3)
    default: Any = REQUIRED
    doc: str = ""


@dataclass(frozen=True)
class MotionDef:
    name: str
    fn: Callable[[float, dict[str, Any]], Pose]
    params: Mapping[str, Param]
    rig: str | None  # the rig template whose bones the motion drives, or None for plain objects
    doc: str


_REGISTRY: dict[str, MotionDef] = {}


def motion(name: str, rig: str | None = None, **params: Param):
    """Register a motion function under ``name`` with its parameter schema."""

    def deco(fn):
        _REGISTRY[name] = MotionDef(name, fn, dict(params), rig, (fn.__doc__ or "").strip().splitlines()[0])
        return fn

    return deco


def available_motions() -> list[str]:
    return sorted(_REGISTRY)


def get_motion(name: str, where: str = "motion.kind") -> MotionDef:
    if name not in _REGISTRY:
        raise UserError(f"{where}: unknown motion '{name}' (known: {', '.join(available_motions())})")
    return _REGISTRY[name]


def validate_params(name: str, params: Mapping[str, Any], where: str = "motion.params") -> dict[str, Any]:
    """Check ``params`` against the motion's schema; return a complete dict (defaults filled, floats as float).

    ``where`` prefixes every message (e.g. "configs/scenes/x.yaml: key 'objects[2].motion.params'").
    """
    mdef = get_motion(name)
    if not isinstance(params, Mapping):
        raise UserError(f"{where} must be a mapping, got {type(params).__name__}")
    for key in params:
        if key not in mdef.params:
            raise UserError(
                f"{where}.{key}: not a parameter of motion '{name}' (known: {', '.join(sorted(mdef.params))})"
            )
    out: dict[str, Any] = {}
    for key, spec in mdef.params.items():
        if key not in params or params[key] is None:
            if spec.default is REQUIRED:
                raise UserError(f"{where}.{key}: required by motion '{name}' ({spec.doc})")
            value = spec.default
        else:
            value = params[key]
        out[key] = _coerce(spec.kind, value, f"{where}.{key}")
    return out


def _num(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise UserError(f"{where}: must be a finite number, got {value!r}")
    return float(value)


def _coerce(kind: str, value: Any, where: str) -> Any:
    if kind == "float":
        return _num(value, where)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"{where}: must be an integer, got {value!r}")
        return value
    if kind == "vec3":
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            raise UserError(f"{where}: must be a list of 3 numbers, got {value!r}")
        return tuple(_num(v, where) for v in value)
    if kind == "path":
        if not isinstance(value, (list, tuple)) or len(value) < 2:
            raise UserError(f"{where}: must be a list of at least 2 points [x, y, z], got {value!r}")
        return tuple(_coerce("vec3", p, f"{where}[{i}]") for i, p in enumerate(value))
    raise AssertionError(kind)


def evaluate(name: str, t: float, params: Mapping[str, Any]) -> Pose:
    """Pose of motion ``name`` at time ``t`` (clamped to [0, 1]) with validated ``params``."""
    mdef = get_motion(name)
    full = validate_params(name, params)
    return mdef.fn(min(1.0, max(0.0, float(t))), full)


# ----------------------------------------------------------------------------------------------------
# small helpers (all smooth or at least continuous in t)


def smoothstep(x: float) -> float:
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def _lerp(a: Vec3, b: Vec3, s: float) -> Vec3:
    return (a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s, a[2] + (b[2] - a[2]) * s)


def path_point(points: tuple[Vec3, ...], s: float) -> tuple[Vec3, Vec3]:
    """Point and unit tangent at arc-length fraction ``s`` of a polyline with Catmull-Rom smoothing.

    Arc-length parametrisation keeps the speed constant along the path (no jumps at the joints).
    """
    pts = list(points)
    n = len(pts) - 1
    lengths = [math.dist(pts[i], pts[i + 1]) for i in range(n)]
    total = sum(lengths) or 1.0
    target = min(1.0, max(0.0, s)) * total
    i = 0
    while i < n - 1 and target > lengths[i]:
        target -= lengths[i]
        i += 1
    u = 0.0 if lengths[i] == 0 else min(1.0, target / lengths[i])
    p0 = pts[i - 1] if i > 0 else pts[i]
    p1, p2 = pts[i], pts[i + 1]
    p3 = pts[i + 2] if i + 2 <= n else pts[i + 1]
    pos, tan = [], []
    for k in range(3):
        a, b, c, d = p0[k], p1[k], p2[k], p3[k]
        pos.append(0.5 * (2 * b + (-a + c) * u + (2 * a - 5 * b + 4 * c - d) * u * u + (-a + 3 * b - 3 * c + d) * u ** 3))
        tan.append(0.5 * ((-a + c) + 2 * (2 * a - 5 * b + 4 * c - d) * u + 3 * (-a + 3 * b - 3 * c + d) * u * u))
    norm = math.sqrt(sum(v * v for v in tan)) or 1.0
    return (pos[0], pos[1], pos[2]), (tan[0] / norm, tan[1] / norm, tan[2] / norm)


def _heading(tangent: Vec3) -> float:
    """Yaw (about +z) that turns the +x axis onto the tangent's horizontal direction."""
    return math.atan2(tangent[1], tangent[0])


# ----------------------------------------------------------------------------------------------------
# plain objects


@motion(
    "bounce",
    height=Param("float", REQUIRED, "apex height of each hop above the rest position"),
    bounces=Param("int", 2, "number of hops over t in [0, 1]"),
    phase=Param("float", 0.0, "fraction of a hop to shift the cycle by"),
    travel=Param("vec3", ZERO, "horizontal displacement from t = 0 to t = 1"),
    spin_deg=Param("vec3", ZERO, "total rotation (degrees, XYZ) from t = 0 to t = 1"),
)
def _bounce(t: float, p: dict) -> Pose:
    """A ball bouncing: |sin| hops (ground contact at the cusps) while drifting and rolling."""
    s = math.pi * (p["bounces"] * t + p["phase"])
    z = p["height"] * abs(math.sin(s))
    tr = p["travel"]
    spin = tuple(math.radians(a) * t for a in p["spin_deg"])
    return Pose(location=(tr[0] * t, tr[1] * t, z + tr[2] * t), rotation=spin)


@motion(
    "swing",
    axis=Param("vec3", (1.0, 0.0, 0.0), "weights of the angle on the X, Y, Z Euler angles (a unit axis: a plain swing)"),
    amplitude_deg=Param("float", REQUIRED, "peak angle of the swing"),
    cycles=Param("float", 1.0, "full periods over t in [0, 1]"),
    phase=Param("float", 0.0, "fraction of a period to shift the cycle by"),
)
def _swing(t: float, p: dict) -> Pose:
    """A pendulum-like sinusoidal rotation about one of the object's axes."""
    a = math.radians(p["amplitude_deg"]) * math.sin(2 * math.pi * (p["cycles"] * t + p["phase"]))
    axis = p["axis"]
    return Pose(rotation=(a * axis[0], a * axis[1], a * axis[2]))


@motion(
    "translate_path",
    points=Param("path", REQUIRED, "polyline [[x, y, z], ...] followed at constant speed (offsets)"),
    face_path=Param("int", 0, "1: turn about z so the object's +x faces the direction of travel"),
    ease=Param("int", 1, "1: smooth start and stop, 0: constant speed"),
)
def _translate_path(t: float, p: dict) -> Pose:
    """Follow a smoothed polyline, optionally heading along it."""
    s = smoothstep(t) if p["ease"] else t
    pos, tan = path_point(p["points"], s)
    rot = (0.0, 0.0, _heading(tan)) if p["face_path"] else ZERO
    return Pose(location=pos, rotation=rot)


# ----------------------------------------------------------------------------------------------------
# rigs (bone names are those of the templates in generator/blender/figure.py)


@motion(
    "jumping_jack",
    rig="humanoid",
    cycles=Param("float", 3.0, "jumping jacks over t in [0, 1]"),
    hop=Param("float", 0.08, "apex height of each hop, in figure heights"),
    arm_deg=Param("float", 150.0, "arm abduction when open (0 = arms down)"),
    leg_deg=Param("float", 18.0, "leg abduction when open"),
    thigh_length=Param("float", 0.24, "thigh length in figure heights (the humanoid template's)"),
)
def _jumping_jack(t: float, p: dict) -> Pose:
    """Jumping jacks: arms up and legs apart, then back, one hop at each switch; soles stay flat."""
    s = p["cycles"] * t
    openness = 0.5 - 0.5 * math.cos(2 * math.pi * s)
    arm = math.radians(p["arm_deg"]) * openness
    leg = math.radians(p["leg_deg"]) * openness
    # the shins counter-rotate so the feet stay flat; the hip then sits lower by thigh * (1 - cos(leg))
    z = p["hop"] * abs(math.sin(2 * math.pi * s)) - p["thigh_length"] * (1.0 - math.cos(leg))
    bones = {
        "upper_arm.L": (0.0, -arm, 0.0),
        "upper_arm.R": (0.0, arm, 0.0),
        "forearm.L": (0.0, -0.15 * arm, 0.0),
        "forearm.R": (0.0, 0.15 * arm, 0.0),
        "thigh.L": (0.0, -leg, 0.0),
        "thigh.R": (0.0, leg, 0.0),
        "shin.L": (0.0, leg, 0.0),
        "shin.R": (0.0, -leg, 0.0),
        "head": (0.12 * openness, 0.0, 0.0),
    }
    return Pose(root=(0.0, 0.0, z), bones=bones)


def _two_link_ik(dx: float, dz: float, l1: float, l2: float) -> tuple[float, float]:
    """Planar IK: hip and knee angles (radians) that put a 2-link leg's end at (dx, dz) from the hip.

    Angles are measured from straight down; positive hip angle swings the leg forward (-y), the knee
    angle is the bend of the shin backward relative to the thigh (>= 0).
    """
    d = min(l1 + l2 - 1e-6, math.hypot(dx, dz))
    cos_knee = (l1 * l1 + l2 * l2 - d * d) / (2 * l1 * l2)
    knee = math.pi - math.acos(max(-1.0, min(1.0, cos_knee)))
    to_foot = math.atan2(dx, -dz)  # angle of the hip->foot line from straight down, forward positive
    cos_a = (l1 * l1 + d * d - l2 * l2) / (2 * l1 * d)
    hip = to_foot + math.acos(max(-1.0, min(1.0, cos_a)))
    return hip, knee


@motion(
    "stand_up",
    rig="humanoid",
    seat_height=Param("float", REQUIRED, "height of the seat top above the soles, in figure heights"),
    start=Param("float", 0.15, "t at which rising starts (sitting still before)"),
    end=Param("float", 0.75, "t at which the figure is upright (standing still after)"),
    thigh_length=Param("float", 0.24, "thigh length in figure heights (the humanoid template's)"),
    shin_length=Param("float", 0.24, "knee to ankle, in figure heights"),
    ankle_height=Param("float", 0.04, "ankle above the sole, in figure heights"),
    hip_height=Param("float", 0.52, "hip joint height when standing, in figure heights"),
)
def _stand_up(t: float, p: dict) -> Pose:
    """A seated figure stands up: feet planted (analytic leg IK), torso leans forward, arms swing.

    The seated pelvis rests on the seat; the feet stay where they were while the hips travel forward
    over them and up, so no part slides through the floor or the seat.
    """
    l1, l2, hip_h = p["thigh_length"], p["shin_length"], p["hip_height"]
    s = smoothstep((t - p["start"]) / max(1e-6, p["end"] - p["start"]))
    seat_hip = p["seat_height"] + 0.05  # the hip joint sits above the seat by the thighs' half thickness
    # seated: thighs horizontal, knees above the feet: feet at l1 forward of the hips
    foot_y = -l1
    hip_y = foot_y * s  # hips move from above the seat to above the feet
    hip_z = seat_hip + (hip_h - seat_hip) * s
    lean = math.radians(35.0) * math.sin(math.pi * s) + math.radians(8.0) * (1.0 - s)
    # the foot's forward (-y) offset from the hip, and its height below the hip
    hip, knee = _two_link_ik(hip_y - foot_y, -(hip_z - p["ankle_height"]), l1, l2)
    arms = math.radians(50.0) * math.sin(math.pi * s)
    bones = {
        # a positive angle about +x swings a downward bone backward (+y) and tilts an upward one forward
        "thigh.L": (-hip, 0.0, 0.0),
        "thigh.R": (-hip, 0.0, 0.0),
        "shin.L": (knee, 0.0, 0.0),
        "shin.R": (knee, 0.0, 0.0),
        "foot.L": (hip - knee, 0.0, 0.0),  # undo the leg's pitch: soles stay flat on the floor
        "foot.R": (hip - knee, 0.0, 0.0),
        "spine": (lean, 0.0, 0.0),
        # seated, the forearms rest forward over the thighs; rising, the arms swing forward for balance
        "upper_arm.L": (-(arms + lean + 0.6 * (1.0 - s)), 0.0, 0.0),
        "upper_arm.R": (-(arms + lean + 0.6 * (1.0 - s)), 0.0, 0.0),
        "forearm.L": (-(0.3 * arms + 0.7 * (1.0 - s)), 0.0, 0.0),
        "forearm.R": (-(0.3 * arms + 0.7 * (1.0 - s)), 0.0, 0.0),
    }
    return Pose(root=(0.0, hip_y, hip_z - hip_h), bones=bones)


@motion(
    "run_cycle",
    rig="quadruped",
    points=Param("path", REQUIRED, "polyline [[x, y, z], ...] the animal runs along (offsets)"),
    strides=Param("float", 6.0, "gait cycles over t in [0, 1]"),
    stride_deg=Param("float", 35.0, "peak leg swing"),
    bob=Param("float", 0.02, "body bob amplitude, in template units"),
    leg_length=Param("float", 0.2, "hip to paw contact, in template units (lowers the body as legs swing)"),
    tail_deg=Param("float", 25.0, "tail wag amplitude"),
)
def _run_cycle(t: float, p: dict) -> Pose:
    """A small animal trotting along a path: diagonal leg pairs in phase, body bob, wagging tail."""
    pos, tan = path_point(p["points"], t)
    ph = 2 * math.pi * p["strides"] * t
    a = math.radians(p["stride_deg"]) * math.sin(ph)
    wag = math.radians(p["tail_deg"]) * math.sin(ph * 0.5)
    bones = {
        # legs hang down along -z; rotation about +y swings them along +x (the running direction)
        "leg.FL": (0.0, a, 0.0),
        "leg.BR": (0.0, a, 0.0),
        "leg.FR": (0.0, -a, 0.0),
        "leg.BL": (0.0, -a, 0.0),
        "tail.1": (0.0, 0.0, wag),
        "tail.2": (0.0, 0.0, 0.8 * wag),
        "head": (0.0, 0.12 * math.sin(ph), 0.0),
    }
    # a swung leg's paw rises by about leg * (1 - cos a): lower the body to keep the paws on the floor
    z = p["bob"] * abs(math.sin(ph)) - p["leg_length"] * (1.0 - math.cos(a))
    return Pose(location=pos, rotation=(0.0, 0.0, _heading(tan)), root=(0.0, 0.0, z), bones=bones)


@motion(
    "crane_swing",
    rig="crane",
    yaw_deg=Param("float", 70.0, "boom yaw amplitude about the mast"),
    yaw_cycles=Param("float", 1.0, "boom yaw periods over t in [0, 1]"),
    swing_deg=Param("float", 25.0, "pendulum amplitude of the hanging load"),
    swing_cycles=Param("float", 3.0, "pendulum periods over t in [0, 1]"),
)
def _crane_swing(t: float, p: dict) -> Pose:
    """A hook on a boom: the boom yaws about the mast while the hanging load swings like a pendulum."""
    yaw = math.radians(p["yaw_deg"]) * math.sin(2 * math.pi * p["yaw_cycles"] * t)
    swing = math.radians(p["swing_deg"]) * math.sin(2 * math.pi * p["swing_cycles"] * t)
    side = 0.4 * math.radians(p["swing_deg"]) * math.sin(2 * math.pi * (p["swing_cycles"] * t + 0.25))
    return Pose(bones={"boom": (0.0, 0.0, yaw), "cable": (side, swing, 0.0)})
