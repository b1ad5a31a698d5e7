"""Render one scene (dynamic and static variants, train and test splits) into the dataset layout.

    render_scene("spheres", "ci", Path("data"), jobs=2)  ->  data/ci/spheres

Order of work: validate everything the user gave (scene, profile, lights, DATA) before any render;
write the env maps and transforms; render the frames that are not already finished for the same key
with every file as recorded (generator.jobs: size and sha256) in ``jobs`` worker processes, each building the scene once; copy the frames that
show the same view; write dataset.json of both variants, with "complete": true last.
"""
from __future__ import annotations

import multiprocessing
import os
import shutil
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from lumibench import layout
from lumibench.errors import UserError
from lumibench.io import atomic_path, atomic_write_json, sha256_file
from lumibench.machine import usable_cores
from lumibench.profiles import load_profile
from lumibench.progress import make_progress

from . import envmap, lights as lights_mod, spec as spec_mod
from . import render_worker
from .jobs import FrameJob, RenderSettings, ScenePlan, gt_samples, plan_scene

DATASET_FORMAT = 1


@dataclass(frozen=True)
class SceneRun:
    """Everything decided before rendering (validated inputs, plan, settings)."""

    spec: Any
    profile: Any  # lumibench.profiles.DatasetProfile
    lights: list  # LightSpec
    plan: ScenePlan
    settings: RenderSettings
    hdr_paths: dict[str, Path]


def default_lights() -> list[str]:
    """The named lights rendered when none are given (configs/lights.yaml, less those with default: false)."""
    return lights_mod.default_light_names()


def resolve_lights(names: list[str] | None) -> list:
    specs = [lights_mod.resolve_light(n) for n in (names or default_lights())]
    seen: dict[str, str] = {}
    for s, raw in zip(specs, names or [s.name for s in specs]):
        if s.name in seen:
            raise UserError(f"two lights would share the folder name '{s.name}' ({seen[s.name]} and {raw}); "
                            "rename one of the files")
        if s.name in layout.GT_KINDS or s.name in ("transforms_train", "transforms_test", "dataset"):
            raise UserError(f"light name '{s.name}' collides with a dataset folder; rename the file")
        seen[s.name] = str(raw)
    return specs


def check_writable(data: Path) -> None:
    """Fail early, with one line, when DATA cannot hold the dataset."""
    data = Path(data)
    try:
        data.mkdir(parents=True, exist_ok=True)
        probe = data / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"DATA directory {data} is not writable ({exc.strerror or exc}); choose another with --data")


def load_spec(scene: str):
    """A scene by name (configs/scenes/<name>.yaml) or a path to a scene YAML file."""
    if scene.endswith((".yaml", ".yml")) or "/" in scene:
        path = Path(scene)
        if not path.is_file():
            raise UserError(f"scene file not found: {path}")
        return spec_mod.load_scene_spec(path.stem, path)
    return spec_mod.load_scene_spec(scene)


def n_frames(scene_spec, profile) -> int:
    return min(profile.frames_for(scene_spec.name), scene_spec.frames_full)


def prepare(scene: str, profile: str, data: Path, lights: list[str] | None = None, *, spec=None,
            frames: int | None = None, test_views: int | None = None) -> SceneRun:
    """Validate the inputs, write env maps and transforms, and plan the frames (no rendering)."""
    spec = spec if spec is not None else load_spec(scene)
    prof = load_profile(profile).dataset
    light_specs = resolve_lights(lights)
    n = frames if frames is not None else n_frames(spec, prof)
    n_test = test_views if test_views is not None else prof.test_views
    if prof.static_timestep >= n:
        raise UserError(f"profile '{profile}': static_timestep {prof.static_timestep} needs more than {n} frames")
    maps = {s.name: lights_mod.prepare_envmap(s) for s in light_specs}  # read errors surface before any write
    data = Path(data)
    check_writable(data)
    plan = plan_scene(spec, n, n_test, prof.static_timestep, data / profile)
    hdr_paths: dict[str, Path] = {}
    for variant in (plan.dynamic_dir, plan.static_dir):
        for name, img in maps.items():
            hdr = layout.envmap_path(variant, name)
            envmap.write_hdr(hdr, img)  # deterministic bytes: rewriting an unchanged map changes nothing
            envmap.preview_png(hdr.with_suffix(".png"), img)
            hdr_paths.setdefault(name, hdr)
    settings = RenderSettings(
        resolution=prof.resolution, spp=prof.spp, gt_spp=gt_samples(prof.spp), seed=spec.seed,
        camera_angle_x=spec.camera.camera_angle_x,
        lights=tuple((name, sha256_file(hdr_paths[name])) for name in maps),
    )
    for variant, docs in plan.transforms(settings.camera_angle_x).items():
        for split, doc in docs.items():
            atomic_write_json(variant / f"transforms_{split}.json", doc)
    return SceneRun(spec, prof, light_specs, plan, settings, hdr_paths)


