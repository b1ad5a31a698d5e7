"""The one Adam every stage uses: torch's fused kernel where it runs, the per-tensor loop elsewhere.

torch's default Adam on the CPU updates each tensor with about eight separate ops; the fused kernel does
one pass per tensor. Over stage 1's six Gaussian tensors and the deformation network that is ~5 ms of a
~70 ms step on one thread against ~1-2 ms (BENCHMARKS.md, "Stage 1 at 1.16x more"). The update is the same
formula; only the order of its float operations differs (a run is another draw of its seed, as on
another CPU), and the optimiser's state dict is the same, so checkpoints resume either way."""
from __future__ import annotations

import torch


def fused_supported(params) -> bool:
    """Fused Adam runs on CPU and CUDA tensors of floating dtype (torch >= 2.4 on the CPU)."""
    return all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params)


def adam(groups, **kwargs) -> torch.optim.Adam:
    """torch.optim.Adam over ``groups`` (a list of tensors or of param-group dicts), fused where supported."""
    groups = list(groups)
    params = [p for g in groups for p in (g["params"] if isinstance(g, dict) else [g])]
    return torch.optim.Adam(groups, fused=fused_supported(params) or None, **kwargs)
