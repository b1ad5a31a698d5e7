"""`python -m method.splat.bench --out bench/latest.json`: rasterizer and tracer timings (medians), scaling
charts and a memory-scaling measurement.

Scenes: N random splats in the box [-1, 1]^3, random orientations, opacities uniform in [0.1, 1], seen by
a camera at radius 4 (Blender's default 39.6 degree FOV); scales log-normal around the size whose 1-sigma
footprint is about one pixel at the box centre, so a 3-sigma footprint spans a few pixels, as after training.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

# OpenMP threads spin while waiting by default; on a shared, loaded machine (CI, other jobs) that made
# 2-thread runs ~4x slower than 1 thread in our measurements. Passive waiting is set unless the user
# chose a policy; it must happen before torch loads its OpenMP runtime. Recorded in the result.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from lumibench.machine import cpu_description
from lumibench.errors import UserError, run_cli

from .camera import Camera

FOV_X = 0.6911112070083618  # Blender default (50 mm lens, 36 mm sensor)


def make_scene(n: int, size: int, seed: int = 0, channels: int = 3, device="cpu", dtype=torch.float32,
               sigma_px: float = 1.0, ref_size: int | None = None):
    """Random splats in the scene box and a camera at radius 4; see the module docstring.

    The median 1-sigma footprint is ``sigma_px`` pixels in an image ``ref_size`` (default ``size``) wide,
    so a fixed ``ref_size`` keeps the world scene fixed while the resolution changes."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2.0 - 1.0)
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=1, keepdim=True)
    focal = 0.5 * (ref_size or size) / math.tan(0.5 * FOV_X)
    s0 = sigma_px * 4.0 / focal
    scales = s0 * torch.exp(0.5 * torch.randn(n, 2, generator=g))
    opac = 0.1 + 0.9 * torch.rand(n, generator=g)
    feats = torch.rand(n, channels, generator=g)
    cam = Camera.look_at((4.0 * math.cos(0.6), 4.0 * math.sin(0.6), 1.2), (0.0, 0.0, 0.0), size, size,
                         camera_angle_x=FOV_X, device=device, dtype=dtype)
    to = dict(device=device, dtype=dtype)
    return means.to(**to), quats.to(**to), scales.to(**to), opac.to(**to), feats.to(**to), cam


def make_surface_scene(n: int, seed: int = 0, device="cpu", dtype=torch.float32):
    """Splats lying on surfaces, as a trained scene has them: 40 % on a ground square, 60 % on three
    spheres, tangent to the surface, sized to cover it about twice, opacities uniform in [0.6, 1]."""
    g = torch.Generator().manual_seed(seed)
    n_ground = int(0.4 * n)
    n_sph = n - n_ground
    ground = torch.cat([torch.rand(n_ground, 2, generator=g) * 3.0 - 1.5, torch.full((n_ground, 1), -0.8)], 1)
    g_normal = torch.tensor([0.0, 0.0, 1.0]).expand(n_ground, 3)
    centres = torch.tensor([[-0.6, -0.3, -0.3], [0.5, 0.2, -0.35], [0.0, 0.7, 0.0]])
    radii = torch.tensor([0.5, 0.45, 0.6])
    which = torch.randint(0, 3, (n_sph,), generator=g)
    v = torch.randn(n_sph, 3, generator=g)
    v = v / v.norm(dim=1, keepdim=True)
    sph = centres[which] + radii[which, None] * v
    means = torch.cat([ground, sph], 0)
    normals = torch.cat([g_normal, v], 0)
    # quaternion whose rotation takes +z to the normal, with a random twist about it
    z = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)
    axis = torch.linalg.cross(z, normals)
    s_ = axis.norm(dim=1, keepdim=True)
    c_ = (z * normals).sum(1, keepdim=True)
    half = torch.atan2(s_, c_) / 2
    axis = torch.where(s_ > 1e-8, axis / s_.clamp_min(1e-8), torch.tensor([1.0, 0.0, 0.0]).expand(n, 3))
    q_align = torch.cat([torch.cos(half), torch.sin(half) * axis], 1)
    tw = torch.rand(n, 1, generator=g) * math.pi
    q_twist = torch.cat([torch.cos(tw), torch.zeros(n, 2), torch.sin(tw)], 1)  # about local z
    w1, v1 = q_align[:, :1], q_align[:, 1:]
    w2, v2 = q_twist[:, :1], q_twist[:, 1:]
    quats = torch.cat([w1 * w2 - (v1 * v2).sum(1, keepdim=True), w1 * v2 + w2 * v1 + torch.linalg.cross(v1, v2)], 1)
    area = 9.0 + float((4 * math.pi * radii ** 2).sum())
    s0 = math.sqrt(2.0 * area / n / math.pi)
    scales = s0 * torch.exp(0.3 * torch.randn(n, 2, generator=g))
    opac = 0.6 + 0.4 * torch.rand(n, generator=g)
    feats = torch.rand(n, 3, generator=g)
    to = dict(device=device, dtype=dtype)
    return means.to(**to), quats.to(**to), scales.to(**to), opac.to(**to), feats.to(**to)


