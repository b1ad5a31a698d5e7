"""Adaptive density control (method/model/density.py) and the Adam that follows the Gaussian count
(method/model/gaussians.py: GaussianAdam) on small hand-made cases whose outcome can be stated exactly:
clone, split, prune, the cap, the optimiser state moving with the rows, and the opacity reset."""
from __future__ import annotations

import math

import pytest
import torch

from method.model.density import DensityStats, densify_and_prune, reset_opacity
from method.model.gaussians import PER_GAUSSIAN, GaussianAdam, Gaussians, inverse_sigmoid
from method.splat.splats import quat_to_rotmat

LRS = {"means": 1e-3, "quats": 1e-3, "log_scales": 5e-3, "opacity_logit": 0.05, "colour_logit": 0.01, "p_logit": 0.01}
SMALL, BIG = 0.005, 0.3  # splat scales on either side of percent_dense * extent = 0.01
DEFAULTS = dict(grad_threshold=0.5, percent_dense=0.01, extent=1.0, min_opacity=0.005, max_gaussians=0,
                max_screen_radius=None)


def _gaussians(scales, opacities=None, seed=0) -> Gaussians:
    """One Gaussian per entry of ``scales`` (a number: isotropic, or a pair), distinct values in every tensor."""
    n = len(scales)
    gen = torch.Generator().manual_seed(seed)
    sc = torch.tensor([[s, s] if not isinstance(s, (tuple, list)) else list(s) for s in scales], dtype=torch.float32)
    op = torch.full((n,), 0.5) if opacities is None else torch.tensor(opacities, dtype=torch.float32)
    q = torch.randn(n, 4, generator=gen)
    return Gaussians({
        "means": torch.randn(n, 3, generator=gen),
        "quats": q / q.norm(dim=-1, keepdim=True),
        "log_scales": sc.log(),
        "opacity_logit": inverse_sigmoid(op),
        "colour_logit": torch.randn(n, 3, generator=gen),
        "p_logit": torch.randn(n, generator=gen),
    })


def _stats(grads, radii=None) -> DensityStats:
    """Statistics whose mean gradient is exactly ``grads`` (count 1 each)."""
    n = len(grads)
    st = DensityStats(n)
    st.grad = torch.tensor(grads, dtype=torch.float32)
    st.count = torch.ones(n)
    if radii is not None:
        st.max_radii = torch.tensor(radii, dtype=torch.float32)
    return st


def _run(g, grads, radii=None, seed=0, **kw):
    opt = GaussianAdam(g, LRS)
    st = _stats(grads, radii)
    args = {**DEFAULTS, **kw}
    res = densify_and_prune(g, opt, st, generator=torch.Generator().manual_seed(seed), **args)
    return res, opt, st


def _snapshot(g):
    return {k: v.detach().clone() for k, v in g.t.items()}


def _assert_rows_equal(after, before, rows_after, rows_before):
    for k in PER_GAUSSIAN:
        torch.testing.assert_close(after[k][rows_after], before[k][rows_before], rtol=0, atol=0, msg=k)


# ------------------------------------------------------------------------------------------ statistics

def test_density_stats_accumulate_the_ndc_gradient_norm_of_visible_gaussians():
    st = DensityStats(3)
    W, H = 200, 100
    # pixel-space gradients; NDC gradient = pixel gradient x (W / 2, H / 2)
    g1 = torch.tensor([[0.03, 0.08], [1.0, 1.0], [0.0, 0.0]])
    st.add(g1, torch.tensor([True, False, True]), torch.tensor([4, 99, 7]), W, H)
    g2 = torch.tensor([[0.0, 0.02], [0.5, 0.0], [0.0, 0.0]])
    st.add(g2, torch.tensor([True, True, False]), torch.tensor([2, 5, 50]), W, H)
    exp0 = math.hypot(0.03 * 100, 0.08 * 50) + 0.02 * 50  # 5 + 1
    torch.testing.assert_close(st.grad, torch.tensor([exp0, 0.5 * 100, 0.0]))
    torch.testing.assert_close(st.count, torch.tensor([2.0, 1.0, 1.0]))
    torch.testing.assert_close(st.mean(), torch.tensor([exp0 / 2, 50.0, 0.0]))
    # the invisible radius 99 (first add) and 50 (second) are not counted
    torch.testing.assert_close(st.max_radii, torch.tensor([4.0, 5.0, 7.0]))
    assert float(DensityStats(2).mean().sum()) == 0.0  # no visits: mean 0, not NaN


