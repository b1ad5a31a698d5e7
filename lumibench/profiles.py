"""Profiles (`configs/profiles/<name>.yaml`): resolution and effort shared by generator and method."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .config import Node, load_yaml
from .errors import UserError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


def available_profiles() -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / "profiles").glob("*.yaml"))


@dataclass(frozen=True)
class DatasetProfile:
    name: str
    resolution: int
    dynamic_frames: int
    spheres_frames: int
    test_views: int
    spp: int
    static_timestep: int

    def frames_for(self, scene: str) -> int:
        return self.spheres_frames if scene == "spheres" else self.dynamic_frames


@dataclass(frozen=True)
class MethodProfile:
    stage1_iterations: int
    stage2_iterations: int


@dataclass(frozen=True)
class Profile:
    name: str
    dataset: DatasetProfile
    method: MethodProfile


def load_profile(name: str) -> Profile:
    path = CONFIG_DIR / "profiles" / f"{name}.yaml"
    if not path.is_file():
        raise UserError(f"unknown profile '{name}' (known: {', '.join(available_profiles())})")
    root = Node(load_yaml(path), str(path))
    root.reject_unknown(["dataset", "method"])
    d = root.child("dataset")
    d.reject_unknown(["resolution", "dynamic_frames", "spheres_frames", "test_views", "spp", "static_timestep"])
    pos = dict(check=lambda v: v > 0, check_msg="must be positive")
    ds = DatasetProfile(
        name=name,
        resolution=d.get("resolution", int, **pos),
        dynamic_frames=d.get("dynamic_frames", int, **pos),
        spheres_frames=d.get("spheres_frames", int, **pos),
        test_views=d.get("test_views", int, **pos),
        spp=d.get("spp", int, **pos),
        static_timestep=d.get("static_timestep", int, check=lambda v: v >= 0, check_msg="must be >= 0"),
    )
    if ds.static_timestep >= min(ds.dynamic_frames, ds.spheres_frames):
        raise root.error("dataset.static_timestep", "must be smaller than the number of frames")
    m = root.child("method")
    m.reject_unknown(["stage1_iterations", "stage2_iterations"])
    ms = MethodProfile(
        stage1_iterations=m.get("stage1_iterations", int, **pos),
        stage2_iterations=m.get("stage2_iterations", int, **pos),
    )
    return Profile(name=name, dataset=ds, method=ms)
