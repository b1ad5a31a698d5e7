"""The rendering pipeline: layout, ground truth, shadows, resume, determinism (generator/pipeline.py)."""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from generator import cameras, lights, motion, postprocess
from generator.envmap import read_envmap
from generator.pipeline import render_scene
from generator.spec import load_scene_spec
from lumibench import layout
from lumibench.io import read_image

REPO = Path(__file__).resolve().parent.parent
SHARED_ENVMAPS = REPO.parent / "shared" / "data" / "envmaps"
LIGHTS = lights.default_light_names()  # the default light set, in lights.yaml order (not city_sharp)


def _files(root: Path, scene: str) -> dict[Path, Path]:
    """Files of both variants of ``scene`` in a DATA/PROFILE tree (other tests may add files beside them),
    without bookkeeping (records and dataset.json hold timings)."""
    variants = [root / scene] + sorted(root.glob(f"{scene}_statictimestep*"))
    return {p.relative_to(root): p for v in variants for p in sorted(v.rglob("*"))
            if p.is_file() and ".frames" not in p.parts and p.name != "dataset.json"}


def assert_same_dataset(a: Path, b: Path, scene: str) -> None:
    """Every file of both variants byte-identical (bookkeeping with timings aside)."""
    fa, fb = _files(a, scene), _files(b, scene)
    assert len(fa) > 100
    assert sorted(fa) == sorted(fb)
    differ = [str(rel) for rel, pa in fa.items() if pa.read_bytes() != fb[rel].read_bytes()]
    assert not differ, f"{len(differ)} files differ, e.g. {differ[:5]}"


# ---- post-processing, no Blender ---------------------------------------------------------------------


def test_ground_truth_normalised_by_coverage():
    h = w = 2
    alpha = np.array([[1.0, 0.5], [0.25, 0.0]], np.float32)
    layers = {"Combined.A": alpha, "albedo.R": 0.6 * alpha, "albedo.G": 0.2 * alpha, "albedo.B": 0.1 * alpha,
              "roughness.X": 0.3 * alpha, "dynamic.X": np.array([[1.0, 0.5], [0.0, 0.0]], np.float32),
              "Normal.X": 0.0 * alpha, "Normal.Y": 0.6 * alpha, "Normal.Z": 0.8 * alpha}
    gt = postprocess.ground_truth_arrays(layers)
    fg = alpha > 0
    np.testing.assert_allclose(gt["albedo"][fg], np.tile([0.6, 0.2, 0.1], (3, 1)), rtol=1e-6)
    np.testing.assert_allclose(gt["roughness"][fg][:, 0], 0.3, rtol=1e-6)
    np.testing.assert_allclose(gt["normal"][fg], np.tile([0.0, 0.6, 0.8], (3, 1)), rtol=1e-6)
    assert np.all(gt["albedo"][~fg] == 0) and np.all(gt["normal"][~fg] == 0)
    # the dynamic mask keeps its coverage meaning
    np.testing.assert_allclose(gt["dynamic_mask"][..., 0], [[1.0, 0.5], [0.0, 0.0]])
    assert gt["albedo"].shape == (h, w, 3) and gt["roughness"].shape == (h, w, 1)


def test_npz_bytes_reproducible_and_readable(tmp_path):
    a = np.random.default_rng(0).random((5, 4, 3)).astype(np.float32)
    postprocess.write_npz(tmp_path / "a.npz", "albedo", a)
    time.sleep(1.1)  # numpy's own savez would stamp a different time now
    postprocess.write_npz(tmp_path / "b.npz", "albedo", a)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    np.testing.assert_array_equal(read_image(tmp_path / "a.npz"), a)
    assert zipfile.ZipFile(tmp_path / "a.npz").namelist() == ["albedo.npy"]


# ---- resume: which frames a run renders again (Blender replaced by a stand-in) ------------------------


