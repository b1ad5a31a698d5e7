"""The per-frame Blender job, run inside a worker process that builds the scene once.

For each frame: pose the scene at its time, place the camera, render the ground-truth pass once (a
multilayer EXR: AOVs, world-space Normal, alpha; few samples, no bounces, no denoiser), turn it into
the GT files, then render the lit RGBA PNG under each light, swapping only the world's env map. The
frame's record (with each file's size and sha256) is written last, so a frame interrupted anywhere is
simply rendered again.
"""
from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any

import bpy

from generator import postprocess
from generator.jobs import FrameJob, RenderSettings
from lumibench import layout
from lumibench.io import atomic_write_json

from . import camera as bcamera
from . import cycles as bcycles
from . import world as bworld
from .build import build_scene, reset_blender

# Importance map for the world: the 32 x 16 maps need little resolution. "MANUAL" matters for speed:
# Cycles' automatic mode rebuilds a large map on every env swap (about 0.7 s each, measured). The map is
# WORLD_SAMPLE_MAP x WORLD_SAMPLE_MAP / 2, or the env map's own size when that is wider (a light with a
# finer `resolution` in lights.yaml: one importance texel per env texel; 128 x 64 maps keep 128).
WORLD_SAMPLE_MAP = 128


class FrameRenderer:
    """One built scene, ready to render frames of any variant (they differ only in time and camera)."""

    def __init__(self, spec, settings: RenderSettings, hdr_paths: dict[str, str], *, threads: int = 0,
                 persistent_data: bool = True):
        self.spec = spec
        self.settings = settings
        self.hdr_paths = {n: str(Path(p).resolve()) for n, p in hdr_paths.items()}
        t0 = time.perf_counter()
        self.scene = reset_blender()
        self.built = build_scene(self.scene, spec)
        bcycles.configure(self.scene, resolution=settings.resolution, spp=settings.spp, seed=settings.seed,
                          threads=threads, persistent_data=persistent_data)
        if self.scene.cycles.use_denoising:
            # OIDN's "Accurate" prefilter denoises the albedo and normal guide passes first: 3 OIDN runs per
            # image. Measured at 128 px / 32 spp (spheres): lit pass 1.33 s -> 0.74 s with "Fast", vs 0.67 s
            # without any denoising. The guide passes of these opaque, mostly diffuse scenes are clean.
            self.scene.cycles.denoising_prefilter = "FAST"
        self.current_light: str | None = None
        self._set_light(settings.light_names[0])
        self.build_seconds = time.perf_counter() - t0
        self.frames_rendered = 0
        self.blender_version = bpy.app.version_string

    def _set_light(self, name: str) -> None:
        if name == self.current_light:
            return
        world = bworld.set_environment(self.scene, self.hdr_paths[name], 1.0)
        world.cycles.sampling_method = "MANUAL"
        world.cycles.sample_map_resolution = max(WORLD_SAMPLE_MAP, bworld.environment_width(world))
        self.current_light = name

    def _pose(self, job: FrameJob) -> None:
        self.built.set_time(job.time)
        bcamera.set_camera(self.scene, job.c2w, self.settings.camera_angle_x)

    def render_gt(self, job: FrameJob, exr_path: Path) -> float:
        """The ground-truth pass to ``exr_path``; returns seconds."""
        sc, c = self.scene, self.scene.cycles
        t0 = time.perf_counter()
        saved = (c.samples, c.use_denoising, c.max_bounces)
        c.samples, c.use_denoising, c.max_bounces = self.settings.gt_spp, False, 0
        vl = sc.view_layers[0]
        vl.use_pass_normal = True
        ims = sc.render.image_settings
        ims.media_type = "MULTI_LAYER_IMAGE"
        ims.color_depth = "32"
        ims.exr_codec = "ZIP"
        try:
            bcycles.render_still(sc, exr_path)
        finally:
            c.samples, c.use_denoising, c.max_bounces = saved
            bcycles.set_png_output(sc)
        return time.perf_counter() - t0

    def render_lit(self, job: FrameJob, light: str) -> float:
        """The lit RGBA PNG under ``light`` (render_still drops Cycles' render-time text chunks)."""
        t0 = time.perf_counter()
        self._set_light(light)
        bcycles.render_still(self.scene, layout.lit_image_path(job.scene_dir, light, job.file_path))
        return time.perf_counter() - t0

    def render(self, job: FrameJob, spec_hash: str) -> dict[str, Any]:
        """All files of one frame, then its record; returns the record."""
        t_start = time.perf_counter()
        self._pose(job)
        rec_path = job.record_path()
        exr = rec_path.with_name(f"{rec_path.stem}.gt.exr")
        gt_s = self.render_gt(job, exr)
        t0 = time.perf_counter()
        try:
            postprocess.exr_to_ground_truth(exr, job.scene_dir, job.file_path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                exr.unlink()
        post_s = time.perf_counter() - t0
        lit_s = {light: round(self.render_lit(job, light), 4) for light in self.settings.light_names}
        record = job.make_record(
            spec_hash, self.settings,
            blender_version=self.blender_version,
            seconds={"gt": round(gt_s, 4), "post": round(post_s, 4), "lit": lit_s,
                     "total": round(time.perf_counter() - t_start, 4),
                     # scene build in this worker before its first frame (bpy import not included)
                     "worker_setup": round(self.build_seconds, 4) if self.frames_rendered == 0 else 0.0},
        )
        self.frames_rendered += 1
        atomic_write_json(rec_path, record)
        return record