# ------------------------------------------------------------------------------------------------ clone

def test_clone_copies_a_small_gaussian_at_or_above_the_threshold_exactly_once():
    g = _gaussians([SMALL, SMALL, SMALL])
    before = _snapshot(g)
    # 0.5 is exactly the threshold (>= clones), 0.4999 is below it, 0.75 above
    res, _, st = _run(g, [0.5, 0.4999, 0.75])
    assert res == {"cloned": 2, "split": 0, "pruned": 0}
    assert len(g) == 5
    after = _snapshot(g)
    _assert_rows_equal(after, before, [0, 1, 2], [0, 1, 2])  # originals untouched, in place
    _assert_rows_equal(after, before, [3, 4], [0, 2])  # identical copies appended in order
    assert st.grad.shape == (5,) and float(st.grad.abs().sum()) == 0.0


def test_below_the_threshold_nothing_changes():
    g = _gaussians([SMALL, BIG])
    before = _snapshot(g)
    res, _, _ = _run(g, [0.49, 0.3])
    assert res == {"cloned": 0, "split": 0, "pruned": 0}
    _assert_rows_equal(_snapshot(g), before, [0, 1], [0, 1])


def test_non_finite_gradient_statistics_are_treated_as_zero():
    g = _gaussians([SMALL, SMALL])
    res, _, _ = _run(g, [float("nan"), float("inf")])
    assert res == {"cloned": 0, "split": 0, "pruned": 0} and len(g) == 2


# ------------------------------------------------------------------------------------------------ split

def test_split_replaces_a_large_gaussian_by_two_shrunk_children_in_its_plane():
    g = _gaussians([SMALL, (BIG, 0.1), SMALL])
    before = _snapshot(g)
    res, _, _ = _run(g, [0.0, 0.6, 0.0], seed=3)
    assert res == {"cloned": 0, "split": 1, "pruned": 1}
    assert len(g) == 4  # 3 + 2 children - the parent
    after = _snapshot(g)
    _assert_rows_equal(after, before, [0, 1], [0, 2])  # the parent (row 1) is gone, the others keep order
    kids = slice(2, 4)
    # scales shrink by 1.6 (3DGS: 0.8 x the number of children, 2)
    torch.testing.assert_close(after["log_scales"][kids], before["log_scales"][[1, 1]] - math.log(1.6))
    torch.testing.assert_close(after["log_scales"][kids].exp(), before["log_scales"][[1, 1]].exp() / 1.6)
    for k in ("quats", "opacity_logit", "colour_logit", "p_logit"):
        torch.testing.assert_close(after[k][kids], before[k][[1, 1]], rtol=0, atol=0, msg=k)
    # the children lie in the parent's plane, within a few sigmas of its centre along each tangent axis
    rot = quat_to_rotmat(before["quats"][1:2])[0]
    off = after["means"][kids] - before["means"][1]
    local = off @ rot  # columns: tangent u, tangent v, normal
    assert float(local[:, 2].abs().max()) < 1e-6
    assert float((local[:, 0].abs() / BIG).max()) < 5 and float((local[:, 1].abs() / 0.1).max()) < 5
    assert not torch.equal(after["means"][2], after["means"][3])


def test_large_means_largest_scale_above_percent_dense_times_extent():
    # (0.3, 0.001): large by its largest scale, so split; (0.009, 0.009) at extent 1: small (0.009 <= 0.01),
    # but large at extent 0.5 (0.009 > 0.005)
    g = _gaussians([(0.3, 0.001), (0.009, 0.009)])
    res, _, _ = _run(g, [0.9, 0.9])
    assert res == {"cloned": 1, "split": 1, "pruned": 1} and len(g) == 4
    res, _, _ = _run(_gaussians([(0.009, 0.009)]), [0.9], extent=0.5)
    assert res == {"cloned": 0, "split": 1, "pruned": 1}