def make_trace_queries(means, quats, scales, n_points: int, n_dirs: int, seed: int = 1):
    """Surface points on random splats, each with its own hemisphere directions around the splat normal
    (as stage 2 does per pixel), origins offset by 0.05 along the direction."""
    from .splats import quat_to_rotmat

    g = torch.Generator().manual_seed(seed)
    dev, dt = means.device, means.dtype
    pick = torch.randint(0, means.shape[0], (n_points,), generator=g).to(dev)
    rot = quat_to_rotmat(quats[pick])
    uv = torch.randn(n_points, 2, generator=g).to(dev, dt) * 0.5
    pts = means[pick] + rot[:, :, 0] * (scales[pick, :1] * uv[:, :1]) + rot[:, :, 1] * (scales[pick, 1:] * uv[:, 1:])
    nrm = rot[:, :, 2]
    d = torch.randn(n_points, n_dirs, 3, generator=g).to(dev, dt)
    d = d / d.norm(dim=-1, keepdim=True)
    d = torch.where((d * nrm[:, None]).sum(-1, keepdim=True) < 0, -d, d)
    origins = (pts[:, None] + 0.05 * d).reshape(-1, 3)
    return origins, d.reshape(-1, 3)


def sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize()


def raster_loss(out):
    """A scalar that uses every rasterizer output, so the backward pass covers all of them."""
    return out.features.sum() + out.depth_expected.sum() * 0.1 + out.distortion.sum() + out.normal.sum() \
        + (out.normal_from_depth * out.normal).sum()


def time_raster(n: int, size: int, repeats: int, device, warmup: int = 1, ref_size: int | None = None,
                backend: str | None = None):
    """Median seconds of rasterize + backward of a loss using every output; also the pair count."""
    from functools import partial

    from .rasterize import rasterize

    rasterize = partial(rasterize, backend=backend)

    means, quats, scales, opac, feats, cam = make_scene(n, size, device=device, ref_size=ref_size)
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
    times, cpu, pairs = [], [], 0
    for i in range(warmup + repeats):
        for p in params:
            p.grad = None
        sync(torch.device(device))
        t0 = time.perf_counter()
        c0 = time.process_time()
        out = rasterize(*params, cam, background=torch.ones(3, device=device))
        raster_loss(out).backward()
        sync(torch.device(device))
        if i >= warmup:
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        pairs = out.num_pairs
    return statistics.median(times), pairs, statistics.median(cpu), min(times)


