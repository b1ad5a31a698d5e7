"""Generator benchmarks: seconds per frame (ground-truth pass and lit pass) per profile, the gain from
persistent data and from JOBS, and projected hours for whole datasets.

Timings are taken inside spawned worker processes (bpy must not load in this process: see
generator/render_worker.py), on the frames the dataset would render, after one warm-up frame (scene
sync, kernel load) that is reported separately.
"""
from __future__ import annotations

import multiprocessing
import os
import platform
import shutil
import statistics
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from lumibench.machine import cpu_description, usable_cores
from lumibench.profiles import load_profile

from . import pipeline, spec as spec_mod
from .jobs import RenderSettings, gt_samples, plan_scene


def _measure_in_worker(spec, settings: RenderSettings, hdr_paths: dict[str, str], scene_root: str, n_frames: int,
                       measure: int, threads: int, persistent: bool) -> dict[str, Any]:
    """Runs in a spawned process: build once, render 1 warm-up + ``measure`` frames, return timings."""
    from .render_worker import _silence_stdout, drop_blender_script_paths

    _silence_stdout()
    drop_blender_script_paths()
    from .blender.render_frame import FrameRenderer

    t0 = time.perf_counter()
    r = FrameRenderer(spec, settings, hdr_paths, threads=threads, persistent_data=persistent)
    build = time.perf_counter() - t0
    plan = plan_scene(spec, n_frames, 1, 0, Path(scene_root))
    train = [j for j in plan.jobs if j.split == "train" and j.scene_dir == plan.dynamic_dir]
    picks = [train[0]] + [train[(i + 1) * (len(train) - 1) // max(measure, 1)] for i in range(measure)]
    frames = []
    for j in picks:
        c0 = time.process_time()  # CPU seconds of all threads: robust to other load on the machine
        rec = r.render(j, spec.spec_hash())
        frames.append(rec["seconds"] | {"cpu": time.process_time() - c0})
    return {"build_s": build, "warmup": frames[0], "frames": frames[1:], "blender": r.blender_version}


def _summary(frames: list[dict]) -> dict[str, float]:
    gt = [f["gt"] for f in frames]
    post = [f["post"] for f in frames]
    lit = [v for f in frames for v in f["lit"].values()]
    total = [f["total"] for f in frames]
    cpu = [f["cpu"] for f in frames]
    return {"gt_s": statistics.median(gt), "post_s": statistics.median(post), "lit_s_per_light": statistics.median(lit),
            "frame_s": statistics.median(total), "frame_cpu_s": statistics.median(cpu), "n": len(frames)}


def measure_frames(scene: str, profile: str, workdir: Path, *, measure: int = 2, lights: list[str] | None = None,
                   persistent: bool = True, threads: int = 0) -> dict[str, Any]:
    """Median seconds of the GT pass, one lit pass and a whole frame (GT + every light) at ``profile``."""
    run = pipeline.prepare(scene, profile, workdir, lights, frames=max(measure + 1, 2), test_views=1)
    n = len(run.plan.times)
    hdrs = {k: str(v) for k, v in run.hdr_paths.items()}
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx) as pool:
        fut = pool.submit(_measure_in_worker, run.spec, run.settings, hdrs, str(workdir / profile), n, measure,
                          threads, persistent)
        res = fut.result()
    prof = run.profile
    return {"scene": scene, "profile": profile, "resolution": prof.resolution, "spp": prof.spp,
            "gt_spp": gt_samples(prof.spp), "denoised": prof.spp > 8, "lights": len(run.settings.lights),
            "persistent_data": persistent, "build_s": res["build_s"], "warmup_frame_s": res["warmup"]["total"],
            **_summary(res["frames"]), "blender": res["blender"]}


def compare_persistent_data(scene: str, profile: str, workdir: Path, rounds: int = 2) -> dict[str, Any]:
    """Persistent data off vs on, alternated in the same run so that the machine's load hits both alike."""
    runs: dict[str, list[dict[str, Any]]] = {"off": [], "on": []}
    for _ in range(rounds):
        for key, flag in (("off", False), ("on", True)):
            runs[key].append(measure_frames(scene, profile, workdir, measure=3, persistent=flag))
    off = min(runs["off"], key=lambda r: r["frame_s"])
    on = min(runs["on"], key=lambda r: r["frame_s"])
    return {"off": off, "on": on, "frame_speedup": off["frame_s"] / on["frame_s"],
            "rounds": rounds, "frame_s_all": {k: [r["frame_s"] for r in v] for k, v in runs.items()}}


def measure_jobs(scene: str, profile: str, workdir: Path, frames: int, test_views: int, jobs: int) -> dict[str, Any]:
    """Wall time of a fresh render_scene (both variants) with ``jobs`` workers, start-up included."""
    out = workdir / f"jobs{jobs}"
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    pipeline.render_scene(scene, profile, out, jobs=jobs, progress=False, frames=frames, test_views=test_views)
    wall = time.perf_counter() - t0
    renders = len(pipeline.prepare(scene, profile, out, frames=frames, test_views=test_views).plan.renders)
    return {"scene": scene, "profile": profile, "jobs": jobs, "frames": frames, "test_views": test_views,
            "renders": renders, "wall_s": wall, "s_per_render": wall / renders}


def renders_per_scene(scene: str, profile: str) -> int:
    """Distinct frames a scene needs: train (dynamic) + train (static) + test, minus the shared views."""
    spec = spec_mod.load_scene_spec(scene)
    prof = load_profile(profile).dataset
    n = pipeline.n_frames(spec, prof)
    return 2 * n - 1 + prof.test_views


def machine() -> dict[str, Any]:
    return {"cpu": cpu_description(), "cores": usable_cores(), "gpu": None, "python": platform.python_version(),
            "platform": platform.platform(), "load_average_at_start": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


DATASET_SCENES = ("jumpingjacks", "standup", "hook", "mouse", "spheres")


def run_bench(out: Path, *, quick: bool = False, progress_print=print) -> dict[str, Any]:
    """All generator benchmarks; returns (and the caller writes) the JSON document."""
    work = Path(tempfile.mkdtemp(prefix="lumibench-genbench-"))
    try:
        doc: dict[str, Any] = {"machine": machine(), "command": "python -m generator bench --out " + str(out)}
        per_profile = []
        for prof in ("ci", "small", "full"):
            progress_print(f"per-frame timing: spheres at {prof}")
            per_profile.append(measure_frames("spheres", prof, work / "frames", measure=1 if prof == "full" else 3))
        doc["per_frame"] = per_profile
        progress_print("persistent data: off vs on (spheres, small)")
        doc["persistent_data"] = compare_persistent_data("spheres", "small", work / "persist")
        scenes = [s for s in DATASET_SCENES if s in spec_mod.available_scenes()]
        progress_print(f"per-scene timing at small: {', '.join(scenes)}")
        doc["scenes_small"] = [measure_frames(s, "small", work / "scenes", measure=2) for s in scenes]
        progress_print("JOBS=1 vs JOBS=2 (spheres, small, 6 frames + 2 test views)")
        j1 = measure_jobs("spheres", "small", work / "jobs", 6, 2, 1)
        j2 = measure_jobs("spheres", "small", work / "jobs", 6, 2, 2)
        doc["jobs"] = {"1": j1, "2": j2, "speedup": j1["wall_s"] / j2["wall_s"]}
        doc["projection"] = _project(doc, scenes)
        doc["machine"]["load_average_at_end"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
        return doc
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _project(doc: dict[str, Any], scenes: list[str]) -> dict[str, Any]:
    """Hours for the five scenes: distinct frames x measured frame seconds (per scene at small; full scaled
    from the spheres full frame by each scene's small-profile ratio), for JOBS=1 and with the JOBS=2 gain."""
    small = {s["scene"]: s["frame_s"] for s in doc["scenes_small"]}
    small_cpu = {s["scene"]: s["frame_cpu_s"] for s in doc["scenes_small"]}
    full = next(p for p in doc["per_frame"] if p["profile"] == "full")
    full_spheres = full["frame_s"]
    speedup = doc["jobs"]["speedup"]
    out: dict[str, Any] = {}
    for prof in ("small", "full"):
        rows = {}
        for s in scenes:
            per_frame = small[s] if prof == "small" else full_spheres * small[s] / small["spheres"]
            n = renders_per_scene(s, prof)
            rows[s] = {"renders": n, "frame_s": per_frame, "hours_jobs1": n * per_frame / 3600.0}
        total = sum(r["hours_jobs1"] for r in rows.values())
        cpu_h = sum(renders_per_scene(s, prof) * (small_cpu[s] if prof == "small"
                                                  else full["frame_cpu_s"] * small_cpu[s] / small_cpu["spheres"])
                    for s in scenes) / 3600.0
        out[prof] = {"scenes": rows, "hours_jobs1": total, "hours_jobs2": total / speedup,
                     "cpu_hours": cpu_h, "hours_idle_2core": cpu_h / 2.0}
    return out


def markdown(doc: dict[str, Any]) -> str:
    """The numbers as the tables BENCHMARKS.md quotes."""
    m = doc["machine"]
    lines = [f"Machine: {m['cpu']}, {m['cores']} cores, no GPU; Blender {doc['per_frame'][0]['blender']} "
             f"(Cycles CPU). Command: `{doc['command']}`.", "",
             f"Load average {m.get('load_average_at_start')} at start, {m.get('load_average_at_end')} at end "
             "(other jobs shared the machine: wall seconds are inflated; CPU seconds are not).", "",
             "| profile | px | spp (GT spp) | denoised | GT pass s | lit pass s (per light) | frame s (GT + 4 lights + files) | frame CPU s | first frame s |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for p in doc["per_frame"]:
        lines.append(f"| {p['profile']} | {p['resolution']} | {p['spp']} ({p['gt_spp']}) | {'yes' if p['denoised'] else 'no'} "
                     f"| {p['gt_s']:.3f} | {p['lit_s_per_light']:.3f} | {p['frame_s']:.3f} | {p['frame_cpu_s']:.2f} "
                     f"| {p['warmup_frame_s']:.2f} |")
    pd = doc["persistent_data"]
    j = doc["jobs"]
    lines += ["", f"Persistent data (small, spheres): frame {pd['off']['frame_s']:.3f} s off -> {pd['on']['frame_s']:.3f} s on "
              f"(x{pd['frame_speedup']:.2f}).",
              f"JOBS (small, spheres, {j['1']['renders']} distinct frames, start-up included): JOBS=1 {j['1']['wall_s']:.1f} s, "
              f"JOBS=2 {j['2']['wall_s']:.1f} s (x{j['speedup']:.2f}).", "",
              "| scene | frame s at small | frame CPU s at small | small: frames, hours (JOBS=1) | full: frames, hours (JOBS=1) |",
              "| --- | --- | --- | --- | --- |"]
    pr = doc["projection"]
    cpu = {x["scene"]: x["frame_cpu_s"] for x in doc["scenes_small"]}
    for s, row in pr["small"]["scenes"].items():
        f = pr["full"]["scenes"][s]
        lines.append(f"| {s} | {row['frame_s']:.2f} | {cpu[s]:.2f} | {row['renders']}, {row['hours_jobs1']:.2f} "
                     f"| {f['renders']}, {f['hours_jobs1']:.1f} |")
    lines += ["", f"All five scenes (wall, as measured): small {pr['small']['hours_jobs1']:.2f} h (JOBS=1), "
              f"{pr['small']['hours_jobs2']:.2f} h (JOBS=2); full {pr['full']['hours_jobs1']:.1f} h (JOBS=1), "
              f"{pr['full']['hours_jobs2']:.1f} h (JOBS=2). From CPU seconds on an idle 2-core machine (CPU / 2): "
              f"small {pr['small']['hours_idle_2core']:.2f} h, full {pr['full']['hours_idle_2core']:.1f} h."]
    return "\n".join(lines) + "\n"
