"""The Blender scene builder: posed geometry stays in the scene box, on (not in) its receivers, really moves,
moves continuously, and materials carry the ground-truth AOVs that Cycles actually renders.

Geometry checks use exact world-space vertices of the rigid (bone-parented or plain) meshes.
"""
from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from generator.blender.build import (  # noqa: E402
    AOV_ALBEDO, AOV_DYNAMIC, AOV_ROUGHNESS, build_scene, reset_blender, world_vertices)
from generator.blender.materials import MOVING_PROPERTY  # noqa: E402
from generator.spec import SCENE_BOX, available_scenes, load_scene_spec  # noqa: E402

REAL_SCENES = ["hook", "jumpingjacks", "mouse", "spheres", "standup"]
TIMES = np.linspace(0.0, 1.0, 21)
TOL = 0.012  # world units: contact, not interpenetration


def _local_box(ob):
    """World->local matrix and the half extents of a static object's own (local) bounding box."""
    corners = np.array([list(c) for c in ob.bound_box])
    lo, hi = corners.min(0), corners.max(0)
    return np.linalg.inv(np.array(ob.matrix_world)), lo, hi


@pytest.fixture(scope="module", params=REAL_SCENES)
def built(request):
    spec = load_scene_spec(request.param)
    scene = reset_blender()
    return build_scene(scene, spec)


def test_all_real_scenes_listed():
    assert set(REAL_SCENES) <= set(available_scenes())


@pytest.mark.slow
def test_dynamic_objects_stay_in_box_and_on_receivers(built):
    spec = built.spec
    statics = [(_local_box(ob), ob.name) for ob in built.static_objects]
    plate_top = max(v[:, 2].max() for v in [world_vertices([built.objects["plate"]])])
    assert built.dynamic_objects, "a real scene needs moving objects"
    for t in TIMES:
        built.set_time(float(t))
        v = world_vertices(built.dynamic_objects)
        assert np.all(np.abs(v) <= SCENE_BOX + 1e-6), f"{spec.name} t={t}: outside the scene box, max {np.abs(v).max(0)}"
        assert v[:, 2].min() >= plate_top - TOL, f"{spec.name} t={t}: below the plate by {plate_top - v[:, 2].min():.4f}"
        for (w2l, lo, hi), name in statics:
            local = v @ w2l[:3, :3].T + w2l[:3, 3]
            inside = np.all((local > lo + TOL) & (local < hi - TOL), axis=1)
            assert not inside.any(), f"{spec.name} t={t}: {inside.sum()} moving vertices inside static '{name}'"


@pytest.mark.slow
def test_static_objects_in_box(built):
    v = world_vertices(built.static_objects)
    assert np.all(np.abs(v) <= SCENE_BOX + 1e-6)
    assert -0.6 - 1e-5 <= v[:, 2].min() <= -0.4  # the ground plate near z = -0.5


@pytest.mark.slow
def test_motion_moves_and_is_continuous_and_repeatable(built):
    built.set_time(0.0)
    v0 = world_vertices(built.dynamic_objects)
    built.set_time(0.5)
    v5 = world_vertices(built.dynamic_objects)
    assert np.linalg.norm(v5 - v0, axis=1).max() > 0.1, "dynamic objects barely move between t=0 and t=0.5"
    for t in (0.0, 0.31, 0.77, 1.0 - 1e-4):
        built.set_time(t)
        a = world_vertices(built.dynamic_objects)
        built.set_time(t + 1e-4)
        b = world_vertices(built.dynamic_objects)
        built.set_time(t + 1e-5)
        c = world_vertices(built.dynamic_objects)
        far, near = np.linalg.norm(b - a, axis=1).max(), np.linalg.norm(c - a, axis=1).max()
        # continuous: a 10x smaller step moves parts ~10x less (a jump would not shrink), and speeds are sane
        assert far < 5e-3, f"{built.spec.name}: moves {far} in dt=1e-4 near t={t}"
        assert near < 0.3 * far + 1e-6, f"{built.spec.name}: discontinuity near t={t} ({near} vs {far})"
    built.set_time(0.31)
    again = world_vertices(built.dynamic_objects)
    built.set_time(0.77)
    built.set_time(0.31)
    assert np.array_equal(again, world_vertices(built.dynamic_objects)), "set_time must not depend on history"
    statics0 = world_vertices(built.static_objects)
    built.set_time(0.9)
    assert np.array_equal(statics0, world_vertices(built.static_objects)), "static objects must not move"


