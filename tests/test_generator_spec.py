"""Scene specs and motion functions (no Blender): validation messages, hashing, purity and continuity."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from generator import motion
from generator.blender.figure import HUMANOID, TEMPLATES
from generator.spec import SCENES_DIR, available_scenes, benchmark_scenes, load_scene_spec
from lumibench.errors import UserError

REAL = ["hook", "jumpingjacks", "mouse", "spheres", "standup"]
MINIMAL = textwrap.dedent(
    """
    seed: 3
    frames_full: 150
    camera: {radius: 4.0, target: [0, 0, 0], elevation_deg: [10, 60], camera_angle_x: 0.69}
    objects:
      - name: plate
        primitive: box
        size: [2, 2, 0.1]
        location: [0, 0, -0.55]
        material: {base_color: [0.5, 0.5, 0.5], roughness: 0.8}
      - name: ball
        primitive: sphere
        size: [0.3, 0.3, 0.3]
        location: [0, 0, -0.35]
        material: {base_color: [0.8, 0.1, 0.1], roughness: 0.15}
        motion: {kind: bounce, params: {height: 0.5}}
    """
)


def _write(tmp_path: Path, text: str, name: str = "toy") -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    return path


def _load(tmp_path, text):
    return load_scene_spec("toy", _write(tmp_path, text))


def test_scene_list_contains_the_five_scenes_and_calibration():
    assert set(REAL) | {"calib_sphere", "calib_sphere_glossy"} == set(available_scenes())
    assert available_scenes() == sorted(available_scenes())
    assert benchmark_scenes() == REAL


def test_spec_hash_covers_the_rig_template(monkeypatch):
    from generator.blender import figure

    spec = load_scene_spec("jumpingjacks")
    before = spec.spec_hash()
    moved = dataclasses.replace(figure.HUMANOID, parts=figure.HUMANOID.parts[1:])
    monkeypatch.setitem(figure.TEMPLATES, "humanoid", moved)
    assert spec.spec_hash() != before
    assert load_scene_spec("spheres").spec_hash() == load_scene_spec("spheres").spec_hash()


@pytest.mark.parametrize("name", REAL)
def test_real_scenes_load_with_moving_and_static_parts(name):
    spec = load_scene_spec(name)
    assert spec.name == name
    assert spec.frames_full == (100 if name == "spheres" else 150)
    assert spec.dynamic_object_names() and spec.static_object_names()
    assert "plate" in spec.static_object_names()
    roughs = set()
    textured = 0
    for o in spec.objects:
        mats = [o.material] if o.material is not None else list(o.materials.values())
        for m in mats:
            roughs.add(m.roughness)
            if m.texture.roughness2 is not None:
                roughs.add(m.texture.roughness2)
            textured += m.texture.kind != "none"
    assert min(roughs) <= 0.25 and max(roughs) >= 0.75, f"{name}: needs glossy and rough materials, got {sorted(roughs)}"
    assert textured >= 2, f"{name}: needs textured albedo"
    assert 0.0 < spec.camera.camera_angle_x < math.pi
    assert 0.0 <= spec.camera.elevation_deg[0] < spec.camera.elevation_deg[1] <= 90.0


def test_calib_sphere_is_one_static_uniform_sphere():
    spec = load_scene_spec("calib_sphere")
    assert len(spec.objects) == 1 and spec.dynamic_object_names() == []
    o = spec.objects[0]
    assert o.primitive == "sphere" and o.motion is None and o.material.texture.kind == "none"


def test_unknown_scene_lists_known(tmp_path):
    with pytest.raises(UserError, match="unknown scene 'nope'.*jumpingjacks"):
        load_scene_spec("nope")


@pytest.mark.parametrize(
    "old,new,pattern",
    [
        ("seed: 3", "seed: three", r"key 'seed' must be an integer"),
        ("seed: 3", "seed: 3\ncolour: red", r"key 'colour' is not a known key"),
        ("radius: 4.0", "radius: -4.0", r"key 'camera.radius'"),
        ("elevation_deg: [10, 60]", "elevation_deg: [10, 120]", r"key 'camera.elevation_deg'"),
        ("size: [0.3, 0.3, 0.3]", "size: [0.3, 0.3]", r"key 'objects\[1\].size' must be a list of 3"),
        ("roughness: 0.15", "roughness: 1.5", r"key 'objects\[1\].material.roughness'"),
        ("roughness: 0.15", "roughness: 0.15, metallic: 1", r"key 'objects\[1\].material.metallic' is not a known key"),
        ("primitive: sphere", "primitive: teapot", r"key 'objects\[1\].primitive' must be one of"),
        ("kind: bounce", "kind: moonwalk", r"key 'objects\[1\].motion.kind' must be one of"),
        ("{height: 0.5}", "{hieght: 0.5}", r"objects\[1\].motion.params'.hieght: not a parameter of motion 'bounce'"),
        ("{height: 0.5}", "{}", r"objects\[1\].motion.params'.height: required by motion 'bounce'"),
        ("{height: 0.5}", "{height: high}", r"objects\[1\].motion.params'.height: must be a finite number"),
        ("name: ball", "name: plate", r"key 'objects\[1\].name' duplicates"),
    ],
)
def test_bad_specs_name_file_and_key(tmp_path, old, new, pattern):
    assert old in MINIMAL
    with pytest.raises(UserError, match=pattern) as info:
        _load(tmp_path, MINIMAL.replace(old, new, 1))
    assert "toy.yaml" in str(info.value) and "\n" not in str(info.value)


def test_malformed_yaml_names_the_file_and_line(tmp_path):
    with pytest.raises(UserError, match=r"toy.yaml: malformed YAML at line \d+"):
        _load(tmp_path, MINIMAL.replace("seed: 3", "seed: [3"))


def test_rig_materials_must_match_template_groups(tmp_path):
    rig = MINIMAL + "\n".join(
        [
            "  - name: guy",
            "    primitive: rig",
            "    rig: humanoid",
            "    size: [1.2, 1.2, 1.2]",
            "    materials:",
            "      skin: {base_color: [0.7, 0.5, 0.4], roughness: 0.5}",
            "      shirt: {base_color: [0.7, 0.1, 0.1], roughness: 0.5}",
            "      pants: {base_color: [0.1, 0.1, 0.4], roughness: 0.5}",
            "      shoes: {base_color: [0.1, 0.1, 0.1], roughness: 0.2}",
            "    motion: {kind: jumping_jack}",
            "",
        ]
    )
    spec = _load(tmp_path, rig)
    assert spec.object("guy").motion.params["cycles"] == 3.0  # default filled in
    with pytest.raises(UserError, match=r"objects\[2\].materials.shoes' is required"):
        _load(tmp_path, rig.replace("      shoes: {base_color: [0.1, 0.1, 0.1], roughness: 0.2}\n", ""))
    with pytest.raises(UserError, match=r"objects\[2\].materials.hat' is not a known key"):
        _load(tmp_path, rig.replace("shoes:", "hat: {base_color: [0, 0, 0], roughness: 0.1}\n      shoes:"))
    with pytest.raises(UserError, match=r"objects\[2\].motion.kind'.*drives a 'quadruped' rig"):
        _load(tmp_path, rig.replace("kind: jumping_jack}", "kind: run_cycle, params: {points: [[0, 0, 0], [1, 0, 0]]}}"))
    with pytest.raises(UserError, match=r"objects\[2\].size' must be uniform"):
        _load(tmp_path, rig.replace("size: [1.2, 1.2, 1.2]", "size: [1.2, 1.0, 1.2]"))


def test_spec_hash_is_stable_and_content_sensitive(tmp_path):
    a = _load(tmp_path, MINIMAL)
    assert a.spec_hash() == _load(tmp_path, MINIMAL).spec_hash()
    # key order and number formatting do not matter
    reordered = MINIMAL.replace("seed: 3\nframes_full: 150", "frames_full: 150\nseed: 3").replace("radius: 4.0", "radius: 4")
    assert _load(tmp_path, reordered).spec_hash() == a.spec_hash()
    for old, new in [("seed: 3", "seed: 4"), ("height: 0.5", "height: 0.51"), ("roughness: 0.15", "roughness: 0.16")]:
        assert _load(tmp_path, MINIMAL.replace(old, new)).spec_hash() != a.spec_hash()
    assert len(a.spec_hash()) == 64
    # the same across processes (no dependence on Python's randomised str hashing)
    code = "from generator.spec import load_scene_spec; print(load_scene_spec('spheres').spec_hash())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == load_scene_spec("spheres").spec_hash()


def test_without_removes_objects_and_rejects_unknown_names():
    spec = load_scene_spec("spheres")
    fewer = spec.without("ball_red", "ball_blue")
    assert "ball_red" not in fewer.dynamic_object_names() and "ball_yellow" in fewer.dynamic_object_names()
    assert len(fewer.objects) == len(spec.objects) - 2
    assert fewer.spec_hash() != spec.spec_hash()
    assert spec.object("ball_red")  # the original is unchanged (frozen)
    with pytest.raises(UserError, match="no object 'ghost'"):
        spec.without("ghost")
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.seed = 5  # type: ignore[misc]


# ---------------------------------------------------------------------------------------------------- motion


def _params(name):
    for scene in REAL:
        for o in load_scene_spec(scene).objects:
            if o.motion is not None and o.motion.kind == name:
                return o.motion.params
    raise AssertionError(name)


def _flat(pose: motion.Pose) -> list[float]:
    vals = [*pose.location, *pose.rotation, *pose.root]
    for k in sorted(pose.bones):
        vals.extend(pose.bones[k])
    return vals


USED = ["bounce", "jumping_jack", "stand_up", "run_cycle", "crane_swing"]


@pytest.mark.parametrize("name", USED)
def test_motion_is_pure_continuous_and_moves(name):
    params = _params(name)
    ts = [i / 400 for i in range(401)]
    first = [_flat(motion.evaluate(name, t, params)) for t in ts]
    again = [_flat(motion.evaluate(name, t, params)) for t in reversed(ts)][::-1]
    assert first == again  # pure: no state, order does not matter
    for a, b in zip(first, first[1:]):
        assert max(abs(x - y) for x, y in zip(a, b)) < 0.12, f"{name}: jump between neighbouring times"
    span = max(abs(x - y) for x, y in zip(first[0], first[200]))
    assert span > 0.05, f"{name}: nothing moves between t=0 and t=0.5"
    assert all(math.isfinite(v) for row in first for v in row)


def test_motion_bones_exist_in_their_rig():
    for name in motion.available_motions():
        mdef = motion.get_motion(name)
        if mdef.rig is None:
            continue
        pose = motion.evaluate(name, 0.3, _params(name))
        assert set(pose.bones) <= set(TEMPLATES[mdef.rig].bone_names), name


def test_motion_defaults_match_the_humanoid_template():
    bones = {b.name: b for b in HUMANOID.bones}
    thigh = bones["thigh.L"]
    shin = bones["shin.L"]
    for name in ("jumping_jack", "stand_up"):
        d = motion.get_motion(name).params
        assert math.isclose(d["thigh_length"].default, math.dist(thigh.head, thigh.tail))
    d = motion.get_motion("stand_up").params
    assert math.isclose(d["shin_length"].default, math.dist(shin.head, shin.tail))
    assert math.isclose(d["hip_height"].default, thigh.head[2])
    assert math.isclose(d["ankle_height"].default, shin.tail[2])


def test_two_link_ik_reaches_the_target():
    l1, l2 = 0.24, 0.24
    for dx, dz in [(0.24, -0.2), (0.1, -0.4), (0.0, -0.47), (0.3, -0.1)]:
        hip, knee = motion._two_link_ik(dx, dz, l1, l2)
        # forward kinematics: angles from straight down, forward positive; shin bent back by knee
        kx, kz = l1 * math.sin(hip), -l1 * math.cos(hip)
        fx, fz = kx + l2 * math.sin(hip - knee), kz - l2 * math.cos(hip - knee)
        assert math.isclose(fx, dx, abs_tol=1e-9) and math.isclose(fz, dz, abs_tol=1e-9)
        assert knee >= 0


def test_unknown_motion_and_bad_params_raise_user_errors():
    with pytest.raises(UserError, match="unknown motion 'fly'"):
        motion.evaluate("fly", 0.0, {})
    with pytest.raises(UserError, match="points: required"):
        motion.evaluate("translate_path", 0.0, {})
    with pytest.raises(UserError, match=r"points\[1\]: must be a list of 3"):
        motion.evaluate("translate_path", 0.0, {"points": [[0, 0, 0], [1, 2]]})


def test_translate_path_endpoints_and_constant_speed():
    pts = [[0, 0, 0], [1, 0, 0], [1, 1, 0]]
    p = {"points": pts, "ease": 0, "face_path": 1}
    assert motion.evaluate("translate_path", 0.0, p).location == pytest.approx((0, 0, 0))
    assert motion.evaluate("translate_path", 1.0, p).location == pytest.approx((1, 1, 0))
    mid = motion.evaluate("translate_path", 0.5, p)
    assert mid.location == pytest.approx((1, 0, 0), abs=1e-9)
    assert motion.evaluate("translate_path", 0.25, p).rotation[2] == pytest.approx(0.0, abs=0.2)
    assert motion.evaluate("translate_path", 0.9, p).rotation[2] == pytest.approx(math.pi / 2, abs=0.2)


def test_bounce_touches_down_and_reaches_apex():
    p = {"height": 0.5, "bounces": 2, "phase": 0.0}
    zs = [motion.evaluate("bounce", i / 1000, p).location[2] for i in range(1001)]
    assert min(zs) == pytest.approx(0.0, abs=1e-12) and max(zs) == pytest.approx(0.5, abs=1e-4)
    assert zs[0] == pytest.approx(0.0) and zs[250] == pytest.approx(0.5)


def test_scenes_dir_has_only_yaml_specs():
    assert all(p.suffix == ".yaml" for p in SCENES_DIR.iterdir() if p.is_file())


def test_swing_is_a_sinusoid_about_the_given_axis():
    p = {"axis": [0, 0, 1], "amplitude_deg": 30.0, "cycles": 2.0}
    assert motion.evaluate("swing", 0.125, p).rotation == pytest.approx((0.0, 0.0, math.radians(30.0)))
    assert motion.evaluate("swing", 0.375, p).rotation == pytest.approx((0.0, 0.0, -math.radians(30.0)))
    assert motion.evaluate("swing", 0.5, p).rotation == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    # t is clamped to [0, 1]: the pose outside equals the pose at the ends
    assert motion.evaluate("swing", 1.7, p) == motion.evaluate("swing", 1.0, p)


def test_spheres_never_touch_each_other():
    """The balls hop in separate lanes: centre distances exceed the sum of radii at every time."""
    spec = load_scene_spec("spheres")
    balls = [o for o in spec.objects if o.dynamic]
    assert len(balls) == 4 and all(o.primitive == "sphere" for o in balls)
    for i in range(1001):
        t = i / 1000
        centres = {
            o.name: [a + b for a, b in zip(o.location, motion.evaluate(o.motion.kind, t, o.motion.params).location)]
            for o in balls
        }
        for a in range(len(balls)):
            for b in range(a + 1, len(balls)):
                gap = math.dist(centres[balls[a].name], centres[balls[b].name]) - (balls[a].size[0] + balls[b].size[0]) / 2
                assert gap > 0.02, f"{balls[a].name} and {balls[b].name} touch at t={t}"
