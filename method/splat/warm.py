"""Compile the Numba kernels into their on-disk cache once, at `make setup`, so a user's first `make demo`
or training does not spend its first minute compiling (61 s on an idle 2-core AVX2 box; BENCHMARKS.md,
"make demo on an idle box"). Every kernel takes float64 / int64 arrays and plain scalars (raster_numba.as_f64),
so one call of each on a tiny scene compiles the signatures that training, relighting and the predictions
use. ``python -m method.splat.warm``; a no-op without Numba.
"""
from __future__ import annotations

import sys
import time

import numpy as np
import torch


def kernels() -> dict:
    """The compiled kernels by name: every Numba dispatcher of the two kernel modules that is not an inlined
    helper (a leading underscore: compiled into its callers, never on its own)."""
    from numba.core.registry import CPUDispatcher

    from method import ssim_numba
    from method.model import basis_numba, blend_numba
    from method.shading import quadrature_numba
    from method.splat import depth_normals_numba, raster_numba, trace_numba

    return {f"{mod.__name__.rsplit('.', 1)[-1]}.{name}": f
            for mod in (raster_numba, depth_normals_numba, trace_numba, blend_numba, basis_numba, quadrature_numba,
                        ssim_numba)
            for name, f in vars(mod).items() if isinstance(f, CPUDispatcher) and not name.startswith("_")}


def warm() -> list[str]:
    """Run each compiled kernel once (raster forward + backward with screen offsets, visibility and hit
    tracing, the nodes' blend, the motion bases' blend, the diffuse quadrature, the training SSIM); return the names of the kernels now compiled. Raises ImportError without Numba."""
    import numba  # noqa: F401  (the point: nothing to warm without it)

    from method.splat.bench import make_scene, make_trace_queries, raster_loss
    from method.splat.rasterize import rasterize
    from method.splat.trace import TraceAccel, trace

    *params, cam = make_scene(64, 16)  # the bench's random splats: float32, as training passes them
    params = [p.requires_grad_(True) for p in params]
    off = torch.zeros(params[0].shape[0], 2, requires_grad=True)
    raster_loss(rasterize(*params, cam, None, screen_offsets=off, backend="numba")).backward()  # depth normals too
    o, d = make_trace_queries(*[p.detach() for p in params[:3]], 8, 4)
    with torch.no_grad():
        accel = TraceAccel.build(*[p.detach() for p in params[:4]])
        trace(*[p.detach() for p in params[:4]], None, o, d, 0.02, accel=accel, backend="numba")  # visibility
    trace(*params, o, d, 0.02, accel=accel, backend="numba")[1].sum().backward()  # hits, differentiable
    frozen = [p.detach() for p in params[:3]] + params[3:]  # stage 2: the compiled compositing of the hits
    sum(v.sum() for v in trace(*frozen, o, d, 0.02, accel=accel, backend="numba")).backward()
    from method.model.blend_numba import blend_at_nodes  # the nodes' blend (model.deform_nodes)

    x = params[0].detach().clone().requires_grad_(True)
    index = np.zeros((x.shape[0], 4), np.int64)
    near, sigma = np.zeros((x.shape[0], 4, 3)), np.ones((x.shape[0], 4))
    blend_at_nodes(x, torch.ones(1, 3, requires_grad=True), index, near, sigma).sum().backward()
    from method.model.basis_numba import basis_offsets  # the motion bases' blend (model.motion_bases)

    quats = torch.ones(x.shape[0], 4)
    logits = torch.zeros(x.shape[0], 3, requires_grad=True)
    eye = torch.eye(3).expand(2, 3, 3)
    basis_offsets(x, quats, logits, eye, torch.zeros(2, 3), torch.ones(2, 4),
                  (torch.zeros(x.shape[0], 3), torch.zeros(x.shape[0], 4)))[0].sum().backward()
    from method.shading.envmap import texel_moments  # stage 2's exact diffuse quadrature
    from method.shading.quadrature_numba import cosine_weights_compiled

    nrm = torch.tensor([[0.0, 0.0, 1.0]], requires_grad=True)
    cosine_weights_compiled(nrm, texel_moments(2, 4, 2)).sum().backward()
    from method.losses import ssim  # the training SSIM (method/ssim_numba.py)

    img = torch.rand(12, 12, 3, requires_grad=True)
    ssim(img, torch.rand(12, 12, 3)).backward()
    return [name for name, f in kernels().items() if f.signatures]


def main() -> int:
    t0 = time.perf_counter()
    try:
        names = warm()
    except ImportError:
        print("warm: numba not installed; the torch path needs no compilation")
        return 0
    print(f"warm: compiled kernels cached ({', '.join(names)}) in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
