"""Env maps: mapping, solid angles, energy-preserving downsampling, rotation, RGBE reader/writer."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from generator import envmap as em
from generator.lights import bpy_data_dir
from lumibench.errors import UserError

SHARED_ENVMAPS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "envmaps"


def _brute_mean(img: np.ndarray, n: int = 1_000_000) -> np.ndarray:
    """Mean radiance over the sphere by brute force, independent of solid_angles(): an equal-area grid
    of directions (uniform in z and in phi), each looking up its nearest texel. Rows depend only on z
    and columns only on phi, so the n x n grid is counted per axis."""
    h, w = img.shape[:2]
    z = -1.0 + 2.0 * (np.arange(n) + 0.5) / n
    rows, _ = em.texel_of_direction(np.stack([np.sqrt(1 - z * z), np.zeros(n), z], -1), h, w)
    phi = 2.0 * math.pi * (np.arange(n) + 0.5) / n
    _, cols = em.texel_of_direction(np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], -1), h, w)
    wr = np.bincount(rows, minlength=h) / n
    wc = np.bincount(cols, minlength=w) / n
    return np.einsum("r,c,rcx->x", wr, wc, img.astype(np.float64))


def test_uv_mapping_axes_and_round_trip():
    # Blender: image centre looks along +X, u = 0.25 along +Y, v = 1 at +Z
    u, v = em.direction_to_uv(np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0.0], [0, 0, 1], [0, 0, -1]]))
    np.testing.assert_allclose(u[:3], [0.5, 0.25, 0.0], atol=1e-12)
    np.testing.assert_allclose(v, [0.5, 0.5, 0.5, 1.0, 0.0], atol=1e-12)
    d = np.random.default_rng(0).normal(size=(1000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(em.uv_to_direction(*em.direction_to_uv(d)), d, atol=1e-9)


def test_solid_angles_sum_and_match_monte_carlo():
    om = em.solid_angles(16, 32)
    assert om.sum() == pytest.approx(4 * math.pi, rel=1e-12)
    assert om[0, 0] < om[7, 0] and om[7, 0] == pytest.approx(om[8, 0])  # poles small, symmetric about the equator
    counts = np.zeros((16, 32))
    d = np.random.default_rng(1).normal(size=(400_000, 3))
    r, c = em.texel_of_direction(d, 16, 32)
    np.add.at(counts, (r, c), 1.0)
    np.testing.assert_allclose(counts.sum(axis=1) / 400_000 * 4 * math.pi, om.sum(axis=1), rtol=0.04)


@pytest.mark.parametrize("shape", [(64, 128), (50, 100), (37, 71)])
def test_downsample_preserves_solid_angle_weighted_mean(shape):
    rng = np.random.default_rng(shape[0])
    img = rng.lognormal(0.0, 1.5, shape + (3,)).astype(np.float32)
    img[3, 5] = 5000.0  # a sun
    small = em.downsample_envmap(img, 32, 16)
    assert small.shape == (16, 32, 3) and small.dtype == np.float32
    np.testing.assert_allclose(em.mean_radiance(small), em.mean_radiance(img), rtol=1e-5)
    # and the source mean itself is the true spherical mean (independent brute force)
    np.testing.assert_allclose(em.mean_radiance(img), _brute_mean(img), rtol=1e-4)


def test_downsample_is_a_block_average_for_a_constant_and_for_exact_multiples():
    const = np.full((40, 90, 3), 2.5, np.float32)
    np.testing.assert_allclose(em.downsample_envmap(const), 2.5, rtol=1e-6)
    img = np.random.default_rng(2).random((32, 64, 3)).astype(np.float32)
    small = em.downsample_envmap(img)
    # brute force: each 2 x 2 block, rows weighted by their own solid angle
    om = em.solid_angles(32, 64)[..., None]
    blocks = (img * om).reshape(16, 2, 32, 2, 3).sum(axis=(1, 3)) / om.reshape(16, 2, 32, 2, 1).sum(axis=(1, 3))
    np.testing.assert_allclose(small, blocks, rtol=1e-5)


def test_downsample_keeps_a_regional_energy_in_its_region():
    img = np.zeros((48, 96, 3), np.float32)
    img[5:9, 10:14] = 100.0  # upper region, not aligned with target texels
    small = em.downsample_envmap(img)
    om_src, om_dst = em.solid_angles(48, 96), em.solid_angles(16, 32)
    e_src = (img[..., 0] * om_src).sum()
    e_dst = (small[..., 0] * om_dst)
    assert e_dst.sum() == pytest.approx(e_src, rel=1e-5)
    assert e_dst[1:3, 3:5].sum() == pytest.approx(e_src, rel=1e-5)  # nothing leaks outside the cover


def test_rotation_moves_a_bright_texel_by_the_given_azimuth():
    h, w = 64, 128
    for row, col in [(10, 20), (40, 100)]:
        img = np.full((h, w, 3), 0.1, np.float32)
        img[row, col] = 50.0
        az0, el0 = em.brightest_direction(img)
        step = 360.0 / w
        for deg in [step * 3, -step * 17, 90.0, 180.0, 360.0 - step * 5]:
            az1, el1 = em.brightest_direction(em.rotate_envmap(img, deg))
            assert el1 == pytest.approx(el0)
            assert ((az1 - az0 - deg + 180) % 360) - 180 == pytest.approx(0.0, abs=1e-9)


def test_fractional_rotation_interpolates_linearly_and_conserves_energy():
    img = np.zeros((8, 16, 3), np.float32)
    img[3, 6] = 1.0
    out = em.rotate_envmap(img, 360.0 / 16 * 0.25)  # a quarter texel towards larger azimuth (smaller column)
    assert out[3, :, 0].sum() == pytest.approx(1.0)
    assert out[3, 5, 0] == pytest.approx(0.25) and out[3, 6, 0] == pytest.approx(0.75)
    np.testing.assert_allclose(em.rotate_envmap(em.rotate_envmap(img, 37.0), -37.0)[3, 6], 1.0, atol=0.6)
    np.testing.assert_allclose(em.mean_radiance(em.rotate_envmap(img, 37.0)), em.mean_radiance(img), rtol=1e-6)


def test_rotation_of_a_real_shipped_map():
    path = bpy_data_dir() / "studiolights" / "world" / "city.exr"
    if not path.is_file():
        pytest.skip(f"bpy's city.exr not found at {path}")
    img = em.read_envmap(path)
    az0, el0 = em.brightest_direction(img)
    for deg in [45.0, -120.0]:
        az1, el1 = em.brightest_direction(em.rotate_envmap(img, deg))
        assert el1 == pytest.approx(el0)
        assert abs(((az1 - az0 - deg + 180) % 360) - 180) <= 360.0 / img.shape[1] + 1e-9


def test_write_hdr_round_trips_to_rgbe_precision(tmp_path):
    rng = np.random.default_rng(3)
    for shape in [(16, 32), (5, 7), (3, 40000)]:  # run-length scanlines, and flat ones (width < 8, >= 32768)
        img = rng.lognormal(0.0, 3.0, shape + (3,)).astype(np.float32)
        img[0, 0] = 0.0
        img[-1, -1] = [2.0 / 256, 2.0 / 256, 1.0 / 256]  # reads (2, 2, 1, e): must not look like an RLE header
        path = tmp_path / f"m{shape[1]}.hdr"
        em.write_hdr(path, img)
        back = em.read_envmap(path)
        assert back.shape == img.shape
        rel = np.abs(back - img).max(axis=-1) / np.maximum(img.max(axis=-1), 1e-30)
        assert rel.max() <= 0.5 / 128 + 1e-6
        assert back[0, 0].tolist() == [0.0, 0.0, 0.0]
    assert not list(tmp_path.glob(".tmp-*"))


def test_reader_handles_flat_and_old_style_runs(tmp_path):
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 4\n"
    px = bytes((128, 64, 32, 129))  # (0.5, 0.25, 0.125) * 2
    path = tmp_path / "old.hdr"
    path.write_bytes(header + px + bytes((1, 1, 1, 3)))  # one pixel, then "repeat 3 times"
    np.testing.assert_allclose(em.read_envmap(path)[0], [[1.0, 0.5, 0.25]] * 4)
    path.write_bytes(header.replace(b"-Y 1", b"+Y 1") + px * 4)
    np.testing.assert_allclose(em.read_envmap(path)[0], [[1.0, 0.5, 0.25]] * 4)


@pytest.mark.parametrize("content,needle", [
    (b"not an hdr", "signature"),
    (b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 2 +X 2\n", "pixel format"),
    (b"#?RADIANCE\n\n-Y 2 +X 2\n" + bytes(8), "truncated"),
    (b"#?RADIANCE\n\n+X 2 -Y 2\n" + bytes(16), "resolution"),
])
def test_corrupt_hdr_is_a_user_error_naming_the_file(tmp_path, content, needle):
    path = tmp_path / "bad.hdr"
    path.write_bytes(content)
    with pytest.raises(UserError, match=needle) as exc:
        em.read_envmap(path)
    assert "bad.hdr" in str(exc.value)


def test_missing_or_unsupported_file(tmp_path):
    with pytest.raises(UserError, match="not found"):
        em.read_envmap(tmp_path / "nope.hdr")
    (tmp_path / "x.png").write_bytes(b"")
    with pytest.raises(UserError, match="unsupported"):
        em.read_envmap(tmp_path / "x.png")


def test_preview_png(tmp_path):
    from lumibench.io import read_image

    img = np.random.default_rng(4).lognormal(0, 2, (16, 32, 3)).astype(np.float32)
    em.preview_png(tmp_path / "p.png", img)
    prev = read_image(tmp_path / "p.png")
    assert prev.shape == (128, 256, 3) and 0.05 < prev.mean() < 0.95


@pytest.mark.skipif(not SHARED_ENVMAPS.is_dir(), reason=f"shared sample env maps not present at {SHARED_ENVMAPS}")
def test_shared_user_maps_load_downsample_as_noop_and_round_trip(tmp_path):
    files = sorted(SHARED_ENVMAPS.glob("*.hdr"))
    assert len(files) >= 2
    for f in files:
        img = em.read_envmap(f)
        assert img.shape == (16, 32, 3) and np.all(np.isfinite(img)) and img.max() > 1.0
        np.testing.assert_array_equal(em.downsample_envmap(img), img)
        out = tmp_path / f.name
        em.write_hdr(out, img)
        np.testing.assert_array_equal(em.read_envmap(out), img)  # values already on the RGBE grid