def test_split_children_are_distributed_as_the_parent_splat_and_deterministic():
    """Many large splats of one anisotropic shape, randomly oriented: the children's offsets, in each parent's tangent frame and
    divided by the parent's scales, are standard normal (the sampling uses the parent's scales, not the
    shrunk ones, along the right axes); the same generator state gives the same children."""
    n = 3000
    sc = (0.4, 0.05)

    def run(seed):
        g = _gaussians([sc] * n, seed=1)
        before = _snapshot(g)
        res, _, _ = _run(g, [1.0] * n, seed=seed)
        assert res == {"cloned": 0, "split": n, "pruned": n} and len(g) == 2 * n
        return before, _snapshot(g)

    before, after = run(11)
    rot = quat_to_rotmat(before["quats"])  # (n, 3, 3)
    par = torch.arange(n).repeat(2)  # children: first sample of every parent, then the second
    off = after["means"] - before["means"][par]
    local = torch.einsum("nk,nkj->nj", off, rot[par])
    assert float(local[:, 2].abs().max()) < 1e-5
    zu, zv = local[:, 0] / sc[0], local[:, 1] / sc[1]
    for z in (zu, zv):
        assert abs(float(z.mean())) < 0.05
        assert float(z.std()) == pytest.approx(1.0, abs=0.05)
    assert abs(float((zu * zv).mean())) < 0.05  # independent axes
    _, again = run(11)
    for k in PER_GAUSSIAN:
        torch.testing.assert_close(again[k], after[k], rtol=0, atol=0)
    _, other = run(12)
    assert not torch.equal(other["means"], after["means"])


# ------------------------------------------------------------------------------------------------ prune

def test_prune_transparent_gaussians():
    g = _gaussians([SMALL, SMALL, SMALL], opacities=[0.004, 0.006, 0.5])
    before = _snapshot(g)
    res, _, st = _run(g, [0.0, 0.0, 0.0])
    assert res == {"cloned": 0, "split": 0, "pruned": 1}
    assert len(g) == 2 and st.grad.shape == (2,)
    _assert_rows_equal(_snapshot(g), before, [0, 1], [1, 2])


def test_prune_oversized_screen_radius_only_when_a_limit_is_given():
    radii = [30.0, 10.0, 20.0]
    g = _gaussians([SMALL, SMALL, SMALL])
    res, _, _ = _run(g, [0.0, 0.0, 0.0], radii=radii, max_screen_radius=None)
    assert res["pruned"] == 0 and len(g) == 3
    g = _gaussians([SMALL, SMALL, SMALL])
    before = _snapshot(g)
    res, _, _ = _run(g, [0.0, 0.0, 0.0], radii=radii, max_screen_radius=20.0)
    assert res["pruned"] == 1 and len(g) == 2  # 30 > 20 goes; 20 (not above) stays
    _assert_rows_equal(_snapshot(g), before, [0, 1], [1, 2])


def test_prune_large_world_size_only_with_the_screen_limit():
    # world rule: max scale > 0.1 x extent (extent 2: 0.2); 0.25 goes, 0.15 stays
    scales = [(0.25, 0.01), (0.15, 0.15), SMALL]
    g = _gaussians(scales)
    res, _, _ = _run(g, [0.0] * 3, extent=2.0, max_screen_radius=None)
    assert res["pruned"] == 0 and len(g) == 3
    g = _gaussians(scales)
    before = _snapshot(g)
    res, _, _ = _run(g, [0.0] * 3, extent=2.0, max_screen_radius=1e9)
    assert res["pruned"] == 1 and len(g) == 2
    _assert_rows_equal(_snapshot(g), before, [0, 1], [1, 2])


def test_never_prunes_every_gaussian():
    g = _gaussians([SMALL, SMALL], opacities=[0.001, 0.002])
    res, _, _ = _run(g, [0.0, 0.0])
    assert res["pruned"] == 0 and len(g) == 2


def test_new_copies_of_a_transparent_gaussian_are_pruned_with_it():
    """A clone copies the opacity, so the opacity rule (applied after densification) removes both."""
    g = _gaussians([SMALL, SMALL], opacities=[0.001, 0.5])
    res, _, _ = _run(g, [0.9, 0.0])
    assert res == {"cloned": 1, "split": 0, "pruned": 2} and len(g) == 1


# -------------------------------------------------------------------------------------------------- cap

def test_cap_takes_the_highest_gradients_first():
    # 4 Gaussians, room for 2 more: candidates 0 (0.9, small), 1 (0.6, small), 2 (0.7, big), 3 (0.8, small)
    g = _gaussians([SMALL, SMALL, BIG, SMALL])
    before = _snapshot(g)
    res, _, _ = _run(g, [0.9, 0.6, 0.7, 0.8], max_gaussians=6)
    assert res == {"cloned": 2, "split": 0, "pruned": 0}
    assert len(g) == 6
    _assert_rows_equal(_snapshot(g), before, [0, 1, 2, 3, 4, 5], [0, 1, 2, 3, 0, 3])
    # the big one first: it is split (net +1), then the best clone
    g = _gaussians([SMALL, SMALL, BIG, SMALL])
    before = _snapshot(g)
    res, _, _ = _run(g, [0.9, 0.6, 0.95, 0.8], max_gaussians=6)
    assert res == {"cloned": 1, "split": 1, "pruned": 1}
    assert len(g) == 6
    after = _snapshot(g)
    _assert_rows_equal(after, before, [0, 1, 2, 3], [0, 1, 3, 0])
    torch.testing.assert_close(after["log_scales"][4:], before["log_scales"][[2, 2]] - math.log(1.6))


