"""Named lights (configs/lights.yaml) and user env-map files -> the maps the dataset is lit by (32 x 16 unless a
light names its own ``resolution``)."""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lumibench.config import Node, load_yaml
from lumibench.errors import UserError
from lumibench.layout import LIGHT_FILE_SUFFIXES, parse_light
from lumibench.profiles import CONFIG_DIR

from .envmap import downsample_envmap, read_envmap, rotate_envmap

LIGHTS_YAML = CONFIG_DIR / "lights.yaml"
ENV_WIDTH, ENV_HEIGHT = 32, 16  # every light's map unless it names its own resolution
MAX_ENV_HEIGHT = 1024           # a larger map would only make every shading lookup slower
BPY_PREFIX = "bpy:"


@dataclass(frozen=True)
class LightSpec:
    """One lighting condition: an env-map file, a rotation about world +Z and a radiance multiplier."""

    name: str
    source: Path
    rotation_deg: float = 0.0
    strength: float = 1.0
    resolution: tuple[int, int] = (ENV_WIDTH, ENV_HEIGHT)  # (width, height) of the prepared map
    default: bool = True  # rendered when no lights are named (`make dataset` without LIGHTS)


def bpy_data_dir() -> Path:
    """bpy's bundled data folder (``<bpy>/5.0/datafiles``) located without importing bpy."""
    spec = importlib.util.find_spec("bpy")
    locations = list(spec.submodule_search_locations or []) if spec else []
    for loc in locations:
        for cand in sorted(Path(loc).glob("*/datafiles")):
            return cand
    raise UserError("cannot locate the bpy package's datafiles (is bpy==5.0.1 installed? run `make setup`)")


def _resolve_source(raw: str, base: Path) -> Path:
    if raw.startswith(BPY_PREFIX):
        return bpy_data_dir() / raw[len(BPY_PREFIX):]
    p = Path(raw).expanduser()
    return p if p.is_absolute() else (base / p)


def load_lights(path: str | Path = LIGHTS_YAML) -> dict[str, LightSpec]:
    """Parse and validate lights.yaml; errors name the file and the key. Files are checked on use.

    ``source`` is ``bpy:<path under bpy's datafiles>``, an absolute path, or a path relative to the YAML.
    """
    path = Path(path)
    root = Node(load_yaml(path), str(path))
    root.reject_unknown(["lights"])
    lights = root.child("lights")
    if not lights.data:
        raise lights.error("lights", "must list at least one light")
    out: dict[str, LightSpec] = {}
    for name in lights.data:
        if not isinstance(name, str) or not name.isidentifier():
            raise lights.error(str(name), "is not a valid light name (letters, digits and _ only)")
        node = lights.child(name)
        node.reject_unknown(["source", "rotation_deg", "strength", "resolution", "default"])
        source = node.get("source", str, check=lambda s: s.lower().endswith(LIGHT_FILE_SUFFIXES),
                          check_msg="must be an .hdr or .exr file")
        rotation = node.get("rotation_deg", float, 0.0, check=lambda r: -360.0 <= r <= 360.0,
                            check_msg="must be in [-360, 360] degrees")
        strength = node.get("strength", float, 1.0, check=lambda s: 0.0 < s < 1e6, check_msg="must be positive")
        resolution = node.get("resolution", list, [ENV_WIDTH, ENV_HEIGHT], check=_valid_resolution,
                              check_msg=f"must be [width, height] in texels with width = 2 x height (an "
                                        f"equirectangular map) and 1 <= height <= {MAX_ENV_HEIGHT}, e.g. [128, 64]")
        default = node.get("default", bool, True)
        out[name] = LightSpec(name, _resolve_source(source, path.parent), rotation, strength,
                              (int(resolution[0]), int(resolution[1])), default)
    return out


def _valid_resolution(value: list) -> bool:
    if len(value) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return False
    width, height = value
    return 1 <= height <= MAX_ENV_HEIGHT and width == 2 * height


def default_light_names(lights_yaml: str | Path = LIGHTS_YAML) -> list[str]:
    """The lights rendered when none are named, in lights.yaml order (those without ``default: false``)."""
    return [name for name, spec in load_lights(lights_yaml).items() if spec.default]


def resolve_light(name_or_path: str | Path, lights_yaml: str | Path = LIGHTS_YAML) -> LightSpec:
    """A light by name from lights.yaml, or a user .hdr/.exr path (rotation 0, strength 1).

    The light's name for a path is the file stem (lumibench.layout.parse_light: the dataset's ``<light>/``
    folder).
    """
    text = str(name_or_path)
    lights = load_lights(lights_yaml)
    if text in lights:
        spec = lights[text]
        if not spec.source.is_file():
            raise UserError(f"light '{text}': environment map not found: {spec.source} (see {lights_yaml})")
        return spec
    name, p = parse_light(text)
    if p is None:
        raise UserError(f"unknown light '{text}' (known: {', '.join(sorted(lights))}; "
                        f"or give a path to an .hdr or .exr file, named by its stem)")
    if not p.is_file():
        raise UserError(f"light file not found: {p}")
    return LightSpec(name, p.resolve(), 0.0, 1.0)


def prepare_envmap(spec: LightSpec) -> np.ndarray:
    """Read, rotate (at source resolution), scale by strength and downsample to float32 height x width x 3
    (16 x 32 unless the light names its resolution; energy-preserving, see envmap.downsample_envmap).

    The result is exactly the radiance the scene is lit by: the pipeline writes it as ``<light>.hdr``
    and renders with that file at world strength 1.
    """
    img = read_envmap(spec.source)
    if spec.rotation_deg:
        img = rotate_envmap(img, spec.rotation_deg)
    width, height = spec.resolution
    small = downsample_envmap(img, width, height)
    return (small * np.float32(spec.strength)).astype(np.float32)
