"""The compiled CPU backend (Numba) held to the torch reference: values and gradients of every input on
the random and edge-case scenes, the thresholds it must share, and the backend setting itself."""
from __future__ import annotations

import math

import pytest
import torch

import method.splat.backend as backend_mod
from method.splat.camera import Camera
from method.splat.rasterize import rasterize
from method.splat.trace import TraceAccel, trace

pytest.importorskip("numba")

from test_splat_raster import KEYS, SCENES, random_scene  # noqa: E402
from test_splat_trace import random_rays, random_scene as trace_scene  # noqa: E402

F64 = torch.float64
RASTER_KW = dict(distortion_near=1.0, distortion_far=10.0, depth_ratio=0.3)


def _raster_both(params, cam, offsets=True, bg=None, **kw):
    """Outputs and the gradients of every input (incl. the screen offsets) for both backends."""
    res = {}
    for be in ("torch", "numba"):
        leaves = [p.clone().requires_grad_(True) for p in params]
        off = torch.zeros(params[0].shape[0], 2, dtype=params[0].dtype, requires_grad=True) if offsets else None
        out = rasterize(*leaves, cam, bg, screen_offsets=off, backend=be, **kw)
        g = torch.Generator().manual_seed(7)
        loss = sum((getattr(out, k) * torch.randn(getattr(out, k).shape, generator=g, dtype=F64).to(
            getattr(out, k).dtype)).sum() for k in KEYS)
        grads = torch.autograd.grad(loss, leaves + ([off] if offsets else []), allow_unused=True)
        res[be] = (out, grads)
    return res


def _close(a, b, tol, msg):
    scale = max(1.0, float(b.detach().abs().max())) if b.numel() else 1.0
    torch.testing.assert_close(a, b, atol=tol * scale, rtol=0, msg=msg)


@pytest.mark.parametrize("cfg", SCENES, ids=lambda c: "-".join(f"{k}{v}" for k, v in c.items()))
def test_raster_values_and_gradients_equal_torch(cfg):
    params, cam = random_scene(**cfg)
    bg = torch.linspace(0.1, 0.9, params[4].shape[1], dtype=F64)
    res = _raster_both(params, cam, bg=bg, **RASTER_KW)
    (a, ga), (b, gb) = res["numba"], res["torch"]
    assert a.num_pairs == b.num_pairs > 0
    assert torch.equal(a.visible, b.visible)
    _close(a.radii, b.radii, 1e-10, "radii")
    for k in KEYS:
        _close(getattr(a, k), getattr(b, k), 1e-10, k)
    names = ("means", "quats", "scales", "opacities", "features", "screen_offsets")
    fallback_only = cfg.get("scale", (1.0,))[0] < 0.01  # sub-pixel splats: scales cannot matter there
    for name, x, y in zip(names, ga, gb):
        assert float(y.abs().max()) > 0 or (fallback_only and name == "scales"), name  # every input reached
        _close(x, y, 1e-9, name)


def test_raster_camera_inside_the_cloud_and_behind_the_near_plane():
    """Splats behind the camera and crossing its plane (unbounded footprints), and a near plane that cuts
    hits off (depth < near): the same pairs and gradients."""
    params, _ = random_scene(n=64, seed=2, scale=(0.2, 0.8), spread=2.0)
    cam = Camera.look_at((0.05, -0.1, 0.02), (0.3, 1.0, 0.1), 16, 12, dtype=F64)
    for near in (0.01, 0.4):
        res = _raster_both(params, cam, near=near)
        (a, ga), (b, gb) = res["numba"], res["torch"]
        assert a.num_pairs == b.num_pairs
        # the kernels see the valid splats only, renumbered by depth: visibility comes back in place
        assert torch.equal(a.visible, b.visible) and 0 < int(b.visible.sum()) < len(b.visible)
        for k in KEYS:
            _close(getattr(a, k), getattr(b, k), 1e-10, k)
        for x, y in zip(ga, gb):
            _close(x, y, 1e-9, "grad")


