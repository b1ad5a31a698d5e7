"""`python -m method.splat.bench_ab [--device cuda] [--trace-sweep]`: the CUDA-specific rasterizer paths
against the generic ones, in one process, alternating (timings on shared machines drift; ratios taken this
way do not); with --trace-sweep, the tracer's chunk sizes and DDA steps per round instead.

"before" = span groups exact up to 12 and aten segment_reduce sums (the CPU choices); "after" = the CUDA
choices (EXACT_SPAN_MAX, CUDA_PREFIX_SUMS). Prints medians, their ratio, and how far outputs and gradients
moved. On CPU both settings run the same code except the span grouping.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from . import rasterize as R
from . import segments as S
from .bench import make_scene, raster_loss, sync as _sync_device


def _configure(device: str, cuda_choices: bool) -> None:
    is_cuda = device.startswith("cuda")
    R.EXACT_SPAN_MAX[is_cuda] = 2 if cuda_choices else 12
    S.CUDA_PREFIX_SUMS = cuda_choices


def _step(params, cam, device):
    for p in params:
        p.grad = None
    out = R.rasterize(*params, cam, background=torch.ones(3, device=device))
    raster_loss(out).backward()
    return out, [p.grad.clone() for p in params]


def _sync(device: str) -> None:
    _sync_device(torch.device(device))


def compare(size: int, n: int, device: str, rounds: int = 8) -> dict:
    m, q, s, o, f, cam = make_scene(n, size, device=device)
    params = [t.clone().requires_grad_(True) for t in (m, q, s, o, f)]
    saved = (dict(R.EXACT_SPAN_MAX), S.CUDA_PREFIX_SUMS)
    try:
        res, times = {}, {False: [], True: []}
        for choice in (False, True):
            _configure(device, choice)
            res[choice] = _step(params, cam, device)
        for _ in range(rounds):
            for choice in (False, True):
                _configure(device, choice)
                _sync(device)
                t0 = time.perf_counter()
                _step(params, cam, device)
                _sync(device)
                times[choice].append(time.perf_counter() - t0)
    finally:
        R.EXACT_SPAN_MAX.update(saved[0])
        S.CUDA_PREFIX_SUMS = saved[1]
    (oa, ga), (ob, gb) = res[False], res[True]
    before, after = statistics.median(times[False][1:]), statistics.median(times[True][1:])
    return {"size": size, "splats": n, "pairs": oa.num_pairs, "pairs_after": ob.num_pairs,
            "before_s": before, "after_s": after, "ratio": after / before,
            "max_abs_feature_diff": float((oa.features - ob.features).detach().abs().max()),
            "max_rel_grad_diff": max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-12)) for a, b in zip(ga, gb))}


def trace_sweep(device: str, rounds: int = 3) -> list[dict]:
    """Tracer query time for each (candidate chunk, steps per round, ray chunk), interleaved per round."""
    from . import trace as T
    from .bench import make_trace_queries

    rows = []
    means, quats, scales, opac, feats, _ = make_scene(20_000, 100, device=device)
    accel = T.TraceAccel.build(means, quats, scales, opac)
    settings = [(c, s, r) for c in (1 << 20, 1 << 22, 1 << 24) for s in (8, 16, 32) for r in (1 << 17, 1 << 20)]
    name = "CUDA_CANDIDATE_CHUNK" if device.startswith("cuda") else "CANDIDATE_CHUNK"
    saved = getattr(T, name)
    try:
        for pts in (1024, 16384):
            o, d = make_trace_queries(means, quats, scales, pts, 64)
            times = {k: [] for k in settings}
            ref = T.trace(means, quats, scales, opac, feats, o, d, 0.0, accel=accel)
            for _ in range(rounds + 1):
                for c, s, r in settings:
                    setattr(T, name, c)
                    _sync(device)
                    t0 = time.perf_counter()
                    got = T.trace(means, quats, scales, opac, feats, o, d, 0.0, accel=accel, steps_per_round=s,
                                  ray_chunk=r)
                    _sync(device)
                    times[(c, s, r)].append(time.perf_counter() - t0)
                    assert torch.allclose(got[0], ref[0], atol=1e-5), (c, s, r)
            for (c, s, r), ts in times.items():
                rows.append({"rays": o.shape[0], "candidate_chunk": c, "steps_per_round": s, "ray_chunk": r,
                             "seconds": statistics.median(ts[1:])})
    finally:
        setattr(T, name, saved)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--trace-sweep", action="store_true", help="sweep the tracer's chunking instead")
    args = ap.parse_args(argv)
    if args.trace_sweep:
        for r in trace_sweep(args.device):
            print(f"rays {r['rays']}: candidate chunk 2^{r['candidate_chunk'].bit_length() - 1}, "
                  f"{r['steps_per_round']} steps/round, ray chunk 2^{r['ray_chunk'].bit_length() - 1}: "
                  f"{r['seconds'] * 1e3:.1f} ms")
        return 0
    cases = [(100, 20_000), (400, 200_000), (800, 300_000)] if args.device.startswith("cuda") else [(100, 20_000)]
    for size, n in cases:
        r = compare(size, n, args.device)
        print(f"{size} px, {n // 1000}k splats, {r['pairs']} pairs: before {r['before_s'] * 1e3:.1f} ms, after "
              f"{r['after_s'] * 1e3:.1f} ms (x{r['ratio']:.2f}); outputs moved {r['max_abs_feature_diff']:.1e}, "
              f"gradients {r['max_rel_grad_diff']:.1e} (relative)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