def time_trace(n: int, n_points: int, n_dirs: int, repeats: int, device, warmup: int = 1,
               cell_factor: float | None = None, surfaces: bool = False, backend: str | None = None,
               features: bool = True) -> dict:
    """Median build and query seconds (query: transmittance and features, forward only; ``features``
    False: the transmittance alone, as relighting's visibility asks for it)."""
    from functools import partial

    from .trace import TraceAccel, trace

    trace = partial(trace, backend=backend)

    if surfaces:
        means, quats, scales, opac, feats = make_surface_scene(n, device=device)
    else:
        means, quats, scales, opac, feats, _ = make_scene(n, 100, device=device)
    origins, dirs = make_trace_queries(means, quats, scales, n_points, n_dirs)
    cell = None
    if cell_factor is not None:
        k = torch.sqrt(2.0 * torch.log((opac / 0.01).clamp_min(1.0)))
        cell = cell_factor * float((k * scales.max(1).values).median())
    build, query, cpu = [], [], []
    for i in range(warmup + repeats):
        sync(torch.device(device))
        t0 = time.perf_counter()
        c0 = time.process_time()
        accel = TraceAccel.build(means, quats, scales, opac, cell_size=cell)
        sync(torch.device(device))
        t1 = time.perf_counter()
        trans, _ = trace(means, quats, scales, opac, feats if features else None, origins, dirs, 0.0, accel=accel)
        sync(torch.device(device))
        t2 = time.perf_counter()
        if i >= warmup:
            build.append(t1 - t0)
            query.append(t2 - t1)
            cpu.append(time.process_time() - c0)
    return dict(build=statistics.median(build), query=statistics.median(query), query_min=min(query),
                cpu_seconds=statistics.median(cpu),
                mean_visibility=float(trans.mean()), cells=list(accel.res), entries=int(accel.entries.numel()))


def run_backends(repeats: int) -> dict:
    """The compiled CPU backend against the torch path, alternated in one run so that the ratios share the
    machine's load: rasterize + backward at 100 and 128 px (20k splats), the tracer query (1024 points x
    64 directions, 20k splats, random volume and surfaces; and visibility alone on the surfaces), and the compiled kernels' share of a step."""
    from lumibench.progress import track

    res: dict = {"raster": [], "trace": [], "visibility": []}
    cases = [("raster", 100), ("raster", 128), ("trace", False), ("trace", True), ("visibility", True)]
    for kind, arg in track(cases, description="backends"):
        t: dict = {"torch": [], "numba": []}
        for _ in range(repeats):  # alternate: each round times both
            for be in ("torch", "numba"):
                if kind == "raster":
                    sec, pairs, _, _ = time_raster(20_000, arg, 1, "cpu", backend=be)
                else:
                    sec = time_trace(20_000, 1024, 64, 1, "cpu", surfaces=arg, backend=be,
                                     features=kind == "trace")["query"]
                t[be].append(sec)
        row = {"torch": statistics.median(t["torch"]), "numba": statistics.median(t["numba"])}
        row["speedup"] = row["torch"] / row["numba"]
        if kind == "raster":
            row.update(size=arg, splats=20_000, pairs=pairs, ns_per_pair_numba=row["numba"] / pairs * 1e9)
        else:
            row.update(scene="surfaces" if arg else "random volume", points=1024, dirs=64, splats=20_000,
                       features=kind == "trace")
        res[kind].append(row)
    res["raster_kernels"] = raster_kernel_split(128, repeats)
    res["compile"] = numba_compile_seconds()
    return res


def raster_kernel_split(size: int, repeats: int) -> dict:
    """Where a compiled rasterize + backward step goes at ``size`` px / 20k splats: the kernels (projection,
    compositing; forward and backward) and everything else (torch ops, conversions), from the profiler."""
    from torch.profiler import profile

    from .rasterize import rasterize

    means, quats, scales, opac, feats, cam = make_scene(20_000, size)
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
    for _ in range(2):
        raster_loss(rasterize(*params, cam, background=torch.ones(3), backend="numba")).backward()
    t0 = time.perf_counter()
    with profile() as prof:
        for _ in range(repeats):
            out = rasterize(*params, cam, background=torch.ones(3), backend="numba")
            raster_loss(out).backward()
    total = (time.perf_counter() - t0) / repeats
    ev = {e.key: e.cpu_time_total / 1e6 / repeats for e in prof.key_averages()}
    keys = {"composite forward": "_RasterRows", "composite backward": "_RasterRowsBackward",
            "projection forward": "_ProjectRows", "projection backward": "_ProjectRowsBackward"}
    split = {name: ev.get(k, 0.0) for name, k in keys.items()}
    split["other (torch, profiler overhead)"] = max(0.0, total - sum(split.values()))
    return {"size": size, "splats": 20_000, "pairs": out.num_pairs, "seconds_per_step_profiled": total,
            "split_s": split,
            "ns_per_pair": {k: v / out.num_pairs * 1e9 for k, v in split.items() if k.startswith("composite")}}


