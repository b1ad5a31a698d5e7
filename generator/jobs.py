"""What to render for one scene: the frame jobs of both variants, and the per-frame completion records.

A job is one camera at one time in one variant/split. Jobs that see exactly the same image (same camera,
same time: every test view, and the static variant's frame at the static timestep) are rendered once and
copied, so the two variants can never disagree. A frame is finished when all its files exist and its
record (``<scene>/.frames/<split>/r_NNNN.json``, written last) carries the same key (spec hash, render
settings, the light set with the sha256 of each ``<light>.hdr``, the camera and the time) and lists every
file with the size and sha256 it had when written: a file truncated or changed afterwards makes the frame
unfinished again.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lumibench import layout
from lumibench.io import sha256_file

from . import cameras

RECORD_DIR = ".frames"
GT_EXTS = {"albedo": (".png", ".npz"), "roughness": (".png", ".npz"), "normal": (".png", ".npz"),
           "dynamic_mask": (".png", ".npz")}


GT_MAX_SPP = 16


def gt_samples(spp: int) -> int:
    """Samples of the ground-truth pass: enough for a stable coverage estimate at silhouettes, no more."""
    return max(4, min(int(spp), GT_MAX_SPP))


@dataclass(frozen=True)
class RenderSettings:
    """Everything about a render that is not the scene spec: it goes into every frame's key."""

    resolution: int
    spp: int
    gt_spp: int
    seed: int
    camera_angle_x: float
    lights: tuple[tuple[str, str], ...]  # (name, sha256 of the <light>.hdr actually rendered with)

    @property
    def light_names(self) -> list[str]:
        return [n for n, _ in self.lights]

    def as_dict(self) -> dict[str, Any]:
        return {"resolution": self.resolution, "spp": self.spp, "gt_spp": self.gt_spp, "seed": self.seed,
                "camera_angle_x": self.camera_angle_x, "lights": {n: h for n, h in self.lights}}