@pytest.fixture
def stand_in_renderer(monkeypatch):
    """Replace the Blender frame renders by a writer of bytes that depend on the frame's key; the record is
    made by the same FrameJob.make_record the real renderer uses. Returns the list of rendered labels."""
    from generator import pipeline
    from lumibench.io import atomic_write_json

    rendered: list[str] = []

    def render_frames(run, pending, spec_hash, jobs, progress, on_rendered):
        for job in pending:
            key = json.dumps(job.key(spec_hash, run.settings), sort_keys=True)
            for p in job.outputs(run.settings.light_names):
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(f"{p.name} {key}".encode() * 4)
            atomic_write_json(job.record_path(), job.make_record(spec_hash, run.settings, seconds={"total": 0.0}))
            rendered.append(job.label)

    monkeypatch.setattr(pipeline, "_render_frames", render_frames)
    return rendered


def test_resume_re_renders_exactly_the_affected_frames(stand_in_renderer, tmp_path, monkeypatch):
    from generator import pipeline

    rendered = stand_in_renderer
    scene, static = "spheres", "spheres_statictimestep0000"

    def run(**kw):
        rendered.clear()
        kw.setdefault("frames", 3)
        kw.setdefault("lights", ["city", "sunset"])
        out = render_scene(scene, "ci", tmp_path, progress=False, test_views=1, **kw)
        assert layout.is_complete(out) and layout.is_complete(out.parent / static)
        return sorted(rendered)

    everything = [f"{scene}/test/r_0000", *(f"{scene}/train/r_000{i}" for i in range(3)),
                  *(f"{static}/train/r_000{i}" for i in (1, 2))]  # static train 0 and both test views: copies
    assert run() == everything
    assert run() == []
    record = json.loads((tmp_path / "ci" / scene / ".frames" / "train" / "r_0001.json").read_text())
    assert len(record["files"]) == 2 + 8 and all(len(f["sha256"]) == 64 for f in record["files"].values())
    # a truncated file (another size) and a changed byte (same size): those two frames only
    npz = layout.gt_path(tmp_path / "ci" / scene, "normal", "train/r_0001", ".npz")
    npz.write_bytes(npz.read_bytes()[:10])
    png = layout.lit_image_path(tmp_path / "ci" / static, "sunset", "train/r_0002")
    data = bytearray(png.read_bytes())
    data[5] ^= 1
    png.write_bytes(bytes(data))
    copy = layout.gt_path(tmp_path / "ci" / static, "albedo", "test/r_0000")  # a copied frame is copied again
    copy.write_bytes(b"")
    assert run() == [f"{scene}/train/r_0001", f"{static}/train/r_0002"]
    assert copy.read_bytes() == layout.gt_path(tmp_path / "ci" / scene, "albedo", "test/r_0000").read_bytes()
    # one more frame: the times of the dynamic frames 1 and 2 change, frame 0 (t = 0), the test view and the
    # static variant (all at t = 0, same cameras) do not
    assert run(frames=4) == [f"{scene}/train/r_0001", f"{scene}/train/r_0002", f"{scene}/train/r_0003",
                             f"{static}/train/r_0003"]
    assert run(frames=4) == []
    # a render setting (samples per pixel) changes every frame
    real = pipeline.load_profile

    def more_samples(name):
        prof = real(name)
        return dataclasses.replace(prof, dataset=dataclasses.replace(prof.dataset, spp=prof.dataset.spp + 1))

    all_renders = [f"{scene}/test/r_0000", *(f"{scene}/train/r_000{i}" for i in range(4)),
                   *(f"{static}/train/r_000{i}" for i in (1, 2, 3))]
    monkeypatch.setattr(pipeline, "load_profile", more_samples)
    assert run(frames=4) == all_renders
    monkeypatch.setattr(pipeline, "load_profile", real)
    assert run(frames=4) == all_renders  # and back
    # so do the light set and the scene spec
    spec = load_scene_spec(scene)
    assert run(frames=4, lights=["city"]) == all_renders
    assert run(frames=4, spec=spec.without(spec.dynamic_object_names()[0])) == all_renders
    assert run(frames=4) == all_renders and run(frames=4) == []


# ---- the rendered ci dataset -------------------------------------------------------------------------


