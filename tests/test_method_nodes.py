"""The deformation field read at nodes (model.deform_nodes, method/model/nodes.py): the farthest points and
the blend against brute-force references, the scene's field (stage 2's cached path with nodes:
tests/test_method_stage1.py), the nodes through a checkpoint, resume equality, and the setting's validation."""
from __future__ import annotations

import shutil

import pytest
import torch

from lumibench.errors import UserError
from method.model.deform import DeformNet
from method.model.gaussians import Gaussians
from method.model.nodes import K_NEIGHBOURS, MotionNodes, farthest_points
from method.model.scene import DynamicScene


def _points(n=300, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1)


def test_farthest_points_is_the_greedy_maximin_order():
    """Each chosen point is the one farthest from those chosen before it (brute force over all pairs)."""
    x = _points(200)
    idx = farthest_points(x, 25).tolist()
    assert idx[0] == 0 and len(set(idx)) == 25
    d = torch.cdist(x, x)
    for i in range(1, 25):
        far = d[:, idx[:i]].min(1).values
        assert far[idx[i]] == far.max()
    assert farthest_points(x, 500).tolist() == list(range(200))  # more nodes than points: every point


def test_blend_weights_match_a_per_gaussian_brute_force():
    """Nearest K nodes by a full sort per Gaussian, softmax of -d^2 / (2 sigma^2), sigma the node's mean distance
    to its 3 nearest other nodes; the blend is the weighted sum of the nodes' values."""
    x = _points(150, seed=1)
    mn = MotionNodes(30)
    mn.choose(x)
    nodes = mn.nodes
    moved = x + 0.01 * _points(150, seed=2)  # the means drift after the choice: weights follow, neighbours do not
    w = mn.weights(moved)
    vals = _points(30, seed=3)
    blended = mn.blend(vals, w)
    dn = torch.cdist(nodes, nodes)
    sigma = dn.sort(1).values[:, 1:4].mean(1)
    for i in range(150):
        near = torch.cdist(x[i:i + 1], nodes)[0].argsort()[:K_NEIGHBOURS]
        d2 = ((moved[i] - nodes[near]) ** 2).sum(-1)
        wi = torch.softmax(-d2 / (2 * sigma[near] ** 2), 0)
        assert torch.allclose(w[i], wi, atol=1e-12)
        assert torch.allclose(blended[i], (wi[:, None] * vals[near]).sum(0), atol=1e-12)


def _scene(n=60, nodes=0, seed=0, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=gen) * 2 - 1) * 0.6
    g = Gaussians.from_points(pts, 0.6, -0.01, gen, colours=torch.rand(n, 3, generator=gen))
    g = Gaussians({k: v.to(dtype) for k, v in g.t.items()})
    net = DeformNet(3, 16, 1, 3, 2, 8, 6).to(dtype)
    with torch.no_grad():
        for head in (net.d_mu, net.d_rot, net.d_col):
            head.weight.copy_(0.3 * torch.randn(head.weight.shape, generator=gen, dtype=dtype))
            head.bias.copy_(0.1 * torch.randn(head.bias.shape, generator=gen, dtype=dtype))
    sc = DynamicScene(g, net, torch.zeros(3, dtype=dtype), 1.0)
    if nodes:
        sc.nodes = MotionNodes(nodes)
    return sc


