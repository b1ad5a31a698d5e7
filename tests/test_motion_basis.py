"""Rigid motion bases (method/model/motion_basis.py) on cases with a known answer: quaternion algebra against
rotation matrices, Kabsch's fit of an exact rigid motion, and the bases fitted to two rigid bodies and a
static part reproducing every trajectory (positions and rotations) at the knots and between them; the
network's option in the blend; the compiled blend (method/model/basis_numba.py) held to the torch reference;
and in training: resume equality across the split, stage 2's freeze, the settings' validation and their place
in the settings hash."""
from __future__ import annotations

import math
import shutil

import pytest
import torch

from method.model.gaussians import Gaussians
from method.model.scene import DynamicScene
from method.clustering import kmeans
from method.model.motion_basis import MotionBasis, kabsch, matrix_to_quat, quat_mul, quat_to_matrix


def _axis_angle(axis, angle) -> torch.Tensor:
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), math.sin(angle / 2) * a])


def test_quaternion_matrix_round_trip_and_product():
    gen = torch.Generator().manual_seed(0)
    q = torch.randn(64, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    m = quat_to_matrix(q)
    assert torch.allclose(m @ m.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(64, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(m), torch.ones(64, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(matrix_to_quat(m), q, atol=1e-10)
    r = torch.randn(64, 4, generator=gen, dtype=torch.float64)
    # the Hamilton product composes rotations: R(a b) = R(a) R(b)
    assert torch.allclose(quat_to_matrix(quat_mul(q, r)), m @ quat_to_matrix(r), atol=1e-12)
    # a quarter turn about z takes x to y
    qz = _axis_angle([0, 0, 1], math.pi / 2)
    assert torch.allclose(quat_to_matrix(qz) @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)


def test_kabsch_recovers_a_rigid_motion_about_the_centroid():
    gen = torch.Generator().manual_seed(1)
    src = torch.randn(40, 3, generator=gen, dtype=torch.float64) + torch.tensor([3.0, -1.0, 2.0], dtype=torch.float64)
    rot = quat_to_matrix(_axis_angle([1, 2, -0.5], 2.5))  # past a half turn: no small-angle shortcut
    t = torch.tensor([0.3, -0.7, 1.1], dtype=torch.float64)
    c = src.mean(0)
    dst = (src - c) @ rot.T + c + t
    r, tr = kabsch(src, dst)
    assert torch.allclose(r, rot, atol=1e-10)
    assert torch.allclose(tr, t, atol=1e-10)
    # a reflection is never returned: mirrored points give a proper rotation
    r2, _ = kabsch(src, dst * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    assert float(torch.linalg.det(r2)) > 0


def test_kmeans_separates_two_far_groups():
    gen = torch.Generator().manual_seed(2)
    x = torch.cat([torch.randn(30, 2, generator=gen), torch.randn(20, 2, generator=gen) + 50.0])
    labels = kmeans(x, 2, torch.Generator().manual_seed(0))
    assert labels[:30].unique().numel() == 1 and labels[30:].unique().numel() == 1
    assert int(labels[0]) != int(labels[30])


def _two_bodies(times):
    """Two rigid bodies (one spinning about its centre while it translates, one swinging about a pivot above
    it) and a static part: canonical means and quaternions, and every point's position and rotation at each
    time."""
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(25, 3, generator=gen) * 0.2 + torch.tensor([1.0, 0.0, 0.0])
    b = torch.randn(25, 3, generator=gen) * 0.2 + torch.tensor([-1.0, 0.0, 0.0])
    s = torch.randn(30, 3, generator=gen) * 0.5 + torch.tensor([0.0, 0.0, -2.0])
    means = torch.cat([a, b, s])
    quats = torch.randn(80, 4, generator=gen)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    pos, rots = [], []
    for t in times:
        ra = quat_to_matrix(_axis_angle([0, 0, 1], 1.2 * t).float())
        rb = quat_to_matrix(_axis_angle([1, 0, 0], 0.8 * math.sin(3 * t)).float())
        ca, pb = a.mean(0), torch.tensor([-1.0, 0.0, 1.0])
        pa = (a - ca) @ ra.T + ca + torch.tensor([0.0, 0.5 * t, 0.0])
        pbt = (b - pb) @ rb.T + pb
        pos.append(torch.cat([pa, pbt, s]))
        rots.append(torch.cat([quat_mul(matrix_to_quat(ra).expand(25, 4), quats[:25]),
                               quat_mul(matrix_to_quat(rb).expand(25, 4), quats[25:50]), quats[50:]]))
    return means, quats, torch.stack(pos, 1), torch.stack(rots, 1)


def test_fitted_bases_reproduce_rigid_trajectories():
    times = [i / 9 for i in range(10)]
    means, quats, traj, rots = _two_bodies(times)
    moving = torch.arange(80) < 50
    basis = MotionBasis(times, 2)
    logits, info = basis.fit(means, traj, moving, torch.Generator().manual_seed(0), sharpness=8.0)
    assert sorted(info["cluster_sizes"]) == [25, 25]
    w = torch.softmax(logits, -1)
    assert bool((w[50:, 0] > 0.99).all())          # the static part keeps the identity
    assert bool((w[:50, 1:].max(1).values > 0.99).all())  # each body one basis
    for j, t in enumerate(times):
        d_mu, d_rot = basis.offsets(means, quats, logits, t)
        assert torch.allclose(means + d_mu, traj[:, j], atol=1e-4)
        q = quats + d_rot
        # the same rotation (q and -q are one)
        assert bool(((q * rots[:, j]).sum(-1).abs() > 1 - 1e-5).all())
    # between two training times: the linear blend of the neighbours (the bodies' motions interpolated)
    d_mid, _ = basis.offsets(means, quats, logits, (times[3] + times[4]) / 2)
    assert torch.allclose(means[50:] + d_mid[50:], means[50:], atol=1e-6)
    assert float((means[:50] + d_mid[:50] - (traj[:50, 3] + traj[:50, 4]) / 2).norm(dim=-1).max()) < 0.02


def test_offsets_are_differentiable_in_every_input():
    times = [0.0, 0.5, 1.0]
    means, quats, traj, _ = _two_bodies(times)
    basis = MotionBasis(times, 2)
    logits, _ = basis.fit(means, traj, torch.arange(80) < 50, torch.Generator().manual_seed(0))
    m = means.clone().requires_grad_(True)
    lg = logits.clone().requires_grad_(True)
    d_mu, d_rot = basis.offsets(m, quats, lg, 0.25)
    (d_mu.square().sum() + d_rot.square().sum()).backward()
    assert m.grad is not None and lg.grad is not None
    assert basis.trans.grad is not None and float(basis.quat.grad.abs().sum()) > 0


def test_offsets_gradients_match_finite_differences():
    """The blend's analytic gradients (the weights' softmax written out, the rigid motions, the network's
    column) against central differences, float64, at logits that mix every option."""
    times = [0.0, 0.5, 1.0]
    means, quats, traj, _ = _two_bodies(times)
    basis = MotionBasis(times, 2, network=True).double()
    rigid = MotionBasis(times, 2)
    rigid.fit(means, traj, torch.arange(80) < 50, torch.Generator().manual_seed(0))
    basis.load_state_dict({k: v.double() for k, v in rigid.state_dict().items()})
    gen = torch.Generator().manual_seed(7)
    n = 12
    inputs = (means[:n].double(), quats[:n].double(), torch.randn(n, 4, generator=gen, dtype=torch.float64),
              torch.randn(n, 3, generator=gen, dtype=torch.float64), torch.randn(n, 4, generator=gen, dtype=torch.float64))
    inputs = tuple(x.clone().requires_grad_(True) for x in inputs)

    def f(m, q, lg, f0, f1):
        return basis.offsets(m, q, lg, 0.3, (f0, f1))

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7)


def test_state_round_trip():
    times = [0.0, 0.5, 1.0]
    means, quats, traj, _ = _two_bodies(times)
    basis = MotionBasis(times, 2)
    logits, _ = basis.fit(means, traj, torch.arange(80) < 50, torch.Generator().manual_seed(0))
    again = MotionBasis.from_state(basis.state())
    for t in (0.0, 0.3, 1.0):
        a = basis.offsets(means, quats, logits, t)
        b = again.offsets(means, quats, logits, t)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_the_network_option_blends_the_fields_offset_with_the_bases():
    """With ``network``, the last weight column takes the network's own (d mu, d r): all on it gives the
    field's offset exactly, all on a basis gives that basis's rigid motion, and a mix the same convex mix."""
    times = [0.0, 0.5, 1.0]
    means, quats, traj, _ = _two_bodies(times)
    rigid = MotionBasis(times, 2)
    logits, _ = rigid.fit(means, traj, torch.arange(80) < 50, torch.Generator().manual_seed(0), sharpness=8.0)
    both = MotionBasis(times, 2, network=True)
    both.load_state_dict(rigid.state_dict())
    gen = torch.Generator().manual_seed(5)
    field = (torch.randn(80, 3, generator=gen), torch.randn(80, 4, generator=gen))
    on_net = torch.cat([torch.full((80, 3), -1e4), torch.zeros(80, 1)], 1)
    d_mu, d_rot = both.offsets(means, quats, on_net, 0.3, field)
    assert torch.equal(d_mu, field[0]) and torch.equal(d_rot, field[1])
    off_net = torch.cat([logits, torch.full((80, 1), -1e4)], 1)
    a = both.offsets(means, quats, off_net, 0.3, field)
    b = rigid.offsets(means, quats, logits, 0.3)
    assert torch.allclose(a[0], b[0], atol=1e-5) and torch.allclose(a[1], b[1], atol=1e-5)
    # half on the network, half on one body's basis: the mean of the two offsets
    k = int(torch.softmax(logits, -1)[0].argmax())
    half = torch.full((80, 4), -1e4)
    half[:, k] = 0.0
    half[:, -1] = 0.0
    one = torch.full((80, 3), -1e4)
    one[:, k] = 0.0
    m = both.offsets(means, quats, half, 0.3, field)
    r = rigid.offsets(means, quats, one, 0.3)
    assert torch.allclose(m[0], (r[0] + field[0]) / 2, atol=1e-5)
    assert torch.allclose(m[1], (r[1] + field[1]) / 2, atol=1e-5)
    # the fit adds the column; a Gaussian whose best rigid misfit exceeds the network's takes the network
    back = MotionBasis(times, 2, network=True)
    lg, info = back.fit(means, traj, torch.arange(80) < 50, torch.Generator().manual_seed(0), sharpness=8.0,
                        network_err=torch.cat([torch.full((25,), 1e3), torch.zeros(55)]))
    assert lg.shape == (80, 4)
    assert bool((lg[:25].argmax(1) != 3).all()) and bool((lg[25:50].argmax(1) == 3).all())
    assert abs(info["network_share"] - 0.5) < 1e-6
    assert MotionBasis.from_state(back.state()).network


@pytest.mark.parametrize("warmup", [6, 14])
def test_resume_with_motion_bases_equals_an_uninterrupted_run(ci_dataset, tmp_path, warmup):
    """The bases are made at the P split (iteration warmup + 1): before the checkpoint at 12 (they travel in
    it, with their optimiser and the weights' rows) or after it (the resumed run makes them itself)."""
    from method.checkpoints import load_checkpoint
    from method.config import load_method_config
    from method.train import train_stage1
    from tests.test_method_stage1 import TINY

    torch.set_num_threads(1)
    cfg = lambda: load_method_config("ci", TINY + [  # noqa: E731
        f"stage1.warmup={warmup}", "stage1.p_from_motion=true", "model.motion_bases=3", "model.motion_knots=4"])
    full = tmp_path / "full"
    train_stage1(ci_dataset, "city", full, cfg(), seed=3, progress=False, write_outputs=False)
    part = tmp_path / "part"
    shutil.copytree(full, part)
    (part / "checkpoints" / "stage1_000024.pt").unlink()
    train_stage1(ci_dataset, "city", part, cfg(), seed=3, resume=True, progress=False, write_outputs=False)
    a = load_checkpoint(full / "checkpoints" / "stage1_000024.pt", "cpu")
    b = load_checkpoint(part / "checkpoints" / "stage1_000024.pt", "cpu")
    first = load_checkpoint(full / "checkpoints" / "stage1_000012.pt", "cpu")
    assert (first["basis"] is not None) == (warmup < 12)
    assert a["gaussians"]["basis_logit"].shape == (a["gaussians"]["means"].shape[0], 5)
    for k in a["gaussians"]:
        assert torch.equal(a["gaussians"][k], b["gaussians"][k]), k
    for k in ("quat", "trans", "pivot", "times"):
        assert torch.equal(a["basis"][k], b["basis"][k]), k
    assert not torch.equal(a["basis"]["trans"], torch.zeros_like(a["basis"]["trans"]))  # trained, not idle


def test_stage2_freezes_the_bases_and_their_weights():
    from method.stage2 import freeze_geometry

    times = [0.0, 1.0]
    means, quats, traj, _ = _two_bodies(times)
    g = Gaussians({"means": means, "quats": quats, "log_scales": torch.zeros(80, 2), "opacity_logit": torch.zeros(80),
                   "colour_logit": torch.zeros(80, 3), "p_logit": torch.zeros(80), "basis_logit": torch.zeros(80, 3)})
    scene = DynamicScene(g, None, torch.zeros(3), 1.0, 0.5, True, True)
    scene.basis = MotionBasis(times, 2)
    freeze_geometry(scene)
    assert not g.t["basis_logit"].requires_grad
    assert not any(p.requires_grad for p in scene.basis.parameters())


@pytest.mark.parametrize("extra,needle", [
    (["model.motion_bases=-1"], "model.motion_bases"),
    (["model.motion_bases=4"], "p_from_motion"),  # ci splits P by L_P alone: the bases would never be made
    (["model.motion_bases=4", "stage1.p_from_motion=true", "model.motion_knots=1"], "model.motion_knots"),
])
def test_motion_bases_settings_are_validated(extra, needle):
    from lumibench.errors import UserError
    from method.config import load_method_config

    with pytest.raises(UserError, match=needle):
        load_method_config("ci", extra)


def test_the_bases_settings_hash_only_where_the_bases_are_on(tmp_path):
    """A run without bases hashes the same whatever the bases' own settings (so runs recorded before they
    existed keep their hash); with bases, those settings set runs apart."""
    from method.config import load_method_config
    from method.run_record import identity, settings_hash, write_record

    def h(name, extra):
        write_record(tmp_path / name, load_method_config("small", extra), identity(tmp_path / "s", "city", 0, "cpu", False))
        return settings_hash(tmp_path / name)

    off = ["model.motion_bases=0"]  # small's default is 8 since session 46
    assert h("off", off) == h("off_knots", off + ["model.motion_knots=6", "stage1.basis_sharpness=2.0"])
    on = h("on", ["model.motion_bases=8"])
    assert on != h("off", off)
    assert on != h("on_knots", ["model.motion_bases=8", "model.motion_knots=6"])


@pytest.mark.parametrize("network", [True, False])
def test_the_compiled_blend_equals_the_torch_reference(network):
    """The compiled blend (method/model/basis_numba.py, what a CPU training runs) against the torch ops of
    offsets_reference, float64: both outputs and the gradients of every input (means, rotations, logits,
    the network's offsets, the bases' knots), at rotations off the unit sphere and bases far from the
    identity, so every term of the backward matters."""
    pytest.importorskip("numba")
    from method.model.basis_numba import basis_offsets

    gen = torch.Generator().manual_seed(3)
    n, bases = 300, 5
    basis = MotionBasis([0.0, 0.3, 0.7, 1.0], bases, network=network).double()
    with torch.no_grad():
        basis.quat.add_(0.5 * torch.randn(basis.quat.shape, generator=gen, dtype=torch.float64))
        basis.trans.add_(0.5 * torch.randn(basis.trans.shape, generator=gen, dtype=torch.float64))
        basis.pivot.copy_(torch.randn(basis.pivot.shape, generator=gen, dtype=torch.float64))
    leaves = [torch.randn(n, 3, generator=gen, dtype=torch.float64), torch.randn(n, 4, generator=gen, dtype=torch.float64),
              2 * torch.randn(n, bases + 1 + network, generator=gen, dtype=torch.float64),
              torch.randn(n, 3, generator=gen, dtype=torch.float64), torch.randn(n, 4, generator=gen, dtype=torch.float64)]
    g_mu = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    g_rot = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    results = []
    for compiled in (False, True):
        xs = [x.clone().requires_grad_(True) for x in leaves]
        basis.zero_grad()
        field = (xs[3], xs[4]) if network else None
        a, b, q = basis.at(0.45)
        if compiled:
            d_mu, d_rot = basis_offsets(xs[0], xs[1], xs[2], a, b, q, field)
        else:
            d_mu, d_rot = basis.offsets_reference(xs[0], xs[1], xs[2], (a, b, q), field)
        ((d_mu * g_mu).sum() + (d_rot * g_rot).sum()).backward()
        grads = [x.grad for x in (xs if network else xs[:3])] + [basis.quat.grad.clone(), basis.trans.grad.clone()]
        results.append([d_mu.detach(), d_rot.detach()] + grads)
    for want, got in zip(*results):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    assert float(results[0][-1].abs().max()) > 0.1 and float(results[0][-2].abs().max()) > 0.1  # the knots learn