@pytest.mark.slow
def test_materials_wire_aovs_to_the_bsdf_inputs(built):
    names = {a.name for a in bpy.context.view_layer.aovs}
    assert {AOV_ALBEDO, AOV_ROUGHNESS, AOV_DYNAMIC} <= names
    dyn_meshes = {ob.name for ob in built.dynamic_objects}
    for ob in built.dynamic_objects + built.static_objects:
        mat = ob.data.materials[0]
        nodes = mat.node_tree.nodes
        bsdfs = [n for n in nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"]
        assert len(bsdfs) == 1
        bsdf = bsdfs[0]
        assert bsdf.inputs["Metallic"].default_value == 0.0
        aovs = {n.aov_name: n for n in nodes if n.bl_idname == "ShaderNodeOutputAOV"}
        assert set(aovs) == {AOV_ALBEDO, AOV_ROUGHNESS, AOV_DYNAMIC}
        # the AOV reads the very socket the BSDF reads
        assert aovs[AOV_ALBEDO].inputs["Color"].links[0].from_socket == bsdf.inputs["Base Color"].links[0].from_socket
        assert aovs[AOV_ROUGHNESS].inputs["Value"].links[0].from_socket == bsdf.inputs["Roughness"].links[0].from_socket
        dyn = aovs[AOV_DYNAMIC].inputs["Value"]
        if ob.name in dyn_meshes:  # each part of a moving object says whether it moves (its object property)
            node = dyn.links[0].from_node
            assert (node.bl_idname, node.attribute_type, node.attribute_name) == (
                "ShaderNodeAttribute", "OBJECT", MOVING_PROPERTY)
        else:
            assert not dyn.is_linked and dyn.default_value == 0.0


@pytest.mark.slow
def test_the_parts_marked_moving_are_those_that_move(built):
    """Brute force on the test's own time grid: a part is marked moving exactly when one of its vertices
    leaves its t = 0 position; among the five scenes only standup's planted feet never move."""
    built.set_time(0.0)
    start = {ob.name: world_vertices([ob]) for ob in built.dynamic_objects}
    most = dict.fromkeys(start, 0.0)
    for t in TIMES[1:]:
        built.set_time(float(t))
        for ob in built.dynamic_objects:
            most[ob.name] = max(most[ob.name], float(np.abs(world_vertices([ob]) - start[ob.name]).max()))
    built.set_time(0.0)
    for ob in built.dynamic_objects:
        assert ob[MOVING_PROPERTY] == (1.0 if most[ob.name] > 1e-4 else 0.0), (ob.name, most[ob.name])
    for ob in built.static_objects:
        assert ob[MOVING_PROPERTY] == 0.0
    still = sorted(n for n, d in most.items() if d <= 1e-4)
    assert still == (["person.foot.L", "person.foot.R"] if built.spec.name == "standup" else [])


def _render_aovs(scene, path, res=24, spp=2):
    """Tiny Cycles render to a multilayer EXR; return {pass name: H x W x C float array}."""
    import OpenEXR

    from generator.blender import cycles as bcyc

    bcyc.configure(scene, resolution=res, spp=spp, seed=0)
    bcyc.set_exr_output(scene, multilayer=True)
    bcyc.render_still(scene, path)
    passes = {}
    with OpenEXR.File(str(path)) as f:
        for part in f.parts:
            for name, ch in part.channels.items():
                arr = np.asarray(ch.pixels, dtype=np.float32)
                # "ViewLayer.albedo" (H x W x 3) or "ViewLayer.dynamic.X" (H x W)
                pieces = name.split(".")
                key = pieces[1] if len(pieces) > 1 else pieces[0]
                passes[key] = arr if arr.ndim == 3 else arr[..., None]
    return passes


@pytest.mark.slow
def test_cycles_renders_the_aovs_with_exact_values(tmp_path):
    """calib_sphere: the AOVs at fully covered pixels are the spec's base colour and roughness, dynamic 0;
    spheres: the dynamic AOV is 1 on the balls and 0 on the plate."""
    from generator.blender import camera as bcam
    from generator.cameras import look_at

    spec = load_scene_spec("calib_sphere")
    scene = reset_blender()
    build_scene(scene, spec)
    bcam.set_camera(scene, look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.0)), spec.camera.camera_angle_x)
    ch = _render_aovs(scene, tmp_path / "calib.exr")
    assert {AOV_ALBEDO, AOV_ROUGHNESS, AOV_DYNAMIC, "Combined"} <= set(ch), sorted(ch)
    alpha = ch["Combined"][..., 3]
    albedo = ch[AOV_ALBEDO][..., :3]
    rough = ch[AOV_ROUGHNESS][..., 0]
    dyn = ch[AOV_DYNAMIC][..., 0]
    c = albedo.shape[0] // 2
    core = (slice(c - 2, c + 2), slice(c - 2, c + 2))
    mat = spec.object("sphere").material
    np.testing.assert_allclose(albedo[core].reshape(-1, 3), np.tile(mat.base_color, (16, 1)), atol=1e-5)
    np.testing.assert_allclose(rough[core], mat.roughness, atol=1e-5)
    assert np.all(dyn == 0.0)
    assert albedo[0, 0].max() == 0.0  # background: no surface, no AOV
    assert alpha[core].min() > 0.999 and alpha[0, 0] == 0.0

    spec = load_scene_spec("spheres")
    scene = reset_blender()
    built = build_scene(scene, spec)
    built.set_time(0.0)
    bcam.set_camera(scene, look_at((0.0, -0.01, 4.2), (0.0, 0.0, -0.3)), spec.camera.camera_angle_x)
    ch = _render_aovs(scene, tmp_path / "spheres.exr", res=48)
    dyn = ch[AOV_DYNAMIC][..., 0]
    assert (dyn > 0.99).sum() >= 20, "balls should cover pixels of the dynamic mask"
    assert (dyn == 0.0).sum() >= 0.5 * dyn.size, "the plate is static"
    assert dyn.min() >= 0.0 and dyn.max() <= 1.0 + 1e-6


