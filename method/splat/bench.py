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

import torch

from lumibench.errors import UserError, run_cli

from .camera import Camera

FOV_X = 0.6911112070083618  # Blender default (50 mm lens, 36 mm sensor)


def make_scene(n: int, size: int, seed: int = 0, channels: int = 3, device="cpu", dtype=torch.float32,
               sigma_px: float = 1.0):
    """Random splats in the scene box and a camera at radius 4; see the module docstring."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2.0 - 1.0)
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=1, keepdim=True)
    focal = 0.5 * size / math.tan(0.5 * FOV_X)
    s0 = sigma_px * 4.0 / focal
    scales = s0 * torch.exp(0.5 * torch.randn(n, 2, generator=g))
    opac = 0.1 + 0.9 * torch.rand(n, generator=g)
    feats = torch.rand(n, channels, generator=g)
    cam = Camera.look_at((4.0 * math.cos(0.6), 4.0 * math.sin(0.6), 1.2), (0.0, 0.0, 0.0), size, size,
                         camera_angle_x=FOV_X, device=device, dtype=dtype)
    to = dict(device=device, dtype=dtype)
    return means.to(**to), quats.to(**to), scales.to(**to), opac.to(**to), feats.to(**to), cam


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


def _sync(dev):
    if dev.type == "cuda":
        torch.cuda.synchronize()


def time_raster(n: int, size: int, repeats: int, device, warmup: int = 1) -> tuple[float, int]:
    from .rasterize import rasterize

    means, quats, scales, opac, feats, cam = make_scene(n, size, device=device)
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
    times, pairs = [], 0
    for i in range(warmup + repeats):
        for p in params:
            p.grad = None
        _sync(torch.device(device))
        t0 = time.perf_counter()
        out = rasterize(*params, cam, background=torch.ones(3, device=device))
        loss = out.features.sum() + out.depth_expected.sum() * 0.1 + out.distortion.sum() + out.normal.sum() \
            + (out.normal_from_depth * out.normal).sum()
        loss.backward()
        _sync(torch.device(device))
        if i >= warmup:
            times.append(time.perf_counter() - t0)
        pairs = out.num_pairs
    return statistics.median(times), pairs


def time_trace(n: int, n_points: int, n_dirs: int, repeats: int, device, warmup: int = 1) -> dict:
    from .trace import TraceAccel, trace

    means, quats, scales, opac, feats, _ = make_scene(n, 100, device=device)
    origins, dirs = make_trace_queries(means, quats, scales, n_points, n_dirs)
    build, query = [], []
    for i in range(warmup + repeats):
        _sync(torch.device(device))
        t0 = time.perf_counter()
        accel = TraceAccel.build(means, quats, scales, opac)
        _sync(torch.device(device))
        t1 = time.perf_counter()
        trans, _ = trace(means, quats, scales, opac, feats, origins, dirs, 0.0, accel=accel)
        _sync(torch.device(device))
        t2 = time.perf_counter()
        if i >= warmup:
            build.append(t1 - t0)
            query.append(t2 - t1)
    return dict(build=statistics.median(build), query=statistics.median(query),
                mean_visibility=float(trans.mean()), cells=list(accel.res), entries=int(accel.entries.numel()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m method.splat.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/latest.json", help="JSON file to write (a PNG chart goes beside it)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2, the CI machine)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case (median reported)")
    ap.add_argument("--quick", action="store_true", help="small cases only (smoke test)")
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
    from .bench_report import run_all

    result = run_all(dev, args.repeats, args.quick, out_path)
    result.update(device=_device_name(dev), threads=torch.get_num_threads(), torch=torch.__version__,
                  python=platform.python_version(), command=" ".join(["python -m method.splat.bench"] + list(argv or sys.argv[1:])))
    from lumibench.io import atomic_write_json

    atomic_write_json(out_path, result)
    print(json.dumps({k: v for k, v in result.items() if not isinstance(v, (dict, list))}, indent=1))
    return 0


def _device_name(dev: str) -> str:
    if dev.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(dev))
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"cpu ({cpu}, {os.cpu_count()} logical cores)"


if __name__ == "__main__":
    sys.exit(run_cli(main))