def numba_compile_seconds() -> dict:
    """First-call seconds of a rasterize + backward and a trace in fresh processes: with an empty numba cache
    (compiling every kernel) and again with the cache that run left (loading them)."""
    import subprocess
    import tempfile

    code = (
        "import time, torch; t0 = time.perf_counter()\n"
        "from method.splat.bench import make_scene, make_trace_queries, raster_loss\n"
        "from method.splat.rasterize import rasterize\n"
        "from method.splat.trace import trace\n"
        "m, q, s, o, f, cam = make_scene(2000, 32)\n"
        "p = [t.requires_grad_(True) for t in (m, q, s, o, f)]\n"
        "t1 = time.perf_counter(); raster_loss(rasterize(*p, cam, backend='numba')).backward()\n"
        "t2 = time.perf_counter(); org, d = make_trace_queries(m, q, s, 16, 8)\n"
        "trace(m.detach(), q.detach(), s.detach(), o.detach(), f.detach(), org, d, backend='numba')\n"
        "print(t2 - t1, time.perf_counter() - t2, t1 - t0)\n"
    )
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("cold", "warm"):
            r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env,
                               cwd=str(Path(__file__).resolve().parents[2]))
            raster, tr, imports = (float(v) for v in r.stdout.strip().splitlines()[-1].split())
            out[label] = {"raster_first_call_s": raster, "trace_first_call_s": tr, "imports_s": imports}
    return out


def peak_rss_mb(n: int, size: int, ref_size: int | None) -> dict:
    """Working memory of one rasterize + backward in a fresh process: the peak resident set size above
    the resident size just before the call (peak reset through /proc/self/clear_refs, Linux)."""
    code = (
        "import torch; torch.set_num_threads(2)\n"
        "from method.splat.bench import make_scene\n"
        "from method.splat.rasterize import rasterize\n"
        f"m, q, s, o, f, cam = make_scene({n}, {size}, ref_size={ref_size!r})\n"
        "p = [t.requires_grad_(True) for t in (m, q, s, o, f)]\n"
        "rasterize(*p, cam)\n"  # warm-up: first-call allocations of torch itself are not ours
        "def kb(key):\n"
        "    return int([l for l in open('/proc/self/status') if l.startswith(key)][0].split()[1])\n"
        "open('/proc/self/clear_refs', 'w').write('5')\n"
        "before = kb('VmRSS:')\n"
        "out = rasterize(*p, cam)\n"
        "(out.features.sum() + out.distortion.sum() + out.normal.sum() + out.depth_expected.sum()).backward()\n"
        "print(before, kb('VmHWM:'), out.num_pairs)\n"
    )
    import subprocess

    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=str(Path(__file__).resolve().parents[2]))
    before, peak, pairs = (int(v) for v in res.stdout.strip().splitlines()[-1].split())
    return {"splats": n, "size": size, "pixels": size * size, "fixed_scene": ref_size is not None,
            "pairs": pairs, "working_mb": (peak - before) / 1024.0}


def run_trace(device: str, repeats: int) -> dict:
    """The tracer keys: random volume and splats on surfaces (also alone: ``--trace-only``)."""
    res: dict = {}
    tr = time_trace(20_000, 1024, 64, repeats, device)
    res["trace_1024pts_64dirs_20k"] = tr["query"]
    res["trace_build_20k"] = tr["build"]
    res["trace_detail"] = tr
    ts = time_trace(20_000, 1024, 64, repeats, device, surfaces=True)
    res["trace_1024pts_64dirs_20k_surfaces"] = ts["query"]
    res["trace_detail_surfaces"] = ts
    return res


def run_trace_scaling(device: str, repeats: int, splats=(20_000, 100_000, 300_000),
                      points=(1024, 4096, 16384), n_dirs: int = 64) -> list[dict]:
    """Tracer query time against splat and ray counts (random volume, ``n_dirs`` directions per point)."""
    from lumibench.progress import track

    rows = []
    for n, pts in track([(n, p) for n in splats for p in points], description="trace scaling"):
        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats(device)
        tr = time_trace(n, pts, n_dirs, repeats, device)
        rows.append({"splats": n, "rays": pts * n_dirs, "build": tr["build"], "query": tr["query"],
                     "mrays_per_s": pts * n_dirs / tr["query"] / 1e6, "mean_visibility": tr["mean_visibility"]})
        if device.startswith("cuda"):
            rows[-1]["cuda_peak_mb"] = torch.cuda.max_memory_allocated(device) / 2 ** 20
    return rows


