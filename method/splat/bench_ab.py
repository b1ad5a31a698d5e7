"""`python -m method.splat.bench_ab [--device cuda]`: the CUDA-specific rasterizer paths against the generic
ones, in one process, alternating (timings on shared machines drift; ratios taken this way do not).

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
from .bench import make_scene


def _configure(device: str, cuda_choices: bool) -> None:
    is_cuda = device.startswith("cuda")
    R.EXACT_SPAN_MAX[is_cuda] = 2 if cuda_choices else 12
    S.CUDA_PREFIX_SUMS = cuda_choices


def _step(params, cam, device):
    for p in params:
        p.grad = None
    out = R.rasterize(*params, cam, background=torch.ones(3, device=device))
    loss = out.features.sum() + out.depth_expected.sum() * 0.1 + out.distortion.sum() + out.normal.sum() \
        + (out.normal_from_depth * out.normal).sum()
    loss.backward()
    return out, [p.grad.clone() for p in params]


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = ap.parse_args(argv)
    cases = [(100, 20_000), (400, 200_000), (800, 300_000)] if args.device.startswith("cuda") else [(100, 20_000)]
    for size, n in cases:
        r = compare(size, n, args.device)
        print(f"{size} px, {n // 1000}k splats, {r['pairs']} pairs: before {r['before_s'] * 1e3:.1f} ms, after "
              f"{r['after_s'] * 1e3:.1f} ms (x{r['ratio']:.2f}); outputs moved {r['max_abs_feature_diff']:.1e}, "
              f"gradients {r['max_rel_grad_diff']:.1e} (relative)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