def test_raster_pair_record_reused_between_renders():
    """The backward walks the forward's record of composited pairs, whose buffers are reused from one render
    to the next, as are the backward's gradient buffers (raster_numba._ScratchPool): gradients of a render are
    the same whether its record and buffers are fresh or reused after a larger scene's, or after a forward
    whose backward never ran, or in a second backward through one forward (its record handed on after the first
    and written again)."""
    import method.splat.raster_numba as rn

    def grads(params, cam):
        leaves = [p.clone().requires_grad_(True) for p in params]
        out = rasterize(*leaves, cam, None, backend="numba", **RASTER_KW)
        (out.features.sum() + out.depth_expected.sum() + out.distortion.sum()).backward()
        return [p.grad for p in leaves]

    rn._records.free.clear()
    rn._grad_buffers.free.clear()
    small, cam_s = random_scene(n=40, seed=3)
    big, cam_b = random_scene(n=400, seed=4)
    first = grads(small, cam_s)  # a fresh record
    grads(big, cam_b)  # a larger record: the pool now holds buffers filled with another scene's pairs
    rn._records.free[:] = [max(rn._records.free, key=lambda rec: rec[0].shape[0])]  # only the big scene's
    assert rn._records.free[0][0].shape[0] > 400 and rn._grad_buffers.free
    again = grads(small, cam_s)  # in the big scene's buffers
    params = [p.clone().requires_grad_(True) for p in small]
    rasterize(*params, cam_s, None, backend="numba", **RASTER_KW)  # a forward whose backward never runs
    last = grads(small, cam_s)
    for a, b, c in zip(first, again, last):
        assert torch.equal(a, b) and torch.equal(a, c)
    # two forwards before their backwards: each keeps its own record
    leaves = [p.clone().requires_grad_(True) for p in small]
    out = rasterize(*leaves, cam_s, None, backend="numba", **RASTER_KW)
    other = [p.clone().requires_grad_(True) for p in big]
    out_big = rasterize(*other, cam_b, None, backend="numba", **RASTER_KW)
    (out.features.sum() + out.depth_expected.sum() + out.distortion.sum()).backward()
    out_big.features.sum().backward()
    for a, p in zip(first, leaves):
        assert torch.equal(a, p.grad)
    # a second backward through one forward (retain_graph; gradcheck does it once per output): the record,
    # handed on after the first and overwritten by another render's, is written again
    leaves = [p.clone().requires_grad_(True) for p in small]
    out = rasterize(*leaves, cam_s, None, backend="numba", **RASTER_KW)
    loss = out.features.sum() + out.depth_expected.sum() + out.distortion.sum()
    loss.backward(retain_graph=True)
    grads(big, cam_b)
    rn._records.free[:] = [max(rn._records.free, key=lambda rec: rec[0].shape[0])]  # only the big scene's
    for p in leaves:
        p.grad = None
    loss.backward()
    for a, p in zip(first, leaves):
        assert torch.equal(a, p.grad)


def test_raster_stop_rule_is_shared(monkeypatch):
    """The compiled kernels read the stop threshold from rasterize.T_STOP: lifting it composites more pairs
    in both backends alike (near-opaque stacks: the stop really cuts)."""
    import method.splat.rasterize as rz

    params, cam = random_scene(seed=3, opacity=(0.9, 1.0), n=64)
    a, b = rasterize(*params, cam, backend="numba"), rasterize(*params, cam, backend="torch")
    n0 = a.num_pairs
    assert n0 == b.num_pairs
    assert torch.equal(a.visible, b.visible)
    monkeypatch.setattr(rz, "T_STOP", 1e-300)
    n1 = rasterize(*params, cam, backend="numba").num_pairs
    assert n1 == rasterize(*params, cam, backend="torch").num_pairs > n0 + 20


def test_raster_empty_image():
    params, cam = random_scene(n=4)
    params[0] = params[0] + torch.tensor([0.0, -10.0, 0.0], dtype=F64)  # all behind the camera
    leaves = [p.clone().requires_grad_(True) for p in params]
    out = rasterize(*leaves, cam, torch.tensor([0.5, 0.5, 0.5], dtype=F64), backend="numba")
    assert out.num_pairs == 0 and not bool(out.visible.any())
    torch.testing.assert_close(out.features, torch.full((16, 16, 3), 0.5, dtype=F64))
    (out.features.sum() + out.alpha.sum()).backward()
    assert all(float(p.grad.abs().max()) == 0.0 for p in leaves)


def test_raster_float32_close_to_torch_float32():
    params, cam = random_scene(seed=1, n=64)
    p32 = [p.float() for p in params]
    res = _raster_both(p32, cam.to(dtype=torch.float32), offsets=False)
    (a, ga), (b, gb) = res["numba"], res["torch"]
    for k in ("features", "alpha", "depth_expected", "distortion", "normal"):
        _close(getattr(a, k), getattr(b, k), 1e-5, k)
    for x, y in zip(ga, gb):
        _close(x, y, 2e-4, "grad")