def run_all(device: str, repeats: int, quick: bool, out_path: Path) -> dict:
    """All measurements; writes the charts beside ``out_path``."""
    from lumibench.progress import track

    res: dict = {"unit": "seconds (median)", "repeats": repeats}
    keyed = [(100, 20_000)] if quick else [(100, 20_000), (200, 50_000), (400, 200_000)]
    if device.startswith("cuda") and not quick:
        keyed.append((800, 300_000))  # the paper's training size (NeRF-synthetic 800 px, ~300k splats)
    splat_series = [5_000, 10_000, 20_000] if quick else [5_000, 10_000, 20_000, 40_000, 80_000, 160_000]
    pixel_series = [50, 100] if quick else [50, 100, 200, 400]
    jobs = [("key", s, n) for s, n in keyed] + [("splats", 100, n) for n in splat_series] \
        + [("pixels", s, 20_000) for s in pixel_series]
    scaling = {"vs_splats_at_100px": [], "vs_pixels_at_20k_fixed_scene": []}
    for kind, size, n in track(jobs, description="raster"):
        reps = max(1, repeats if size * size * max(n, 20_000) <= 200 * 200 * 50_000 else repeats // 2)
        t, pairs, cpu, tmin = time_raster(n, size, reps, device, ref_size=100 if kind == "pixels" else None)
        row = {"pixels": size * size, "size": size, "splats": n, "seconds": t, "seconds_min": tmin, "pairs": pairs,
               "cpu_seconds": cpu}
        if device.startswith("cuda"):
            row["cuda_peak_mb"] = torch.cuda.max_memory_allocated(device) / 2 ** 20
            torch.cuda.reset_peak_memory_stats(device)
        if kind == "key":
            res[f"raster_fwdbwd_{size}px_{n // 1000}k"] = t
            res.setdefault("raster_detail", {})[f"{size}px_{n // 1000}k"] = row
        elif kind == "splats":
            scaling["vs_splats_at_100px"].append(row)
        else:
            scaling["vs_pixels_at_20k_fixed_scene"].append(row)
    res["raster_scaling"] = scaling
    res.update(run_trace(device, repeats))
    if not quick:
        sweep = []
        for fac in track([0.25, 0.5, 1.0, 2.0], description="trace cell sweep"):
            r = time_trace(20_000, 1024, 64, max(1, repeats // 2), device, cell_factor=fac)
            sweep.append({"cell_over_median_radius": fac, **r})
        res["trace_cell_sweep"] = sweep
    if device == "cpu":
        cases = [(20_000, 100, 100), (20_000, 200, 100), (20_000, 400, 100),
                 (40_000, 100, None), (80_000, 100, None), (160_000, 100, None)]
        mem = [peak_rss_mb(n, size, ref) for n, size, ref in track(cases[:2] if quick else cases, description="memory")]
        for r in mem:
            r["bytes_per_pair"] = r["working_mb"] * 2 ** 20 / max(1, r["pairs"])
        res["memory"] = mem
    _chart(res, out_path.with_name("raster_scaling.png"), _device_name(device))
    return res


def _chart(res: dict, path: Path, label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lumibench.io import atomic_path

    sc = res["raster_scaling"]
    fig, axes = plt.subplots(1, 3 if "memory" in res else 2, figsize=(13, 3.8))
    a = sc["vs_splats_at_100px"]
    axes[0].loglog([r["splats"] for r in a], [r["seconds"] for r in a], "o-", label="median")
    axes[0].loglog([r["splats"] for r in a], [r["seconds_min"] for r in a], "v:", label="min")
    axes[0].legend(fontsize=7)
    axes[0].set(xlabel="splats (100 x 100 px)", ylabel="fwd + bwd seconds", title="time vs splat count")
    b = sc["vs_pixels_at_20k_fixed_scene"]
    axes[1].loglog([r["pixels"] for r in b], [r["seconds"] for r in b], "o-", label="median")
    axes[1].loglog([r["pixels"] for r in b], [r["seconds_min"] for r in b], "v:", label="min")
    axes[1].legend(fontsize=7)
    axes[1].set(xlabel="pixels (20k splats, same scene)", ylabel="fwd + bwd seconds", title="time vs pixel count")
    for ax, rows in ((axes[0], a), (axes[1], b)):
        for r in rows:
            ax.annotate(f"{r['pairs'] / 1e6:.2f}M pairs", (r["splats"] if ax is axes[0] else r["pixels"], r["seconds"]),
                        fontsize=7, textcoords="offset points", xytext=(3, -10))
        ax.grid(True, which="both", alpha=0.3)
    if "memory" in res:
        m = res["memory"]
        fixed = [r for r in m if r["fixed_scene"]]
        more = [r for r in m if not r["fixed_scene"]]
        axes[2].plot([r["pairs"] / 1e6 for r in fixed], [r["working_mb"] for r in fixed], "o-",
                     label="20k splats, 100-400 px")
        axes[2].plot([r["pairs"] / 1e6 for r in more], [r["working_mb"] for r in more], "s-",
                     label="40k-160k splats, 100 px")
        axes[2].set(xlabel="(pixel, splat) pairs (millions)", ylabel="peak working memory (MiB)",
                    title="memory vs pairs")
        axes[2].grid(True, alpha=0.3)
        axes[2].legend(fontsize=7)
    fig.suptitle(f"2DGS rasterizer, {label}", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m method.splat.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/latest.json", help="JSON file to write (a PNG chart goes beside it)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2, the CI machine)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case (median reported)")
    ap.add_argument("--quick", action="store_true", help="small cases only (smoke test)")
    ap.add_argument("--trace-only", action="store_true", help="only the tracer keys (no rasterizer, sweep, chart)")
    ap.add_argument("--backends", action="store_true",
                    help="only the compiled CPU backend against the torch path (ratios, kernel split, compile time)")
    ap.add_argument("--trace-scaling", action="store_true",
                    help="also time the tracer at 20k-300k splats and 65k-1M rays (minutes on a CPU)")
    args = ap.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda requested but torch sees no CUDA device; use --device cpu")
    if args.device not in ("cpu",) and not args.device.startswith("cuda"):
        raise UserError(f"--device must be cpu or cuda, got {args.device!r}")
    if args.repeats < 1 or args.threads < 1:
        raise UserError("--repeats and --threads must be >= 1")
    torch.set_num_threads(args.threads)
    out_path = Path(args.out)
    dev = args.device
    load_before = list(os.getloadavg())
    result = {"device": _device_name(dev), "threads": torch.get_num_threads()}
    if args.backends:
        if dev != "cpu":
            raise UserError("--backends compares the CPU backends; use --device cpu")
        result.update({"unit": "seconds (median)", "repeats": args.repeats, "backends": run_backends(args.repeats)})
    elif args.trace_only:
        result.update({"unit": "seconds (median)", "repeats": args.repeats}, **run_trace(dev, args.repeats))
    else:
        result.update(run_all(dev, args.repeats, args.quick, out_path))
    if args.trace_scaling:
        result["trace_scaling"] = run_trace_scaling(dev, max(1, args.repeats // 2))
    result.update(device=_device_name(dev), threads=torch.get_num_threads(), torch=torch.__version__,
                  omp_wait_policy=os.environ.get("OMP_WAIT_POLICY"),
                  python=platform.python_version(), command=" ".join(["python -m method.splat.bench"] + list(argv or sys.argv[1:])))
    from lumibench.io import atomic_write_json

    result["load_average_before"] = load_before
    result["load_average_after"] = list(os.getloadavg())
    atomic_write_json(out_path, result)
    print(json.dumps({k: v for k, v in result.items() if not isinstance(v, (dict, list))}, indent=1))
    return 0


def _device_name(dev: str) -> str:
    if dev.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(dev))
    return f"cpu ({cpu_description()}, {os.cpu_count()} logical cores)"


if __name__ == "__main__":
    sys.exit(run_cli(main))