def test_field_with_nodes_is_the_network_at_the_nodes_blended():
    """A field constant in space (the heads' weights zero) comes out the same at every Gaussian with nodes as
    without (the weights sum to one); a varying one is the blend of the network read at the nodes, and the
    nodes are re-chosen when the Gaussian count changes."""
    sc = _scene(nodes=12)
    x = sc.normalised(sc.g.means)
    d_mu, d_rot, d_col = sc.field(x, 0.3)
    w = sc.nodes.weights(x)
    ref = sc.net(sc.nodes.nodes, 0.3)
    for a, b in zip((d_mu, d_rot, d_col), ref):
        assert torch.allclose(a, sc.nodes.blend(b, w), atol=1e-12)
    assert not torch.allclose(d_mu, sc.net(x, 0.3)[0], atol=1e-3)  # nodes are not every Gaussian
    for head in (sc.net.d_mu, sc.net.d_rot, sc.net.d_col):
        head.weight.data.zero_()
    flat = _scene(nodes=0)
    flat.net.load_state_dict(sc.net.state_dict())
    for a, b in zip(sc.field(x, 0.3), flat.field(x, 0.3)):
        assert torch.allclose(a, b, atol=1e-12)
    fewer = x[:40]
    sc.field(fewer, 0.3)
    assert sc.nodes.index.shape == (40, K_NEIGHBOURS) and int(sc.nodes.index.max()) < 12


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_nodes_on_cuda_match_the_cpu():
    """The same nodes, neighbours, weights and field on a GPU as on the CPU (float64): the farthest-point loop
    and the chunked neighbour search keep every tensor on the means' device."""
    x = _points(3000, seed=4)
    cpu, gpu = MotionNodes(200), MotionNodes(200)
    cpu.choose(x)
    gpu.choose(x.cuda())
    assert gpu.nodes.is_cuda and gpu.index.is_cuda
    assert torch.equal(gpu.index.cpu(), cpu.index) and torch.allclose(gpu.nodes.cpu(), cpu.nodes, atol=0)
    moved = x + 0.01 * _points(3000, seed=5)
    assert torch.allclose(gpu.weights(moved.cuda()).cpu(), cpu.weights(moved), atol=1e-12)
    sc, sc_gpu = _scene(n=500, nodes=40), _scene(n=500, nodes=40)
    sc_gpu.g = Gaussians({k: v.cuda() for k, v in sc_gpu.g.t.items()})
    sc_gpu.net.load_state_dict(sc.net.state_dict())  # the trunk's initialisation draws from the global generator
    sc_gpu.net, sc_gpu.center = sc_gpu.net.cuda(), sc_gpu.center.cuda()
    a, b = sc.deform(0.7), sc_gpu.deform(0.7)
    assert sc_gpu.nodes.index.is_cuda and torch.equal(sc_gpu.nodes.index.cpu(), sc.nodes.index)
    for k in ("means", "quats", "colours"):
        assert torch.allclose(getattr(a, k), getattr(b, k).cpu(), atol=1e-10), k


def test_nodes_travel_with_the_checkpoint():
    """scene_state -> scene_from_checkpoint keeps the nodes, so a stage-2 or relight load deforms as trained."""
    from method.checkpoints import scene_from_checkpoint, scene_state
    from method.config import load_method_config

    sc = _scene(nodes=10, dtype=torch.float32)
    sc.model_cfg = {**load_method_config("ci", [])["model"], "mlp_depth": 3, "mlp_width": 16, "mlp_skip": 1,
                    "pos_freqs": 3, "time_freqs": 2, "time_net_width": 8, "time_net_out": 6}
    sc.refresh_nodes()
    with torch.no_grad():
        sc.g.t["means"] += 0.05  # drifted since the choice: a reload must not re-choose
    back = scene_from_checkpoint(scene_state(sc), {}, "cpu")
    assert torch.equal(back.nodes.nodes, sc.nodes.nodes) and torch.equal(back.nodes.index, sc.nodes.index)
    assert torch.equal(sc.deform(0.4).means, back.deform(0.4).means)


def test_resume_with_nodes_equals_an_uninterrupted_run(ci_dataset, tmp_path):
    """Density control stops at iteration 10, so the nodes chosen after its last step are the ones the
    checkpoint at 12 carries; the resumed run must use them, not re-choose them from the drifted means."""
    from method.checkpoints import load_checkpoint
    from method.config import load_method_config
    from method.train import train_stage1
    from tests.test_method_stage1 import TINY

    torch.set_num_threads(1)
    cfg = lambda: load_method_config("ci", TINY + ["stage1.densify_until=10", "model.deform_nodes=64"])  # noqa: E731
    full = tmp_path / "full"
    train_stage1(ci_dataset, "city", full, cfg(), seed=3, progress=False, write_outputs=False)
    part = tmp_path / "part"
    shutil.copytree(full, part)
    (part / "checkpoints" / "stage1_000024.pt").unlink()
    train_stage1(ci_dataset, "city", part, cfg(), seed=3, resume=True, progress=False, write_outputs=False)
    a = load_checkpoint(full / "checkpoints" / "stage1_000024.pt", "cpu")
    b = load_checkpoint(part / "checkpoints" / "stage1_000024.pt", "cpu")
    assert a["nodes"]["nodes"].shape == (64, 3)
    for k in a["gaussians"]:
        assert torch.equal(a["gaussians"][k], b["gaussians"][k]), k
    for k in a["net"]:
        assert torch.equal(a["net"][k], b["net"][k]), k