@pytest.mark.slow
def test_ci_dataset_layout(ci_dataset, ci_profile):
    spec = load_scene_spec(ci_dataset.name)
    n = min(ci_profile.frames_for(spec.name), spec.frames_full)
    static = ci_dataset.parent / layout.static_scene_name(spec.name, ci_profile.static_timestep)
    t_static = ci_profile.static_timestep / (n - 1)
    for scene in (ci_dataset, static):
        assert layout.is_complete(scene), scene
        meta = json.loads((scene / "dataset.json").read_text())
        assert list(meta)[-1] == "complete" and meta["spec_hash"] == spec.spec_hash()
        assert meta["seed"] == spec.seed and meta["profile"]["name"] == "ci" and meta["blender_version"]
        assert [lt["name"] for lt in meta["lights"]] == LIGHTS
        train = layout.read_transforms(scene, "train")
        test = layout.read_transforms(scene, "test")
        assert len(train.frames) == n and len(test.frames) == ci_profile.test_views
        assert train.camera_angle_x == pytest.approx(spec.camera.camera_angle_x)
        assert [f.file_path for f in train.frames] == [f"train/r_{i:04d}" for i in range(n)]
        if scene == ci_dataset:
            times = [f.time for f in train.frames]
            assert times[0] == 0.0 and times[-1] == 1.0 and np.all(np.diff(times) > 0)
        else:
            assert all(f.time == pytest.approx(t_static) for f in train.frames)
        assert all(f.time == pytest.approx(t_static) for f in test.frames)
        assert len(meta["frame_seconds"]) == n + ci_profile.test_views
        for split, tr in (("train", train), ("test", test)):
            for f in tr.frames:
                for light in LIGHTS:
                    img = read_image(layout.lit_image_path(scene, light, f.file_path))
                    assert img.shape == (ci_profile.resolution, ci_profile.resolution, 4)
                for kind, ch in (("albedo", 3), ("roughness", 1), ("normal", 3), ("dynamic_mask", 1)):
                    assert layout.gt_path(scene, kind, f.file_path).is_file()
                    arr = read_image(layout.gt_path(scene, kind, f.file_path, ".npz"))
                    assert arr.shape == (ci_profile.resolution, ci_profile.resolution, ch), (kind, arr.shape)
        # the env maps written beside the scene are the 32 x 16 maps of lights.yaml (RGBE precision)
        for light in LIGHTS:
            written = read_envmap(layout.envmap_path(scene, light))
            expected = lights.prepare_envmap(lights.resolve_light(light))
            assert written.shape == (16, 32, 3)
            # RGBE: an 8-bit mantissa shared by the texel, so the error scales with its largest channel
            assert np.all(np.abs(written - expected) <= expected.max(-1, keepdims=True) / 128 + 1e-6)
            assert (scene / f"{light}.png").is_file()
    # the static variant's test split is the same set of images as the dynamic one's
    for rel in ("city/test/r_0000.png", "albedo/test/r_0001.npz", "sunset/train/r_0000.png"):
        assert (ci_dataset / rel).read_bytes() == (static / rel).read_bytes(), rel
    # no temporary or staging file survives a finished run
    assert not list(ci_dataset.parent.rglob(".tmp-*")) and not list(ci_dataset.parent.rglob("*.exr"))


