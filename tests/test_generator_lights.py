"""lights.yaml validation, light resolution (names and user files) and the prepared 32 x 16 maps."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from generator import envmap as em
from generator.lights import LIGHTS_YAML, LightSpec, bpy_data_dir, load_lights, prepare_envmap, resolve_light
from lumibench.errors import UserError

DEFAULTS = ("city", "sunrise", "courtyard", "sunset")


def _yaml(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "lights.yaml"
    p.write_text(text)
    return p


def test_default_lights_load_and_exist():
    lights = load_lights()
    assert set(DEFAULTS) <= set(lights)
    for name in DEFAULTS:
        spec = lights[name]
        assert spec.name == name and spec.source.is_file(), spec.source
        assert spec.source.is_relative_to(bpy_data_dir())


def test_default_lights_dominant_directions_differ():
    """The four defaults are lit from clearly different azimuths; the sunny ones are peaky."""
    az = {}
    for name in DEFAULTS:
        small = prepare_envmap(resolve_light(name))
        assert small.shape == (16, 32, 3) and small.dtype == np.float32
        az[name], el = em.brightest_direction(small)
        assert el > 0.0  # the dominant light is above the horizon
        lum = small @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        peak_over_mean = lum.max() / (em.solid_angles(16, 32) * lum).sum() * 4 * np.pi
        assert peak_over_mean > (50 if name in ("city", "sunrise") else 5), name
    names = list(az)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            gap = abs(((az[names[i]] - az[names[j]] + 180) % 360) - 180)
            assert gap >= 60.0, (names[i], names[j], az)


def test_prepare_envmap_is_rotate_then_downsample_then_scale(tmp_path):
    img = np.random.default_rng(0).lognormal(0, 1, (40, 80, 3)).astype(np.float32)
    em.write_hdr(tmp_path / "m.hdr", img)
    src = em.read_envmap(tmp_path / "m.hdr")
    out = prepare_envmap(LightSpec("m", tmp_path / "m.hdr", 30.0, 2.0))
    np.testing.assert_allclose(out, 2.0 * em.downsample_envmap(em.rotate_envmap(src, 30.0)), rtol=1e-6)
    np.testing.assert_allclose(em.mean_radiance(out), 2.0 * em.mean_radiance(src), rtol=1e-5)


def test_user_path_resolves_with_rotation_zero(tmp_path):
    p = tmp_path / "my_sky.hdr"
    em.write_hdr(p, np.ones((16, 32, 3), np.float32))
    spec = resolve_light(str(p))
    assert spec == LightSpec("my_sky", p.resolve(), 0.0, 1.0)
    np.testing.assert_allclose(prepare_envmap(spec), 1.0, rtol=1e-6)


def test_unknown_light_lists_the_known_ones():
    with pytest.raises(UserError) as exc:
        resolve_light("moonlight")
    msg = str(exc.value)
    assert "moonlight" in msg and all(n in msg for n in DEFAULTS)


def test_missing_user_file_is_named(tmp_path):
    with pytest.raises(UserError, match="not found.*nothere.exr"):
        resolve_light(str(tmp_path / "nothere.exr"))


def test_missing_file_of_a_named_light_is_named(tmp_path):
    y = _yaml(tmp_path, "lights:\n  ghost:\n    source: maps/ghost.hdr\n")
    with pytest.raises(UserError, match=r"ghost.*not found.*maps/ghost\.hdr"):
        resolve_light("ghost", y)


def test_relative_and_bpy_sources(tmp_path):
    y = _yaml(tmp_path, "lights:\n  a:\n    source: sub/a.exr\n  b:\n    source: bpy:studiolights/world/city.exr\n")
    lights = load_lights(y)
    assert lights["a"].source == tmp_path / "sub" / "a.exr"
    assert lights["b"].source == bpy_data_dir() / "studiolights" / "world" / "city.exr"
    assert lights["a"].rotation_deg == 0.0 and lights["a"].strength == 1.0


@pytest.mark.parametrize("text,key", [
    ("lights:\n  city:\n    source: a.hdr\n    rotaton_deg: 5\n", "lights.city.rotaton_deg"),
    ("lights:\n  city:\n    source: a.hdr\n    rotation_deg: east\n", "lights.city.rotation_deg"),
    ("lights:\n  city:\n    source: a.hdr\n    strength: -1\n", "lights.city.strength"),
    ("lights:\n  city:\n    rotation_deg: 5\n", "lights.city.source"),
    ("lights:\n  city:\n    source: a.png\n", "lights.city.source"),
    ("lights:\n  city: [1, 2]\n", "lights.city"),
    ("lite:\n  city: {}\n", "lite"),
    ("lights: {}\n", "lights"),
    ("lights:\n  city:\n    source: a.hdr\n   strength: 1\n", "line"),
])
def test_bad_yaml_names_the_key(tmp_path, text, key):
    y = _yaml(tmp_path, text)
    with pytest.raises(UserError) as exc:
        load_lights(y)
    msg = str(exc.value)
    assert str(y) in msg and key in msg and "\n" not in msg


def test_cli_style_error_exit_code(tmp_path, capsys):
    from lumibench.errors import run_cli

    y = _yaml(tmp_path, "lights:\n  city:\n    source: a.hdr\n    bogus: 1\n")
    assert run_cli(lambda argv: load_lights(y)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "lights.city.bogus" in err


def test_shipped_yaml_is_the_default():
    assert LIGHTS_YAML.name == "lights.yaml" and LIGHTS_YAML.is_file()