@pytest.mark.parametrize("value", [-1, 2.5, True])
def test_deform_nodes_must_be_a_count(value):
    from method.config import load_method_config

    with pytest.raises(UserError, match="model.deform_nodes"):
        load_method_config("ci", [f"model.deform_nodes={str(value).lower()}"])


def test_a_checkpoint_with_session_29s_motion_placement_is_refused():
    """Nodes chosen in position and motion blended with a motion term; loaded by position alone they would
    blend other neighbours without a word, so the checkpoint is refused with what to do."""
    mn = MotionNodes(8)
    mn.choose(_points(40, seed=1))
    st = mn.state()
    assert MotionNodes.from_state(st, "cpu").index.equal(mn.index)
    st["motion"] = torch.zeros(40, 15, dtype=torch.float64)
    with pytest.raises(UserError, match="train the run again"):
        MotionNodes.from_state(st, "cpu")


def test_blend_all_values_and_gradients_match_a_per_gaussian_brute_force():
    """The three network outputs blended in one gather (blend_all): values and the gradients of the node
    values and the positions (through the weights) as a per-Gaussian loop computes them, in float64."""
    x = _points(80, seed=4)
    mn = MotionNodes(20)
    mn.choose(x)
    moved = (x + 0.01 * _points(80, seed=5)).requires_grad_(True)
    outs = tuple(_points(20, seed=s)[:, :c].clone().requires_grad_(True) for s, c in ((6, 3), (7, 2), (8, 1)))
    w = mn.weights(moved)
    got = mn.blend_all(outs, w)
    assert [g.shape for g in got] == [(80, 3), (80, 2), (80, 1)]
    probe = [torch.randn(g.shape, generator=torch.Generator().manual_seed(i), dtype=g.dtype) for i, g in enumerate(got)]
    sum((g * p).sum() for g, p in zip(got, probe)).backward()
    grads = [moved.grad.clone()] + [o.grad.clone() for o in outs]
    moved.grad = None
    for o in outs:
        o.grad = None
    ref_loss = 0.0
    for i in range(80):
        near = mn.index[i]
        d2 = ((moved[i] - mn.nodes[near]) ** 2).sum(-1)
        wi = torch.softmax(-d2 / (2 * mn.sigma[near] ** 2), 0)
        for o, p, g in zip(outs, probe, got):
            val = (wi[:, None] * o[near]).sum(0)
            assert torch.allclose(g[i], val.detach(), atol=1e-12)
            ref_loss = ref_loss + (val * p[i]).sum()
    ref_loss.backward()
    for a, b in zip(grads, [moved.grad] + [o.grad for o in outs]):
        assert torch.allclose(a, b, atol=1e-10)


def test_compiled_blend_matches_the_torch_reference_values_and_gradients():
    """The compiled blend (method/model/blend_numba.py, what a CPU training runs) against MotionNodes.weights +
    blend_all (the reference, and the CUDA path): the blended outputs and the gradients of the positions and of
    the node values, in float64, on one thread and on two (its per-thread sums)."""
    pytest.importorskip("numba")
    import numba

    from method.splat import backend

    x = _points(300, seed=9)
    mn = MotionNodes(40)
    mn.choose(x)
    moved = (x + 0.02 * _points(300, seed=10)).requires_grad_(True)
    outs = tuple(_points(40, seed=s)[:, :c].clone().requires_grad_(True) for s, c in ((11, 3), (12, 3), (13, 2)))
    probe = [_points(300, seed=20 + i)[:, :o.shape[1]] for i, o in enumerate(outs)]

    def run(name):
        backend.set_backend(name)
        try:
            got = mn.blend_outputs(moved, outs)
        finally:
            backend.set_backend("auto")
        grads = torch.autograd.grad(sum((g * p).sum() for g, p in zip(got, probe)), (moved,) + outs)
        return [g.detach() for g in got], grads

    ref_vals, ref_grads = run("torch")
    assert float(ref_grads[0].abs().max()) > 1e-3  # the positions get a gradient through the weights
    threads = torch.get_num_threads()  # the kernels follow torch's count (raster_numba.match_torch_threads)
    try:
        for n in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)}):
            torch.set_num_threads(n)
            vals, grads = run("numba")
            assert numba.get_num_threads() == n
            for a, b in zip(vals, ref_vals):
                assert torch.allclose(a, b, rtol=0, atol=1e-12)
            for a, b in zip(grads, ref_grads):
                assert torch.allclose(a, b, rtol=0, atol=1e-11)
    finally:
        torch.set_num_threads(threads)