def test_cap_is_never_exceeded():
    assert len(_run(_gaussians([SMALL] * 5), [1.0] * 5, max_gaussians=4)[1].g) == 5  # already over: no growth
    res, opt, _ = _run(_gaussians([SMALL] * 3), [1.0] * 3, max_gaussians=3)
    assert res["cloned"] == 0 and len(opt.g) == 3
    # room for everything: the cap does not bite
    res, opt, _ = _run(_gaussians([SMALL, BIG, SMALL]), [1.0] * 3, max_gaussians=6)
    assert res == {"cloned": 2, "split": 1, "pruned": 1} and len(opt.g) == 6  # 3 + 2 + 2 - 1
    # random mixes of sizes and gradients
    gen = torch.Generator().manual_seed(0)
    for trial in range(20):
        n = int(torch.randint(2, 12, (1,), generator=gen))
        cap = n + int(torch.randint(0, 6, (1,), generator=gen))
        big = torch.rand(n, generator=gen) < 0.5
        scales = [BIG if b else SMALL for b in big.tolist()]
        grads = torch.rand(n, generator=gen).tolist()
        res, opt, _ = _run(_gaussians(scales, seed=trial), grads, max_gaussians=cap, grad_threshold=0.3)
        assert len(opt.g) <= cap
        n_cand = sum(x >= 0.3 for x in grads)
        assert res["cloned"] + res["split"] == min(n_cand, cap - n)


# ------------------------------------------------------------------------------------ optimiser state

def _stepped_adam(g, seed=0, steps=2):
    """GaussianAdam after ``steps`` steps with known, distinct gradients (non-zero moments in every row)."""
    opt = GaussianAdam(g, LRS)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        opt.zero_grad()
        for k in PER_GAUSSIAN:
            g.t[k].grad = torch.randn(g.t[k].shape, generator=gen)
        opt.step()
    return opt


def _moments(opt):
    out = {}
    for grp in opt.opt.param_groups:
        p = grp["params"][0]
        st = opt.opt.state[p]
        out[grp["name"]] = {"exp_avg": st["exp_avg"].clone(), "exp_avg_sq": st["exp_avg_sq"].clone(),
                            "step": float(st["step"])}
    return out


def _check_optimiser_points_at_the_tensors(opt, g):
    for grp in opt.opt.param_groups:
        p = grp["params"][0]
        assert p is g.t[grp["name"]] and p.is_leaf and p.requires_grad
        st = opt.opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
    assert len(opt.opt.state) == len(PER_GAUSSIAN)  # no stale entries for the replaced tensors


def test_adam_moments_follow_clone_split_and_prune():
    # 0: clone; 1: split; 2: pruned (transparent); 3, 4: untouched
    g = _gaussians([SMALL, BIG, SMALL, SMALL, BIG], opacities=[0.5, 0.5, 0.001, 0.5, 0.5])
    opt = _stepped_adam(g)
    before, mom = _snapshot(g), _moments(opt)
    st = _stats([0.8, 0.9, 0.0, 0.1, 0.2], radii=[1.0, 2.0, 3.0, 4.0, 5.0])
    res = densify_and_prune(g, opt, st, generator=torch.Generator().manual_seed(0), **DEFAULTS)
    assert res == {"cloned": 1, "split": 1, "pruned": 2}
    # rows: originals 0, 3, 4 (1 split, 2 pruned), then the clone of 0, then 1's two children
    assert len(g) == 6
    _assert_rows_equal(_snapshot(g), before, [0, 1, 2, 3], [0, 3, 4, 0])
    _check_optimiser_points_at_the_tensors(opt, g)
    new = _moments(opt)
    for name in PER_GAUSSIAN:
        for m in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(new[name][m][:3], mom[name][m][[0, 3, 4]], rtol=0, atol=0, msg=name)
            assert float(new[name][m][3:].abs().sum()) == 0.0, f"{name} {m}: new rows start at zero"
        assert new[name]["step"] == mom[name]["step"] == 2.0
    # statistics: reset to the new count
    for t in (st.grad, st.count, st.max_radii):
        assert t.shape == (6,) and float(t.abs().sum()) == 0.0
    # the optimiser still steps the (new) tensors, new rows with Adam's first-step size (zero moments)
    opt.zero_grad()
    for k in PER_GAUSSIAN:
        g.t[k].grad = torch.ones_like(g.t[k])
    pre = _snapshot(g)
    opt.step()
    moved = g.t["means"].detach() - pre["means"]
    assert float(moved.abs().min()) > 0
    # zero moments, step 3: m = 0.1, v = 0.001; m_hat / sqrt(v_hat) = (0.1 / (1 - 0.9^3)) / sqrt(0.001 / (1 - 0.999^3))
    m_hat = 0.1 / (1 - 0.9 ** 3)
    v_hat = 0.001 / (1 - 0.999 ** 3)
    torch.testing.assert_close(moved[3:], torch.full((3, 3), -LRS["means"] * m_hat / math.sqrt(v_hat)),
                               rtol=1e-3, atol=1e-7)