@pytest.mark.slow
def test_ground_truth_matches_spec_materials(ci_dataset):
    """At the projected centre of the red ball (uniform material), GT = the spec's values, in linear space."""
    spec = load_scene_spec(ci_dataset.name)
    ball = spec.object("ball_red")
    tr = layout.read_transforms(ci_dataset, "train")
    hits = 0
    for f in tr.frames:
        pose = motion.evaluate(ball.motion.kind, f.time, ball.motion.params)
        centre = np.add(ball.location, pose.location)
        px, depth = cameras.project(centre[None], f.c2w, tr.camera_angle_x, 64, 64)
        x, y = np.floor(px[0]).astype(int)
        if not (0 <= x < 64 and 0 <= y < 64) or depth[0] <= 0:
            continue
        albedo = read_image(layout.gt_path(ci_dataset, "albedo", f.file_path, ".npz"))[y, x]
        if not np.allclose(albedo, ball.material.base_color, atol=1e-5):
            continue  # another ball in front of it
        hits += 1
        rough = read_image(layout.gt_path(ci_dataset, "roughness", f.file_path, ".npz"))[y, x, 0]
        dyn = read_image(layout.gt_path(ci_dataset, "dynamic_mask", f.file_path, ".npz"))[y, x, 0]
        normal = read_image(layout.gt_path(ci_dataset, "normal", f.file_path, ".npz"))[y, x]
        assert rough == pytest.approx(ball.material.roughness, abs=1e-5)
        assert dyn == pytest.approx(1.0)
        to_cam = f.c2w[:3, 3] - centre
        assert np.dot(normal, to_cam / np.linalg.norm(to_cam)) > 0.8  # world space, facing the camera
        assert np.linalg.norm(normal) == pytest.approx(1.0, abs=1e-5)
        # the 8-bit albedo PNG is the sRGB encoding of the linear value
        png = read_image(layout.gt_path(ci_dataset, "albedo", f.file_path))[y, x, :3]
        np.testing.assert_allclose(png, postprocess.srgb_encode(albedo), atol=1.0 / 255)
    assert hits >= len(tr.frames) // 2, f"red ball's albedo found in only {hits} frames"
    # a static receiver has mask 0
    plate_mask = [read_image(layout.gt_path(ci_dataset, "dynamic_mask", f.file_path, ".npz")) for f in tr.frames]
    assert min(float((m == 0).mean()) for m in plate_mask) > 0.5


@pytest.mark.slow
def test_lit_images_differ_across_lights_ground_truth_does_not(ci_dataset, tmp_path):
    """Lit images depend on the light; GT does not: a run under another light (a user .hdr file when the
    shared maps exist) reproduces the ci dataset's GT files and its lit image bytes exactly."""
    f = "train/r_0000"
    imgs = {lt: read_image(layout.lit_image_path(ci_dataset, lt, f)) for lt in LIGHTS}
    for i, a in enumerate(LIGHTS):
        for b in LIGHTS[i + 1:]:
            assert np.abs(imgs[a][..., :3] - imgs[b][..., :3]).mean() > 0.02, (a, b)
            np.testing.assert_array_equal(imgs[a][..., 3], imgs[b][..., 3])  # same coverage
    user = sorted(SHARED_ENVMAPS.glob("*.hdr"))[:1]
    light_args = [str(user[0]), "sunset"] if user else ["sunset"]
    other = render_scene(ci_dataset.name, "ci", tmp_path, jobs=1, lights=light_args, progress=False,
                         frames=2, test_views=1)  # camera 0 at time 0 is the same as in the 16-frame run
    for kind in layout.GT_KINDS:  # rendered once per frame, whatever the light set: the same bytes
        for ext in (".npz", ".png"):
            assert layout.gt_path(other, kind, f, ext).read_bytes() == \
                layout.gt_path(ci_dataset, kind, f, ext).read_bytes(), (kind, ext)
    assert layout.lit_image_path(other, "sunset", f).read_bytes() == \
        layout.lit_image_path(ci_dataset, "sunset", f).read_bytes()
    if user:
        name = user[0].stem
        assert read_envmap(layout.envmap_path(other, name)).shape == (16, 32, 3)
        assert np.abs(read_image(layout.lit_image_path(other, name, f))[..., :3] - imgs["sunset"][..., :3]).mean() > 0.01