def worker_threads(jobs: int) -> int:
    """Cycles threads per worker: the cores shared out, so JOBS workers do not oversubscribe."""
    return max(1, usable_cores() // max(1, jobs))


def render_scene(scene: str, profile: str, data: Path, jobs: int = 1, lights: list[str] | None = None,
                 progress: bool = True, *, spec=None, frames: int | None = None,
                 test_views: int | None = None, on_rendered: Callable[[FrameJob, dict], None] | None = None) -> Path:
    """Render (or finish) both variants of ``scene``; returns the dynamic variant's directory.

    Each of the ``jobs`` worker processes builds the scene once and renders many frames. Files are
    byte-identical across runs, JOBS values, frame orders and interrupted/resumed runs (tests hold this:
    Cycles on CPU is deterministic given identical meshes, and every mesh is built in a fixed order).
    ``spec``, ``frames`` and ``test_views`` override the scene file and the profile (tests use them);
    ``on_rendered`` is called in this process after each frame a worker rendered.
    """
    if jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {jobs}")
    run = prepare(scene, profile, data, lights, spec=spec, frames=frames, test_views=test_views)
    spec_hash = run.spec.spec_hash()
    plan, settings = run.plan, run.settings
    pending = [j for j in plan.renders if not j.is_done(spec_hash, settings)]
    copies = [j for j in plan.copies if not j.is_done(spec_hash, settings)]
    variants = (plan.dynamic_dir, plan.static_dir)
    if not pending and not copies and all(layout.is_complete(v) for v in variants):
        return plan.dynamic_dir
    for v in variants:
        _write_dataset_json(v, run, spec_hash, complete=False)
        _remove_stale_temporaries(v)
    if pending:
        _render_frames(run, pending, spec_hash, jobs, progress, on_rendered)
    for j in copies:
        _copy_frame(j, settings)
    for v in variants:
        _write_dataset_json(v, run, spec_hash, complete=True)
    return plan.dynamic_dir


def _render_frames(run: SceneRun, pending: list[FrameJob], spec_hash: str, jobs: int, progress: bool,
                   on_rendered) -> None:
    n_workers = min(jobs, len(pending))
    ctx = multiprocessing.get_context("spawn")
    hdrs = {n: str(p) for n, p in run.hdr_paths.items()}
    init_args = (run.spec, spec_hash, run.settings, hdrs, worker_threads(n_workers))
    with make_progress(disable=not progress) as bar:
        pool = ProcessPoolExecutor(max_workers=n_workers, mp_context=ctx, initializer=render_worker.init_worker,
                                   initargs=init_args)
        task = bar.add_task(f"{run.spec.name} ({run.profile.name})", total=len(pending), rate="")
        futures = {pool.submit(render_worker.render_job, j): j for j in pending}
        t0 = time.perf_counter()
        done_count = 0
        try:
            remaining = set(futures)
            while remaining:
                finished, remaining = wait(remaining, return_when=FIRST_COMPLETED)
                for fut in finished:
                    try:
                        record = fut.result()
                    except BrokenProcessPool:
                        raise RuntimeError(f"a render worker died while rendering {futures[fut].label} "
                                           "(Blender crashed or the process was killed); run again to resume") from None
                    done_count += 1
                    rate = done_count / max(time.perf_counter() - t0, 1e-9)
                    bar.update(task, advance=1, rate=f"{rate:.2f} frames/s")
                    if on_rendered is not None:
                        on_rendered(futures[fut], record)
        except BaseException:
            _abort(pool)  # Ctrl-C or a failure: frames in flight are dropped (no record) and redone on resume
            raise
        pool.shutdown(wait=True)


def _abort(pool: ProcessPoolExecutor) -> None:
    """Stop now: cancel queued frames and terminate the workers instead of waiting for their frames."""
    for proc in list(getattr(pool, "_processes", {}).values()):  # no public API to stop running tasks
        if proc.is_alive():
            proc.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def _remove_stale_temporaries(variant: Path) -> None:
    """Temporary files (``.tmp-*``, ``*.gt.exr`` staging) left by a killed run are never finished files."""
    for p in list(variant.rglob(".tmp-*")) + list((variant / ".frames").rglob("*.gt.exr")):
        if p.is_file():
            p.unlink(missing_ok=True)


def _copy_frame(job: FrameJob, settings: RenderSettings) -> None:
    """A frame that shows exactly the view of an already rendered one: copy its files, then the record."""
    src = job.copy_of
    assert src is not None
    for s, d in zip(src.outputs(settings.light_names), job.outputs(settings.light_names)):
        with atomic_path(d) as tmp:
            shutil.copyfile(s, tmp)
    record = dict(src.read_record() or {})
    record["key"] = job.key(record.get("key", {}).get("spec_hash", ""), settings)
    record["file_path"] = job.file_path
    record["copied_from"] = src.label
    record["files"] = job.file_digests(settings.light_names)  # of the copies, as written
    atomic_write_json(job.record_path(), record)


def _write_dataset_json(variant: Path, run: SceneRun, spec_hash: str, complete: bool) -> None:
    plan, prof, settings = run.plan, run.profile, run.settings
    frames: dict[str, Any] = {}
    blender_version = None
    for j in plan.jobs:
        if j.scene_dir != variant:
            continue
        rec = j.read_record() if complete else None
        if rec:
            blender_version = blender_version or rec.get("blender_version")
            frames[j.file_path] = rec.get("seconds", {}) | ({"copied_from": rec["copied_from"]}
                                                              if "copied_from" in rec else {})
    is_static = variant == plan.static_dir
    doc = {
        "format": DATASET_FORMAT,
        "scene": run.spec.name,
        "variant": "static" if is_static else "dynamic",
        "static_timestep": prof.static_timestep,
        "static_time": plan.static_time,
        "spec_hash": spec_hash,
        "seed": run.spec.seed,
        "blender_version": blender_version,
        "profile": {"name": prof.name, "resolution": prof.resolution, "spp": prof.spp, "gt_spp": settings.gt_spp,
                    "denoised": prof.spp > 8, "frames": len(plan.times), "test_views": len(plan.test_c2w)},
        "lights": [{"name": s.name, "source": str(s.source), "rotation_deg": s.rotation_deg, "strength": s.strength,
                    "resolution": list(s.resolution), "hdr_sha256": h} for s, (_, h) in zip(run.lights, settings.lights)],
        "frame_seconds": frames,
        "complete": bool(complete),
    }
    atomic_write_json(variant / "dataset.json", doc)