def test_raster_without_gradients_equals_with():
    params, cam = random_scene(seed=0)
    with torch.no_grad():
        a = rasterize(*params, cam, backend="numba")
    b = rasterize(*[p.clone().requires_grad_(True) for p in params], cam, backend="numba")
    for k in KEYS:
        torch.testing.assert_close(getattr(a, k), getattr(b, k).detach(), atol=0, rtol=0, msg=k)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trace_values_and_gradients_equal_torch(seed):
    params = trace_scene(seed=seed, opacity=(0.05, 1.0) if seed == 2 else (0.05, 0.95))
    o, d = random_rays(seed=seed, unit=seed != 1, axis_aligned=12)
    tmin = 0.02 if seed != 2 else torch.rand(o.shape[0], dtype=F64, generator=torch.Generator().manual_seed(3)) * 0.5
    accel = TraceAccel.build(*params[:4])
    out = {}
    for be in ("torch", "numba"):
        leaves = [p.clone().requires_grad_(True) for p in params]
        T, F = trace(*leaves, o, d, tmin, accel=accel, backend=be)
        loss = (T * torch.linspace(0.5, 1.5, T.numel(), dtype=F64)).sum() + (F * F).sum()
        out[be] = (T, F, torch.autograd.grad(loss, leaves))
    assert float(out["torch"][0].detach().min()) < 0.1  # occluded rays: the stop rule is exercised
    for x, y in zip(out["numba"][:2], out["torch"][:2]):
        torch.testing.assert_close(x, y, atol=1e-12, rtol=0)
    for x, y in zip(out["numba"][2], out["torch"][2]):
        _close(x, y, 1e-10, "grad")


