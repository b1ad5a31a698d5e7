"""Time the deformation network's forward + backward as a stage-1 iteration runs it: fp32 at every
Gaussian, bf16 at every Gaussian, and fp32 read at nodes and blended (``model.deform_nodes``).

On the CPU the network is most of a `small` stage-1 iteration (BENCHMARKS.md), so how it is evaluated
decides the stage's speed. The variants are timed interleaved, in one process, so their ratios hold on a
loaded machine. ``python -m method.model.bench --out bench/deform.json``
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

from lumibench.errors import UserError
from lumibench.io import atomic_write_json
from lumibench.machine import cpu_description
from method.checkpoints import build_net
from method.config import load_method_config
from method.model.deform import PRECISIONS
from method.model.nodes import MotionNodes


def time_deform(profile: str, gaussians: int, repeats: int, nodes: int | None = None, seed: int = 0) -> dict:
    """Median seconds of one forward + backward of ``profile``'s network over ``gaussians`` positions, per
    precision and read at ``nodes`` nodes (the same weights and inputs), the speed-ups over fp32, and the
    seconds one choice of the nodes takes (stage 1 re-chooses them at each count change and every 500
    iterations)."""
    m = load_method_config(profile)["model"]
    nodes = nodes or m["deform_nodes"] or 4096
    torch.manual_seed(seed)
    ref = build_net({**m, "mlp_precision": "fp32"})
    nets = {}
    for prec in PRECISIONS:
        nets[prec] = build_net({**m, "mlp_precision": prec})
        nets[prec].load_state_dict(ref.state_dict())
    x = torch.rand(gaussians, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1

    def step(net):
        xi = x.clone().requires_grad_()
        d_mu, d_rot, d_col = net(xi, 0.37)
        (d_mu.square().sum() + d_rot.sum() + d_col.sum()).backward()

    mn = MotionNodes(nodes)
    t0 = time.perf_counter()
    mn.choose(x)
    choose_s = time.perf_counter() - t0

    def step_nodes(net):
        xi = x.clone().requires_grad_()
        w = mn.weights(xi)
        d_mu, d_rot, d_col = (mn.blend(v, w) for v in net(mn.nodes, 0.37))
        (d_mu.square().sum() + d_rot.sum() + d_col.sum()).backward()

    variants = {**{p: (step, nets[p]) for p in PRECISIONS}, f"fp32_nodes{nodes}": (step_nodes, nets["fp32"])}
    times: dict[str, list[float]] = {k: [] for k in variants}
    for fn, net in variants.values():
        fn(net)  # warm-up (oneDNN picks its kernels on the first call)
    for _ in range(repeats):
        for k, (fn, net) in variants.items():
            t0 = time.perf_counter()
            fn(net)
            times[k].append(time.perf_counter() - t0)
    med = {k: sorted(v)[len(v) // 2] for k, v in times.items()}
    return {"profile": profile, "gaussians": gaussians, "nodes": nodes,
            "architecture": {k: m[k] for k in ("mlp_depth", "mlp_width", "mlp_skip", "pos_freqs", "time_net_out")},
            "seconds": med, "bf16_speedup": med["fp32"] / med["bf16"],
            "nodes_speedup": med["fp32"] / med[f"fp32_nodes{nodes}"], "nodes_choose_seconds": choose_s}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m method.model.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/deform.json", help="JSON file to write")
    ap.add_argument("--profile", default="small", help="whose model section (default small)")
    ap.add_argument("--gaussians", type=int, default=20_000, help="positions per call (default 20000, small's cap)")
    ap.add_argument("--nodes", type=int, default=None,
                    help="nodes of the blended variant (default: the profile's model.deform_nodes, else 4096)")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2, the CI machine)")
    ap.add_argument("--repeats", type=int, default=15, help="timed calls per precision (median reported)")
    args = ap.parse_args(argv)
    if min(args.gaussians, args.repeats, args.threads, 1 if args.nodes is None else args.nodes) < 1:
        raise UserError("--gaussians, --repeats, --threads and --nodes must be >= 1")
    torch.set_num_threads(args.threads)
    load = list(os.getloadavg())
    res = time_deform(args.profile, args.gaussians, args.repeats, args.nodes)
    res.update(device=f"cpu ({cpu_description()}, {os.cpu_count()} logical cores)", threads=args.threads,
               torch=torch.__version__, repeats=args.repeats, load_average_before=load,
               load_average_after=list(os.getloadavg()),
               command=" ".join(["python -m method.model.bench"] + list(argv if argv is not None else sys.argv[1:])))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(Path(args.out), res)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    from lumibench.errors import run_cli

    sys.exit(run_cli(main))
