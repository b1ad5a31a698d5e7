"""Blender agrees with our conventions: what Cycles renders is where/what our numpy code predicts.

(1) camera: emissive markers at known 3D points land, in the rendered image, on the pixel coordinates
    generator.cameras.project() gives for the written c2w and camera_angle_x;
(2) env map: the background Cycles shows along a direction d is the texel that
    generator.envmap.direction_to_uv(d) selects, with the value read_envmap() reads from the file.
Tiny renders (<= 48 px, few samples); linear EXR output so no view transform is involved.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from generator.blender import camera as bcam  # noqa: E402
from generator.blender import cycles as bcyc  # noqa: E402
from generator.blender import world as bworld  # noqa: E402
from generator.cameras import look_at, project  # noqa: E402
from generator.envmap import direction_to_uv, read_envmap, texel_directions, texel_of_direction, write_hdr  # noqa: E402
from lumibench.io import read_image  # noqa: E402

pytestmark = pytest.mark.slow


def _fresh_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def _emissive_sphere(name, location, radius, rgb):
    mesh = bpy.data.meshes.new(name)
    import bmesh

    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=radius)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender 5 always gives materials a node tree
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.clear()
    em = nodes.new("ShaderNodeEmission")
    em.inputs["Color"].default_value = (*rgb, 1.0)
    em.inputs["Strength"].default_value = 4.0
    out = nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(em.outputs["Emission"], out.inputs["Surface"])
    mesh.materials.append(mat)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _centroid(weights):
    ys, xs = np.mgrid[0:weights.shape[0], 0:weights.shape[1]]
    total = weights.sum()
    return np.array([(weights * (xs + 0.5)).sum() / total, (weights * (ys + 0.5)).sum() / total])


def test_camera_markers_land_where_project_says(tmp_path):
    scene = _fresh_scene()
    res, angle = 40, 0.6
    bcyc.configure(scene, resolution=res, spp=8, seed=0, threads=2)
    scene.cycles.use_denoising = False
    scene.render.film_transparent = False  # black world, markers only
    bcyc.set_exr_output(scene)
    points = np.array([[0.0, 0.0, 0.0], [0.6, 0.55, 0.3], [-0.45, -0.5, 0.4]])  # apart in both views
    colours = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    for i, (p, c) in enumerate(zip(points, colours)):
        _emissive_sphere(f"marker{i}", p, 0.07, c)
    poses = [look_at((3.2, -2.1, 1.7), (0.1, 0.05, 0.0)), look_at((-1.5, 2.8, 2.5), (-0.1, 0.0, 0.1))]
    errors = []
    for k, c2w in enumerate(poses):
        bcam.set_camera(scene, c2w, angle)
        img = read_image(bcyc.render_still(scene, tmp_path / f"cam{k}.exr"))
        expected, depth = project(points, c2w, angle, res, res)
        assert np.all(depth > 0)
        for ch in range(3):
            w = np.clip(img[..., ch], 0.0, None)
            assert w.sum() > 0.5, f"marker {ch} not visible in render {k}"
            got = _centroid(w)
            err = np.linalg.norm(got - expected[ch])
            errors.append(err)
            assert err < 0.35, f"pose {k} marker {ch}: rendered at {got}, project() says {expected[ch]}"
    # the off-centre markers really are off-centre (the test is not trivially satisfied at the centre)
    assert np.abs(expected[1:] - res / 2).max() > 5
    print(f"marker centroid errors (px): {np.round(errors, 3).tolist()}")


def test_project_matches_blender_world_to_camera_view():
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    scene = _fresh_scene()
    bcyc.configure(scene, resolution=48, spp=1, seed=0)
    c2w = look_at((2.0, 3.0, 1.0), (0.2, -0.1, 0.3))
    obj = bcam.set_camera(scene, c2w, 0.8)
    pts = np.random.default_rng(1).normal(0.0, 0.5, (20, 3))
    ours, depth = project(pts, c2w, 0.8, 48, 48)
    theirs = np.array([tuple(world_to_camera_view(scene, obj, Vector(p))) for p in pts])
    # Blender: x right, y up in [0, 1] over the frame, z = depth
    np.testing.assert_allclose(ours[:, 0], theirs[:, 0] * 48, atol=1e-3)
    np.testing.assert_allclose(ours[:, 1], (1.0 - theirs[:, 1]) * 48, atol=1e-3)
    np.testing.assert_allclose(depth, theirs[:, 2], atol=1e-5)


def _distinct_map(h=16, w=32):
    """Every texel a different colour, all channels in (0.05, 1.0]."""
    r, c = np.mgrid[0:h, 0:w]
    return np.stack([(c + 1) / w, (r + 1) / h, 0.05 + ((r * 7 + c * 3) % 19) / 19.0], axis=-1).astype(np.float32)


@pytest.fixture(scope="module")
def env_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("env") / "distinct.hdr"
    write_hdr(path, _distinct_map())
    return path


@pytest.fixture(scope="module")
def fine_env_file(tmp_path_factory):
    """A 128 x 64 map (a light with its own resolution, e.g. city_sharp), every texel distinct."""
    path = tmp_path_factory.mktemp("env_fine") / "distinct_fine.hdr"
    write_hdr(path, _distinct_map(64, 128))
    return path


@pytest.mark.parametrize("size", [(16, 32), (64, 128)])
def test_world_background_along_directions_is_the_selected_texel(tmp_path, env_file, fine_env_file, size):
    """The world shows, along each texel's centre direction, that texel: the 'Closest' lookup of
    direction_to_uv at the default 32 x 16 and at a finer map's own size (128 x 64)."""
    h, w = size
    path = env_file if size == (16, 32) else fine_env_file
    scene = _fresh_scene()
    bcyc.configure(scene, resolution=8, spp=2, seed=0, threads=2)
    scene.render.film_transparent = False
    bcyc.set_exr_output(scene)
    bworld.set_environment(scene, path, strength=1.0)
    assert bworld.environment_width(scene.world) == w
    env = read_envmap(path)
    assert env.shape == (h, w, 3)
    centres = texel_directions(h, w)
    k = h // 16  # the same places on the sphere at either size, plus texels only the fine map has
    picks = [(0, 0), (2 * k, 5 * k), (4 * k, 16 * k), (7 * k, 8 * k), (8 * k, 23 * k), (3 * k, 30 * k),
             (6 * k, 31 * k), (1 * k, 12 * k), (h - 1, w - 1), (h // 2 - 1, w // 2 + 1)]
    for i, (row, col) in enumerate(picks):
        d = centres[row, col]
        # a view narrow enough to stay inside the texel (at the fine map's pole row a texel is 0.07 deg wide)
        bcam.set_camera(scene, look_at((0.0, 0.0, 0.0), d), math.radians(1.0 if k == 1 else 0.02))
        img = read_image(bcyc.render_still(scene, tmp_path / f"dir{i}.exr"))[..., :3]
        r_sel, c_sel = texel_of_direction(d, h, w)
        assert (int(r_sel), int(c_sel)) == (row, col)
        np.testing.assert_allclose(img.reshape(-1, 3), np.broadcast_to(env[row, col], (64, 3)), rtol=1e-5,
                                   err_msg=f"direction {d} (u, v = {direction_to_uv(d)})")


def test_world_background_wide_view_matches_direction_to_uv(tmp_path, env_file):
    """Every pixel of a wide view (pixel-centre rays) shows the texel direction_to_uv picks."""
    scene = _fresh_scene()
    res, angle = 48, math.radians(100.0)
    bcyc.configure(scene, resolution=res, spp=1, seed=0, threads=2)
    scene.render.film_transparent = False
    scene.cycles.filter_width = 0.01  # sample at the pixel centres
    bcyc.set_exr_output(scene)
    bworld.set_environment(scene, env_file)
    env = read_envmap(env_file)
    checked = 0
    for k, (eye, tgt) in enumerate([((0, 0, 0), (1.0, 0.6, 0.5)), ((0, 0, 0), (-0.7, -0.9, -0.3))]):
        c2w = look_at(eye, tgt)
        bcam.set_camera(scene, c2w, angle)
        img = read_image(bcyc.render_still(scene, tmp_path / f"wide{k}.exr"))[..., :3]
        f = 0.5 * res / math.tan(angle / 2)
        ys, xs = np.mgrid[0:res, 0:res] + 0.5
        cam = np.stack([(xs - res / 2) / f, -(ys - res / 2) / f, -np.ones_like(xs)], axis=-1)
        dirs = cam @ c2w[:3, :3].T
        u, v = direction_to_uv(dirs)
        # skip rays within a small margin of a texel boundary (sampling jitter of float precision)
        fu, fv = (u * 32) % 1.0, (v * 16) % 1.0
        safe = (np.minimum(fu, 1 - fu) > 0.02) & (np.minimum(fv, 1 - fv) > 0.02)
        rows, cols = texel_of_direction(dirs, 16, 32)
        expected = env[rows, cols]
        np.testing.assert_allclose(img[safe], expected[safe], rtol=1e-5)
        checked += int(safe.sum())
    assert checked > 0.8 * 2 * res * res


def test_render_still_is_atomic_and_png_rgba(tmp_path, env_file):
    scene = _fresh_scene()
    bcyc.configure(scene, resolution=16, spp=1, seed=3)
    assert scene.cycles.samples == 1 and not scene.cycles.use_denoising and scene.render.film_transparent
    assert scene.view_settings.view_transform == "Standard" and scene.cycles.seed == 3
    bcyc.configure(scene, resolution=16, spp=16, seed=3)
    assert scene.cycles.use_denoising and scene.cycles.denoiser == "OPENIMAGEDENOISE"
    bcyc.configure(scene, resolution=16, spp=1, seed=3)
    bworld.set_environment(scene, env_file)
    bcam.set_camera(scene, look_at((2, 0, 0), (0, 0, 0)), 0.7)
    out = bcyc.render_still(scene, tmp_path / "sub" / "r_0000.png")
    img = read_image(out)
    assert img.shape == (16, 16, 4)
    assert np.all(img[..., 3] == 0.0)  # film transparent, nothing in the scene: zero coverage
    assert sorted(p.name for p in out.parent.iterdir()) == ["r_0000.png"]
    bcyc.set_exr_output(scene, multilayer=True)
    ml = bcyc.render_still(scene, tmp_path / "sub" / "r_0000.gt.exr")
    import OpenEXR

    with OpenEXR.File(str(ml)) as f:
        names = list(f.channels())
    assert any(n.endswith("Combined.R") or n.endswith("Combined") for n in names), names
    assert sorted(p.name for p in out.parent.iterdir()) == ["r_0000.gt.exr", "r_0000.png"]


def test_world_radiance_units_lambertian_plane(tmp_path):
    """A white Lambertian plane facing +Z, lit by a prepared default light, shows albedo * E / pi with
    E = sum over texels of L * (exact cosine-weighted solid angle of the upper-hemisphere part): the file's
    values are radiance at world strength 1, in the mapping direction_to_uv defines."""
    from generator.lights import prepare_envmap, resolve_light

    env = prepare_envmap(resolve_light("courtyard"))
    path = tmp_path / "courtyard.hdr"
    write_hdr(path, env)
    env = read_envmap(path)
    theta = np.linspace(0.0, math.pi / 2, 9)  # the 8 upper rows
    cos_w = (np.sin(theta[1:]) ** 2 - np.sin(theta[:-1]) ** 2) / 2 * (2 * math.pi / 32)
    expected = 0.8 * (env[:8] * cos_w[:, None, None]).sum(axis=(0, 1)) / math.pi

    scene = _fresh_scene()
    bcyc.configure(scene, resolution=16, spp=64, seed=0, threads=2)
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0  # direct light only: nothing else in the scene to bounce from
    bcyc.set_exr_output(scene)
    bworld.set_environment(scene, path)
    bpy.ops.mesh.primitive_plane_add(size=200.0)
    mat = bpy.data.materials.new("white")
    if mat.node_tree is None:
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.clear()
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (0.8, 0.8, 0.8, 1.0)
    out = nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(diffuse.outputs["BSDF"], out.inputs["Surface"])
    bpy.context.active_object.data.materials.append(mat)
    bcam.set_camera(scene, look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)), 0.5)
    img = read_image(bcyc.render_still(scene, tmp_path / "plane.exr"))[..., :3]
    print("plane radiance", img.reshape(-1, 3).mean(axis=0), "expected", expected)
    np.testing.assert_allclose(img.reshape(-1, 3).mean(axis=0), expected, rtol=0.01)


def test_fixed_seed_renders_identical_bytes(tmp_path, env_file):
    """Same settings and seed -> byte-identical PNGs (denoised); another seed -> different noise."""
    outs = []
    for k, seed in enumerate([5, 5, 6]):
        scene = _fresh_scene()
        bcyc.configure(scene, resolution=16, spp=12, seed=seed, threads=2)
        bworld.set_environment(scene, env_file)
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5)
        bcam.set_camera(scene, look_at((2.0, -1.0, 1.0), (0.0, 0.0, 0.0)), 0.8)
        outs.append(bcyc.render_still(scene, tmp_path / f"s{k}.png").read_bytes())
    assert outs[0] == outs[1]
    assert outs[0] != outs[2]