@dataclass
class FrameJob:
    """One output frame: where it goes, what it sees, and (for copies) which rendered frame it equals."""

    scene_dir: Path  # the variant's directory
    split: str
    index: int
    time: float
    c2w: np.ndarray
    copy_of: "FrameJob | None" = field(default=None, repr=False)

    @property
    def file_path(self) -> str:
        return layout.file_path(self.split, self.index)

    @property
    def label(self) -> str:
        return f"{self.scene_dir.name}/{self.file_path}"

    def view_key(self) -> str:
        """Identity of the image content (camera and time), independent of where it is stored."""
        c = np.round(np.asarray(self.c2w, dtype=np.float64), 12) + 0.0
        return hashlib.sha256(c.tobytes() + repr(round(float(self.time), 12)).encode()).hexdigest()

    def key(self, spec_hash: str, settings: RenderSettings) -> dict[str, Any]:
        return {"spec_hash": spec_hash, "settings": settings.as_dict(), "view": self.view_key(),
                "time": float(self.time)}

    def outputs(self, light_names: list[str]) -> list[Path]:
        """Every file this frame writes (the record excluded)."""
        out = [layout.lit_image_path(self.scene_dir, light, self.file_path) for light in light_names]
        for kind, exts in GT_EXTS.items():
            out.extend(layout.gt_path(self.scene_dir, kind, self.file_path, ext) for ext in exts)
        return out

    def record_path(self) -> Path:
        return self.scene_dir / RECORD_DIR / self.split / f"{layout.frame_stem(self.index)}.json"

    def read_record(self) -> dict[str, Any] | None:
        try:
            return json.loads(self.record_path().read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def file_digests(self, light_names: list[str]) -> dict[str, dict[str, Any]]:
        """{path relative to the variant directory: {"size", "sha256"}} of every output file."""
        out = {}
        for p in self.outputs(light_names):
            out[p.relative_to(self.scene_dir).as_posix()] = {"size": p.stat().st_size, "sha256": sha256_file(p)}
        return out

    def make_record(self, spec_hash: str, settings: RenderSettings, **extra: Any) -> dict[str, Any]:
        """The completion record, made once every file is written: the key, ``extra`` (timings, Blender
        version) and the size and sha256 of each file, so that a file changed afterwards is noticed."""
        return {"key": self.key(spec_hash, settings), "file_path": self.file_path, **extra,
                "files": self.file_digests(settings.light_names)}

    def files_match(self, files: Any, light_names: list[str]) -> bool:
        """Every output file exists with the size and sha256 the record lists (sizes first: cheap)."""
        if not isinstance(files, dict):
            return False  # a record without digests (older format) proves nothing about the files
        paths = {p.relative_to(self.scene_dir).as_posix(): p for p in self.outputs(light_names)}
        if set(files) != set(paths):
            return False
        for rel, p in paths.items():
            want = files[rel]
            try:
                size = p.stat().st_size
            except OSError:
                return False
            if not isinstance(want, dict) or want.get("size") != size:
                return False
        return all(files[rel].get("sha256") == sha256_file(p) for rel, p in paths.items())

    def is_done(self, spec_hash: str, settings: RenderSettings) -> bool:
        """Finished for this key: the record carries the same key and every file matches its digest."""
        rec = self.read_record()
        if rec is None or rec.get("key") != _jsonable(self.key(spec_hash, settings)):
            return False
        return self.files_match(rec.get("files"), settings.light_names)


def _jsonable(obj: Any) -> Any:
    """The value as it reads back from JSON (tuples become lists), so keys compare equal after a round trip."""
    return json.loads(json.dumps(obj))


@dataclass
class ScenePlan:
    """Both variants of one scene: directories, transforms and frame jobs."""

    dynamic_dir: Path
    static_dir: Path
    static_time: float
    train_c2w: list[np.ndarray]
    test_c2w: list[np.ndarray]
    times: list[float]
    jobs: list[FrameJob]

    @property
    def renders(self) -> list[FrameJob]:
        return [j for j in self.jobs if j.copy_of is None]

    @property
    def copies(self) -> list[FrameJob]:
        return [j for j in self.jobs if j.copy_of is not None]

    def transforms(self, camera_angle_x: float) -> dict[Path, dict[str, dict]]:
        """{variant dir: {split: transforms document}}."""
        out: dict[Path, dict[str, dict]] = {}
        test = cameras.transforms_dict(camera_angle_x, [
            (layout.file_path("test", i), c, self.static_time) for i, c in enumerate(self.test_c2w)])
        out[self.dynamic_dir] = {
            "train": cameras.transforms_dict(camera_angle_x, [
                (layout.file_path("train", i), c, t) for i, (c, t) in enumerate(zip(self.train_c2w, self.times))]),
            "test": test,
        }
        out[self.static_dir] = {
            "train": cameras.transforms_dict(camera_angle_x, [
                (layout.file_path("train", i), c, self.static_time) for i, c in enumerate(self.train_c2w)]),
            "test": test,
        }
        return out


def frame_times(n: int) -> list[float]:
    """time = i / (N - 1): the first frame is at 0 and the last at 1."""
    if n < 2:
        return [0.0] * n
    return [i / (n - 1) for i in range(n)]


def plan_scene(spec, n_frames: int, test_views: int, static_timestep: int, root: Path) -> ScenePlan:
    """Cameras, times and the deduplicated job list for ``spec`` rendered into ``root`` (DATA/PROFILE)."""
    cam = spec.camera
    train = cameras.train_cameras(n_frames, cam.radius, cam.target, cam.elevation_deg, seed=spec.seed)
    test = cameras.test_cameras(test_views, cam.radius, cam.target, cam.elevation_deg, seed=spec.seed, avoid=train)
    times = frame_times(n_frames)
    static_time = times[static_timestep]
    dyn = layout.scene_dir(root.parent, root.name, spec.name)
    sta = layout.scene_dir(root.parent, root.name, layout.static_scene_name(spec.name, static_timestep))
    jobs = [FrameJob(dyn, "train", i, t, c) for i, (c, t) in enumerate(zip(train, times))]
    jobs += [FrameJob(dyn, "test", i, static_time, c) for i, c in enumerate(test)]
    jobs += [FrameJob(sta, "train", i, static_time, c) for i, c in enumerate(train)]
    jobs += [FrameJob(sta, "test", i, static_time, c) for i, c in enumerate(test)]
    first: dict[str, FrameJob] = {}
    for j in jobs:
        k = j.view_key()
        if k in first:
            j.copy_of = first[k]
        else:
            first[k] = j
    return ScenePlan(dyn, sta, static_time, train, test, times, jobs)