def test_adam_keep_and_append_directly():
    g = _gaussians([SMALL] * 4)
    opt = _stepped_adam(g, seed=4, steps=1)
    mom = _moments(opt)
    before = _snapshot(g)
    opt.keep(torch.tensor([True, False, True, False]))
    _check_optimiser_points_at_the_tensors(opt, g)
    new = _moments(opt)
    for name in PER_GAUSSIAN:
        torch.testing.assert_close(new[name]["exp_avg"], mom[name]["exp_avg"][[0, 2]], rtol=0, atol=0)
        torch.testing.assert_close(new[name]["exp_avg_sq"], mom[name]["exp_avg_sq"][[0, 2]], rtol=0, atol=0)
    rows = {k: v[[1, 3, 3]] for k, v in before.items()}
    opt.append(rows)
    assert len(g) == 5
    _check_optimiser_points_at_the_tensors(opt, g)
    _assert_rows_equal(_snapshot(g), before, [0, 1, 2, 3, 4], [0, 2, 1, 3, 3])
    after = _moments(opt)
    for name in PER_GAUSSIAN:
        torch.testing.assert_close(after[name]["exp_avg"][:2], mom[name]["exp_avg"][[0, 2]], rtol=0, atol=0)
        assert float(after[name]["exp_avg"][2:].abs().sum()) == 0.0
        assert float(after[name]["exp_avg_sq"][2:].abs().sum()) == 0.0


def test_reset_opacity_clamps_to_the_value_and_clears_only_the_opacity_moments():
    g = _gaussians([SMALL] * 4, opacities=[0.9, 0.005, 0.5, 0.0101])
    opt = _stepped_adam(g)
    mom = _moments(opt)
    before = _snapshot(g)
    op = g.opacities.detach().clone()  # after the steps: about 0.9, 0.005, 0.5, 0.0101
    assert float(op[1]) < 0.0099 and float(op[3]) > 0.01
    reset_opacity(g, opt, 0.01)
    expect = torch.tensor([0.01, float(op[1]), 0.01, 0.01])
    torch.testing.assert_close(g.opacities.detach(), expect, rtol=1e-5, atol=0)
    for k in PER_GAUSSIAN:
        if k != "opacity_logit":
            torch.testing.assert_close(g.t[k].detach(), before[k], rtol=0, atol=0)
    _check_optimiser_points_at_the_tensors(opt, g)
    new = _moments(opt)
    for name in PER_GAUSSIAN:
        for m in ("exp_avg", "exp_avg_sq"):
            if name == "opacity_logit":  # 3DGS: the reset tensor's moments restart from zero
                assert float(new[name][m].abs().sum()) == 0.0
            else:
                torch.testing.assert_close(new[name][m], mom[name][m], rtol=0, atol=0)
    # the default value is 0.01, and a later step moves the reset tensor (it is the optimised one)
    g2 = _gaussians([SMALL] * 2, opacities=[0.7, 0.2])
    opt2 = _stepped_adam(g2, steps=1)
    reset_opacity(g2, opt2)
    torch.testing.assert_close(g2.opacities.detach(), torch.full((2,), 0.01), rtol=1e-5, atol=0)
    g2.t["opacity_logit"].grad = torch.ones(2)
    opt2.step()
    assert float(g2.opacities.detach().max()) < 0.01