@pytest.mark.slow
def test_the_dynamic_aov_is_zero_on_the_parts_of_a_moving_figure_that_never_move(tmp_path):
    """standup: the figure's planted feet (shoes) render 0 in the dynamic AOV, its legs, arms and shirt 1."""
    from generator.blender import camera as bcam
    from generator.cameras import look_at

    spec = load_scene_spec("standup")
    scene = reset_blender()
    build_scene(scene, spec).set_time(0.0)
    bcam.set_camera(scene, look_at((0.3, -2.2, 0.2), (0.0, 0.2, -0.45)), spec.camera.camera_angle_x)
    ch = _render_aovs(scene, tmp_path / "standup.exr", res=48)
    dyn, albedo = ch[AOV_DYNAMIC][..., 0], ch[AOV_ALBEDO][..., :3]
    for group, expected in (("shoes", 0.0), ("pants", 1.0), ("skin", 1.0), ("shirt", 1.0)):
        on = np.all(np.abs(albedo - np.array(spec.object("person").materials[group].base_color)) < 1e-4, -1)
        assert on.sum() >= 10, f"{group}: too few pixels in view ({on.sum()})"
        np.testing.assert_array_equal(dyn[on], expected, err_msg=group)


@pytest.mark.slow
def test_scene_in_frame_from_cameras_over_the_spec_hemisphere(built):
    """Every vertex, static or moving, at any time projects inside the image for cameras spread over the
    spec's elevation band at the spec's radius (the cameras the dataset uses)."""
    from generator.cameras import project, train_cameras

    spec = built.spec
    pts = []
    for t in np.linspace(0.0, 1.0, 6):
        built.set_time(float(t))
        pts.append(world_vertices(built.dynamic_objects + built.static_objects))
    pts = np.concatenate(pts)
    cams = train_cameras(32, spec.camera.radius, spec.camera.target, spec.camera.elevation_deg, seed=spec.seed)
    for c2w in cams:
        px, depth = project(pts, c2w, spec.camera.camera_angle_x, 100, 100)
        assert depth.min() > 0.5
        assert np.all((px >= 0.0) & (px <= 100.0)), f"{spec.name}: part of the scene leaves the frame ({px.min(0)}, {px.max(0)})"
