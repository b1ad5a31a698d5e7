"""Camera poses and projection against brute-force pinhole geometry."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from generator.cameras import (camera_directions, intrinsics, look_at, project, test_cameras as make_test_cameras,
                               train_cameras, transforms_dict)
from lumibench.layout import read_transforms


def test_look_at_is_orthonormal_and_looks_at_the_target():
    rng = np.random.default_rng(0)
    for _ in range(50):
        eye, target = rng.normal(0, 3, 3), rng.normal(0, 1, 3)
        c2w = look_at(eye, target)
        R = c2w[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(c2w[3], [0, 0, 0, 1])
        fwd = (target - eye) / np.linalg.norm(target - eye)
        np.testing.assert_allclose(-R[:, 2], fwd, atol=1e-12)  # looks down its -Z
        assert R[2, 0] == pytest.approx(0.0, abs=1e-12)  # no roll: camera x stays horizontal
        assert R[2, 1] >= -1e-12  # camera up points to world +Z side
        px, depth = project(target[None], c2w, 0.7, 64, 48)
        np.testing.assert_allclose(px[0], [32.0, 24.0], atol=1e-9)
        assert depth[0] == pytest.approx(np.linalg.norm(target - eye))


def test_look_at_straight_down_is_defined():
    c2w = look_at((0, 0, 5), (0, 0, 0))
    np.testing.assert_allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 2], [0, 0, 1], atol=1e-12)
    with pytest.raises(ValueError):
        look_at((1, 1, 1), (1, 1, 1))


def test_project_matches_brute_force_pinhole():
    rng = np.random.default_rng(1)
    w, h, angle = 80, 60, 0.9
    c2w = look_at((2.5, -1.0, 1.5), (0.0, 0.2, 0.1))
    pts = rng.normal(0, 0.6, (200, 3))
    px, depth = project(pts, c2w, angle, w, h)
    # brute force: pixel grid of the image plane at distance 1 in camera space, ray per point
    right, up, back, eye = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3]
    half_w = math.tan(angle / 2)
    pixel = 2 * half_w / w  # side of a pixel on the plane at distance 1 (square pixels)
    for p, (x, y), d in zip(pts, px, depth):
        v = p - eye
        dist = -v @ back
        assert d == pytest.approx(dist)
        on_plane = v / dist  # hits the plane z = -1
        sx, sy = on_plane @ right, on_plane @ up
        assert x == pytest.approx((sx + half_w) / pixel)
        assert y == pytest.approx((h * pixel / 2 - sy) / pixel)
    K = intrinsics(angle, w, h)
    cam = (pts - eye) @ c2w[:3, :3]
    hom = (K @ np.stack([cam[:, 0], -cam[:, 1], -cam[:, 2]])).T  # OpenCV-style camera axes
    np.testing.assert_allclose(hom[:, :2] / hom[:, 2:], px, rtol=1e-10)


def test_pixel_centre_convention():
    c2w = look_at((0, -4, 0), (0, 0, 0))  # camera x = world +X, camera y = world +Z
    w = 10
    f = intrinsics(0.5, w, w)[0, 0]
    # a point seen through the centre of pixel (0, 0): half a pixel from the top-left corner
    p = np.array([(0.5 - w / 2) / f * 4.0, 0.0, (w / 2 - 0.5) / f * 4.0])
    np.testing.assert_allclose(project(p[None], c2w, 0.5, w, w)[0][0], [0.5, 0.5], atol=1e-9)


def test_train_cameras_cover_the_hemisphere_deterministically():
    cams = train_cameras(100, 4.0, (0.1, 0.2, 0.3), (15.0, 60.0), seed=7)
    again = train_cameras(100, 4.0, (0.1, 0.2, 0.3), (15.0, 60.0), seed=7)
    other = train_cameras(100, 4.0, (0.1, 0.2, 0.3), (15.0, 60.0), seed=8)
    assert all(np.array_equal(a, b) for a, b in zip(cams, again))
    assert not np.allclose(cams[0], other[0])
    d = camera_directions(cams, (0.1, 0.2, 0.3))
    elev = np.degrees(np.arcsin(d[:, 2]))
    assert elev.min() >= 15.0 - 1e-9 and elev.max() <= 60.0 + 1e-9
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    assert np.histogram(az, bins=8, range=(-180, 180))[0].min() >= 8  # every octant used
    assert np.histogram(elev, bins=3, range=(15, 60))[0].min() >= 15
    # consecutive timesteps see the scene from far apart; the first 10 already span the azimuths
    steps = np.degrees(np.arccos(np.clip((d[1:] * d[:-1]).sum(1), -1, 1)))
    assert np.median(steps) > 60
    assert np.histogram(az[:10], bins=4, range=(-180, 180))[0].min() >= 1
    for c in cams:
        px, depth = project(np.array([[0.1, 0.2, 0.3]]), c, 0.7, 64, 64)
        np.testing.assert_allclose(px[0], [32, 32], atol=1e-9)
        assert depth[0] == pytest.approx(4.0)


def test_test_cameras_are_novel():
    train = train_cameras(150, 4.0, (0, 0, 0), (10.0, 70.0), seed=3)
    test = make_test_cameras(20, 4.0, (0, 0, 0), (10.0, 70.0), seed=3, avoid=train)
    assert len(test) == 20
    dt, dr = camera_directions(test), camera_directions(train)
    sep = np.degrees(np.arccos(np.clip(dt @ dr.T, -1, 1)))
    assert sep.min() >= 2.0
    again = make_test_cameras(20, 4.0, (0, 0, 0), (10.0, 70.0), seed=3, avoid=train)
    assert all(np.array_equal(a, b) for a, b in zip(test, again))
    elev = np.degrees(np.arcsin(dt[:, 2]))
    assert elev.min() >= 10.0 - 1e-9 and elev.max() <= 70.0 + 1e-9
    # even without `avoid`, the test stream differs from the training stream of the same seed
    plain = make_test_cameras(20, 4.0, (0, 0, 0), (10.0, 70.0), seed=3)
    assert np.degrees(np.arccos(np.clip(camera_directions(plain) @ dr.T, -1, 1))).min() > 0.01


def test_bad_camera_arguments():
    with pytest.raises(ValueError):
        train_cameras(4, -1.0)
    with pytest.raises(ValueError):
        train_cameras(4, 1.0, elevation_deg=(60, 10))
    with pytest.raises(ValueError):
        intrinsics(0.0, 10, 10)
    assert train_cameras(0, 1.0) == [] and make_test_cameras(0, 1.0) == []


def test_transforms_dict_is_readable_by_the_layout_reader(tmp_path):
    cams = train_cameras(3, 4.0, seed=0)
    frames = [(f"train/r_{i:04d}", c, i / 2) for i, c in enumerate(cams)]
    doc = transforms_dict(0.69, frames)
    assert doc["frames"][0]["time"] == 0.0 and doc["frames"][0]["file_path"] == "train/r_0000"
    (tmp_path / "transforms_train.json").write_text(json.dumps(doc))
    t = read_transforms(tmp_path, "train")
    assert t.camera_angle_x == pytest.approx(0.69) and len(t.frames) == 3
    np.testing.assert_array_equal(t.frames[2].c2w, cams[2])
    with pytest.raises(ValueError):
        transforms_dict(0.69, [("a", np.eye(3), 0.0)])
    with pytest.raises(ValueError):
        transforms_dict(0.69, [("a", np.eye(4), 1.5)])