@pytest.mark.parametrize("seed, dtype", [(0, torch.float64), (1, torch.float64), (2, torch.float32)])
def test_trace_grid_built_by_the_kernel_equals_torchs(seed, dtype):
    """TraceAccel.build's candidate tests compiled (trace_numba.grid_entries): the same cells, entries in the
    same order, blocks and slots as the torch build, on splats of several sizes (some spanning many cells),
    float32 too; and the same hits when traced."""
    params = [p.to(dtype) for p in trace_scene(n=300, seed=seed, scale=(0.02, 0.4), opacity=(0.005, 0.95))]
    for cell_factor in (0.5, 1.0):
        a = TraceAccel.build(*params[:4], cell_factor=cell_factor, backend="torch")
        b = TraceAccel.build(*params[:4], cell_factor=cell_factor, backend="numba")
        assert a.res == b.res and int(torch.bincount(a.entries).max()) > 8  # some splats span many cells
        for name in ("cell_start", "entries", "blk_start", "blk_plane", "slot_splat"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
    o, d = random_rays(seed=seed)
    Ta, Fa = trace(*params, o.to(dtype), d.to(dtype), 0.0, accel=a, backend="torch")
    Tb, Fb = trace(*params, o.to(dtype), d.to(dtype), 0.0, accel=b, backend="torch")
    assert torch.equal(Ta, Tb) and torch.equal(Fa, Fb)


def test_trace_rays_with_more_hits_than_the_first_pass_holds(monkeypatch):
    """A ray with more kept hits than the first pass's slots is traced again with room for all of them."""
    import method.splat.trace_numba as tn

    params = trace_scene(seed=4, n=200, opacity=(0.02, 0.1))  # faint splats: many hits per ray
    o, d = random_rays(seed=4)
    T0, F0 = trace(*params, o, d, 0.0, backend="torch")
    monkeypatch.setattr(tn, "CAP", 2)
    T1, F1 = trace(*params, o, d, 0.0, backend="numba")
    torch.testing.assert_close(T1, T0, atol=1e-12, rtol=0)
    torch.testing.assert_close(F1, F0, atol=1e-12, rtol=0)
    assert float(T0.min()) < 0.9  # rays do cross several faint splats


def test_trace_thresholds_and_chunks_are_shared():
    params = trace_scene(seed=3, opacity=(0.5, 1.0))
    o, d = random_rays(seed=3)
    for kw in (dict(alpha_min=0.2, T_min=0.3), dict(alpha_min=0.001, T_min=0.001, max_alpha=0.9),
               dict(ray_chunk=37)):
        Ta, Fa = trace(*params, o, d, 0.0, backend="numba", **kw)
        Tb, Fb = trace(*params, o, d, 0.0, backend="torch", **kw)
        torch.testing.assert_close(Ta, Tb, atol=1e-12, rtol=0)
        torch.testing.assert_close(Fa, Fb, atol=1e-12, rtol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trace_visibility_without_gradients_equals_torch(seed, monkeypatch):
    """Visibility only and no gradient (relighting, predictions, the diagnostic): the compiled traversal's own
    transmittance, with no hit list, equals the torch reference (its stop rule, t_min, thresholds, rays along
    the axes, float32 inputs); with opacities changed since the grid was built, the current ones count."""
    import method.splat.trace_numba as tn

    params = trace_scene(seed=seed, opacity=(0.05, 1.0) if seed == 2 else (0.05, 0.95))
    o, d = random_rays(seed=seed, unit=seed != 1, axis_aligned=12)
    tmin = 0.02 if seed != 2 else torch.rand(o.shape[0], dtype=F64, generator=torch.Generator().manual_seed(3)) * 0.5
    accel = TraceAccel.build(*params[:4])
    ref, _ = trace(*params[:4], None, o, d, tmin, accel=accel, backend="torch")
    assert float(ref.min()) < 0.1 and float(ref.max()) == 1.0  # occluded and free rays

    def no_hit_list(*a, **k):
        raise AssertionError("the hit list was built where only the transmittance is needed")

    with monkeypatch.context() as m:
        m.setattr(tn, "march_hits", no_hit_list)
        with torch.no_grad():
            T, F = trace(*[p.clone().requires_grad_(True) for p in params[:4]], None, o, d, tmin, accel=accel,
                         backend="numba")
        assert F is None
        torch.testing.assert_close(T, ref, atol=1e-12, rtol=0)
        for kw in (dict(alpha_min=0.2, T_min=0.3), dict(alpha_min=0.001, T_min=0.001, max_alpha=0.9)):
            acc = TraceAccel.build(*params[:4], alpha_min=kw["alpha_min"])
            Ta, _ = trace(*params[:4], None, o, d, tmin, accel=acc, backend="numba", **kw)
            Tb, _ = trace(*params[:4], None, o, d, tmin, accel=acc, backend="torch", **kw)
            torch.testing.assert_close(Ta, Tb, atol=1e-12, rtol=0)
        p32 = [p.float() for p in params[:4]]
        acc32 = TraceAccel.build(*p32)
        T32, _ = trace(*p32, None, o.float(), d.float(), tmin, accel=acc32, backend="numba")
        assert T32.dtype == torch.float32
        torch.testing.assert_close(T32, trace(*p32, None, o.float(), d.float(), tmin, accel=acc32,
                                              backend="torch")[0], atol=2e-5, rtol=0)
    # opacities fine-tuned under a kept grid (stage 2): the hit list path, alphas from the current opacities
    faded = params[3] * 0.5
    T_new, _ = trace(params[0], params[1], params[2], faded, None, o, d, tmin, accel=accel, backend="numba")
    T_ref, _ = trace(params[0], params[1], params[2], faded, None, o, d, tmin, accel=accel, backend="torch")
    torch.testing.assert_close(T_new, T_ref, atol=1e-12, rtol=0)
    assert float((T_new - ref).abs().max()) > 0.1


def test_backend_setting(monkeypatch):
    cpu = torch.device("cpu")
    assert backend_mod.resolve("auto", cpu) == "numba"
    assert backend_mod.resolve("torch", cpu) == "torch"
    assert backend_mod.resolve("auto", torch.device("cuda")) == "torch"
    with pytest.raises(ValueError, match="CPU only"):
        backend_mod.resolve("numba", torch.device("cuda"))
    with pytest.raises(ValueError, match="one of auto, torch, numba"):
        backend_mod.resolve("fast", cpu)
    monkeypatch.setattr(backend_mod, "_numba_ok", False)  # as on a machine without numba
    assert backend_mod.resolve("auto", cpu) == "torch"
    with pytest.raises(ValueError, match="needs numba"):
        backend_mod.resolve("numba", cpu)
    monkeypatch.setattr(backend_mod, "_default", "torch")
    assert backend_mod.resolve(None, cpu) == "torch"
    with pytest.raises(ValueError, match="splat backend"):
        backend_mod.set_backend("gpu")


def test_setting_reaches_rasterize_and_trace(monkeypatch):
    """rasterize() and trace() take the process default: a broken compiled path must show."""
    import method.splat.raster_numba as rn
    import method.splat.trace_numba as tn

    params, cam = random_scene(seed=0, n=8)

    def boom(*a, **k):
        raise RuntimeError("compiled path taken")

    monkeypatch.setattr(rn, "composite_rows", boom)
    monkeypatch.setattr(tn, "march_hits", boom)
    monkeypatch.setattr(backend_mod, "_default", "numba")
    with pytest.raises(RuntimeError, match="compiled"):
        rasterize(*params, cam)
    o, d = random_rays(r=4)
    with pytest.raises(RuntimeError, match="compiled"):
        trace(*trace_scene(seed=0, n=8), o, d)
    monkeypatch.setattr(backend_mod, "_default", "torch")
    assert rasterize(*params, cam).num_pairs > 0
    assert math.isfinite(float(trace(*trace_scene(seed=0, n=8), o, d)[0].sum()))


def test_every_compiled_kernel_can_be_cached():
    """A kernel that reads a ctypes global (numba.get_num_threads() inside it did) cannot go to numba's
    on-disk cache, so every process compiles it again (~14 s for the raster forward): after a raster
    forward + backward, a trace, the nodes' blend, the diffuse quadrature, the SSIM and the motion bases'
    blend through the compiled backend, no
    kernel they compiled holds one."""
    from numba.core.registry import CPUDispatcher

    import method.splat.raster_numba as rn
    import method.splat.trace_numba as tn

    params, cam = random_scene(**SCENES[0])
    _raster_both(params, cam, **RASTER_KW)
    tparams = trace_scene(seed=0)
    o, d = random_rays(seed=0)
    leaves = [p.clone().requires_grad_(True) for p in tparams]
    T, F = trace(*leaves, o, d, 0.02, accel=TraceAccel.build(*tparams[:4]), backend="numba")
    torch.autograd.grad(T.sum() + F.sum(), leaves, allow_unused=True)
    import numpy as np

    import method.model.blend_numba as bn  # the method's own kernels: the nodes' blend, the diffuse quadrature
    import method.shading.quadrature_numba as qn
    from method.shading.envmap import texel_moments

    x = torch.rand(5, 3, requires_grad=True)
    bn.blend_at_nodes(x, torch.rand(2, 3), np.zeros((5, 2), np.int64), np.zeros((5, 2, 3)), np.ones((5, 2))).sum().backward()
    qn.cosine_weights_compiled(x, texel_moments(2, 4, 2)).sum().backward()
    import method.ssim_numba as sn  # the training SSIM
    from method.losses import _window

    sn.ssim_compiled(torch.rand(12, 12, 3, requires_grad=True), torch.rand(12, 12, 3),
                     _window(torch.float64, "cpu")).backward()
    import method.splat.depth_normals_numba as dn  # the depth normals

    cam64 = Camera.look_at(torch.tensor([0.0, -2.0, 2.0]), torch.zeros(3), 6, 5).to("cpu", F64)
    from method.splat.rasterize import normal_from_depth

    normal_from_depth(torch.rand(5, 6, dtype=F64, requires_grad=True) + 1, cam64, backend="numba").sum().backward()
    import method.model.basis_numba as mn  # the motion bases' blend

    mn.basis_offsets(x, torch.rand(5, 4), torch.rand(5, 3, requires_grad=True), torch.rand(2, 3, 3),
                     torch.rand(2, 3), torch.rand(2, 4), (torch.rand(5, 3), torch.rand(5, 4)))[0].sum().backward()
    kernels = {f"{m.__name__}.{k}": v for m in (rn, tn, bn, qn, sn, dn, mn) for k, v in vars(m).items()
               if isinstance(v, CPUDispatcher)}
    compiled = {name: k for name, k in kernels.items() if k.overloads}
    assert {"method.splat.raster_numba.forward", "method.splat.raster_numba.backward"} <= set(compiled)
    assert any(name.startswith("method.splat.trace_numba.") for name in compiled)
    assert {"method.model.blend_numba.blend_backward", "method.shading.quadrature_numba.cosine_backward",
            "method.ssim_numba.ssim_backward", "method.splat.depth_normals_numba.normals_backward",
            "method.model.basis_numba.basis_backward"} <= set(compiled)
    uncachable = [name for name, k in compiled.items()
                  if k._cache is not None and any(c.library.has_dynamic_globals for c in k.overloads.values())]
    assert uncachable == []


def _run_in_a_fresh_process(code: str):
    """Run ``code`` in a new Python process with Numba's pool at two threads and no thread count set (as on a
    2-core machine with nothing set), from the repository root; the completed process (check=True)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")}
    env["NUMBA_NUM_THREADS"] = "2"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_compiled_kernels_leave_torchs_thread_count_alone():
    """Numba's OpenMP pool, started by the first compiled kernel, sets the process's OpenMP thread count, and
    torch reads the same one: a grid worker set to one thread (benchmark.jobgrid.execute) ran torch on two
    from then on. In a fresh process (the pool starts once): torch set to one thread stays at one, and the
    kernels run on one."""
    code = ("import torch, numba; torch.set_num_threads(1)\n"
            "from method.splat.bench import make_scene, make_trace_queries\n"
            "from method.splat.rasterize import rasterize\nfrom method.splat.trace import trace\n"
            "m, q, s, o, f, cam = make_scene(500, 32)\n"
            "rasterize(m, q, s, o, f, cam, backend='numba')\nafter_raster = torch.get_num_threads()\n"
            "org, d = make_trace_queries(m, q, s, 8, 4)\ntrace(m, q, s, o, None, org, d, backend='numba')\n"
            "print(after_raster, torch.get_num_threads(), numba.get_num_threads())\n")
    out = _run_in_a_fresh_process(code)
    assert out.stdout.split() == ["1", "1", "1"], out.stdout + out.stderr


def test_a_training_alone_gives_the_kernels_torchs_threads_and_torch_one():
    """kernels_take_the_threads (what a training runs in): with torch on two threads, torch runs on one
    inside and the kernels on two, and torch gets its two back after; on one thread (a grid worker) or a
    GPU nothing changes. In a fresh process with a pool of two, as on the 2-core machine."""

    code = ("import torch, numba\nfrom method.splat.backend import kernels_take_the_threads\n"
            "from method.splat.bench import make_scene\nfrom method.splat.rasterize import rasterize\n"
            "m, q, s, o, f, cam = make_scene(500, 32)\nout = []\n"
            "for n, dev in ((2, 'cpu'), (1, 'cpu'), (2, 'cuda')):\n"
            "    torch.set_num_threads(n)\n"
            "    with kernels_take_the_threads(torch.device(dev)) as k:\n"
            "        rasterize(m, q, s, o, f, cam, backend='numba')\n"
            "        out.append((k, torch.get_num_threads(), numba.get_num_threads()))\n"
            "    out.append(torch.get_num_threads())\n"
            "print(out)\n")
    out = _run_in_a_fresh_process(code)
    # (kernels' count it yields, torch inside, Numba inside), then torch after
    assert out.stdout.strip() == "[(2, 1, 2), 2, (1, 1, 1), 1, (2, 2, 2), 2]", out.stdout + out.stderr


def test_the_network_runs_on_the_kernels_threads_forward_and_backward():
    """on_the_kernels_threads (the deformation network in a training alone): torch on both threads while the
    network runs forward and while its backward runs, on one before and after each (the loss and Adam stay on
    one), whether or not the input needs a gradient; the values and gradients are the plain call's, and the
    gradient of the network's input is formed only where the input needs one (the switch back once cost it
    everywhere). Outside kernels_take_the_threads (a grid worker) nothing is switched. In a fresh process with
    a pool of two."""

    code = ("import torch\nfrom method.splat.backend import kernels_take_the_threads, on_the_kernels_threads\n"
            "from method.model.deform import DeformNet\n"
            "torch.manual_seed(0)\nnet = DeformNet(3, 16, 1, 3, 2, 8, 6).double()\n"
            "for h in (net.d_mu, net.d_rot, net.d_col):\n    torch.nn.init.normal_(h.weight)\n"
            "seen = []\n"
            "class Spy(torch.autograd.Function):\n"
            "    @staticmethod\n    def forward(ctx, a):\n        seen.append(('f', torch.get_num_threads()))\n"
            "        return a.view_as(a)\n"
            "    @staticmethod\n    def backward(ctx, g):\n        seen.append(('b', torch.get_num_threads()))\n"
            "        return g\n"
            "class Input(torch.autograd.Function):\n"
            "    @staticmethod\n    def forward(ctx, a):\n        return a.view_as(a)\n"
            "    @staticmethod\n    def backward(ctx, g):\n        seen.append(('input grad', 0))\n        return g\n"
            "class Fn(torch.nn.Module):\n"
            "    def __init__(self):\n        super().__init__()\n        self.net = net\n"
            "    def forward(self, x, t):\n        return tuple(Spy.apply(o) for o in net(Input.apply(x), t))\n"
            "fn = Fn()\n"
            "def grads(x, call):\n    net.zero_grad()\n    out = call(fn, x, 0.4)\n"
            "    mid = torch.get_num_threads()\n    sum((o * o).sum() for o in out).backward()\n"
            "    return mid, torch.get_num_threads(), [p.grad.clone() for p in net.parameters()]\n"
            "torch.set_num_threads(2)\n"
            "res = []\n"
            "for needs in (False, True):\n"
            "    x = torch.rand(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))\n"
            "    x.requires_grad_(needs)\n"
            "    with kernels_take_the_threads(torch.device('cpu')):\n"
            "        ref = grads(x.detach(), lambda f, x, t: f(x, t))\n"
            "        seen.clear()\n"
            "        mid, after, g = grads(x, on_the_kernels_threads)\n"
            "        same = all(torch.allclose(a, b, rtol=1e-12, atol=0) for a, b in zip(g, ref[2]))\n"
            "        res.append((mid, after, sorted(set(seen)), same))\n"
            "seen.clear()\ngrads(torch.rand(5, 3, dtype=torch.float64), on_the_kernels_threads)\n"
            "res.append(sorted(set(seen)))\nprint(res)\n")
    out = _run_in_a_fresh_process(code)
    # (torch's threads after the forward, after the backward, those seen inside the network, grads equal);
    # last: outside a training alone, the network ran on the process's two threads, unswitched
    want = ("[(1, 1, [('b', 2), ('f', 2)], True), (1, 1, [('b', 2), ('f', 2), ('input grad', 0)], True), "
            "[('b', 2), ('f', 2)]]")
    assert out.stdout.strip() == want, out.stdout + out.stderr


def test_setup_warm_up_compiles_every_kernel():
    """`make setup` runs method.splat.warm so a first training does not compile: in a fresh process (the
    on-disk cache loads, or compiles, only what is called) every public kernel must have a signature after
    it, or the user's first run pays that kernel's compile."""
    import os
    import subprocess
    import sys

    from method.splat import warm

    assert len(warm.kernels()) >= 7  # the rasterizer's five and the tracer's two: the comparison below is not empty
    code = ("from method.splat import warm\n"
            "done = set(warm.warm())\n"
            "missing = sorted(set(warm.kernels()) - done)\n"
            "print('MISSING', missing)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert "MISSING []" in out.stdout, out.stdout


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_depth_order_is_torchs_stable_argsort_of_the_valid_splats(dtype):
    """The compiled depth order (a radix sort) gives exactly the order the torch path composites in: ties
    by index, -0.0 equal to +0.0, negatives (behind the camera) first, infinities and NaN last."""
    import numpy as np

    from method.splat.raster_numba import depth_order

    g = torch.Generator().manual_seed(3)
    z = (torch.rand(5000, generator=g, dtype=F64) * 20 - 2).to(dtype)
    z[::7] = z[3]  # many exact ties
    z[10:20] = 0.0
    z[20:30] = -0.0
    z[30:33] = torch.tensor([math.inf, -math.inf, math.nan], dtype=dtype)
    z[40:60] = torch.tensor(1.0 + 2.0 ** -20, dtype=dtype)  # keys that differ from a neighbour in low bytes only
    z[60:70] = torch.tensor(1.0, dtype=dtype)
    z[70:80] = -z[40:50]
    valid = torch.rand(5000, generator=g) < 0.8
    want = torch.argsort(z, stable=True)
    want = want[valid[want]]
    got = depth_order(z.numpy(), valid.numpy())
    assert got.dtype == np.int64
    assert torch.equal(torch.from_numpy(got), want)
    none = depth_order(z.numpy(), np.zeros(5000, np.bool_))
    assert none.shape == (0,)
    lone = torch.ones(50, dtype=dtype)
    lone[0] = 1.0 + torch.finfo(dtype).eps  # one key alone in its byte: that byte's pass still runs
    assert depth_order(lone.numpy(), np.ones(50, np.bool_)).tolist() == list(range(1, 50)) + [0]