@pytest.mark.slow
def test_cast_shadow_on_receivers(ci_dataset, tmp_path):
    """Under the sunny light, receiver pixels are darker with the moving balls present than with them removed
    (SceneSpec.without), far more often than sampling noise makes them brighter."""
    spec = load_scene_spec(ci_dataset.name)
    bare = spec.without(*spec.dynamic_object_names())
    n = 4  # cameras 0..3 are the ci run's (the camera sequence does not depend on the frame count)
    out = render_scene(spec.name, "ci", tmp_path, jobs=1, lights=["city"], progress=False, spec=bare,
                       frames=n, test_views=1)
    darker = brighter = 0
    ratios = []
    for i in range(n):
        f = f"train/r_{i:04d}"
        with_balls = read_image(layout.lit_image_path(ci_dataset, "city", f))
        without = read_image(layout.lit_image_path(out, "city", f))
        dyn = read_image(layout.gt_path(ci_dataset, "dynamic_mask", f, ".npz"))[..., 0]
        receiver = (dyn == 0) & (with_balls[..., 3] == 1.0) & (without[..., 3] == 1.0)
        ratio = with_balls[..., :3].mean(-1)[receiver] / np.maximum(without[..., :3].mean(-1)[receiver], 1e-3)
        darker += int((ratio < 0.7).sum())
        brighter += int((ratio > 1 / 0.7).sum())
        ratios.append(ratio)
    ratios = np.concatenate(ratios)
    assert darker >= 10 and darker >= 4 * brighter, (darker, brighter, float(ratios.min()))
    assert np.median(ratios) == pytest.approx(1.0, abs=0.05)  # the rest of the receivers is unchanged


@pytest.mark.slow
def test_deleted_frame_is_the_only_one_rendered_again(ci_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(ci_dataset.parent.parent, data)
    scene = data / "ci" / ci_dataset.name
    victim = layout.lit_image_path(scene, "courtyard", "train/r_0003")
    victim.unlink()
    static_copy = scene.parent / f"{scene.name}_statictimestep0000" / "albedo" / "test" / "r_0001.png"
    static_copy.unlink()  # a copied frame is copied again, not rendered
    truncated = layout.gt_path(scene, "normal", "train/r_0005", ".npz")  # listed in its record, cut afterwards
    truncated.write_bytes(truncated.read_bytes()[:100])
    record = json.loads((scene / ".frames" / "train" / "r_0005.json").read_text())
    assert record["files"]["normal/train/r_0005.npz"]["size"] > 100  # the real renderer records sizes and hashes
    rendered = []
    render_scene(scene.name, "ci", data, jobs=1, progress=False, on_rendered=lambda job, rec: rendered.append(job.label))
    assert sorted(rendered) == [f"{scene.name}/train/r_0003", f"{scene.name}/train/r_0005"]
    assert victim.read_bytes() == (ci_dataset / victim.relative_to(scene)).read_bytes()  # rendered again: same bytes
    assert truncated.read_bytes() == (ci_dataset / truncated.relative_to(scene)).read_bytes()
    assert_same_dataset(data / "ci", ci_dataset.parent, ci_dataset.name)
    assert layout.is_complete(scene)
    # nothing left to do: a second run renders nothing
    rendered.clear()
    render_scene(scene.name, "ci", data, jobs=1, progress=False, on_rendered=lambda job, rec: rendered.append(job.label))
    assert rendered == []


@pytest.mark.slow
def test_killed_run_resumes_to_identical_files(ci_dataset, tmp_path):
    data = tmp_path / "data"
    cmd = [sys.executable, "-m", "generator", "dataset", "--profile", "ci", "--scenes", ci_dataset.name,
           "--data", str(data), "--jobs", "1", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    records = data / "ci" / ci_dataset.name / ".frames" / "train"
    deadline = time.time() + 120
    def finished_records():  # a kill during a record's atomic write leaves a .tmp-*.json beside them
        return sorted(p for p in records.glob("*.json") if not p.name.startswith("."))

    while time.time() < deadline and len(finished_records()) < 5 and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    scene = data / "ci" / ci_dataset.name
    assert not layout.is_complete(scene)
    done = finished_records()
    assert 5 <= len(done) < 16
    for rec in done:  # a frame with a record has all its files; the frame in flight has no record
        f = f"train/{rec.stem}"
        assert all(layout.lit_image_path(scene, lt, f).is_file() for lt in LIGHTS)
        assert all(layout.gt_path(scene, k, f, ext).is_file() for k in layout.GT_KINDS for ext in (".png", ".npz"))
    rerun = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert layout.is_complete(scene)
    assert_same_dataset(data / "ci", ci_dataset.parent, ci_dataset.name)
