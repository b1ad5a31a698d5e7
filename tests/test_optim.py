"""method.optim.adam: torch's fused Adam, held to the per-tensor loop it replaces."""
import copy

import torch

from method.optim import adam


def _problem(seed):
    g = torch.Generator().manual_seed(seed)
    params = [torch.randn(200, 3, generator=g, dtype=torch.float64).requires_grad_(),
              torch.randn(50, generator=g, dtype=torch.float64).requires_grad_()]
    grads = [[torch.randn(p.shape, generator=g, dtype=torch.float64) for p in params] for _ in range(20)]
    return params, grads


def _run(opt, params, grads):
    for gs in grads:
        for p, gr in zip(params, gs):
            p.grad = gr.clone()
        opt.step()
    return [p.detach().clone() for p in params]


def test_adam_is_fused_on_the_cpu_and_matches_the_loop():
    params, grads = _problem(0)
    ref_params = [p.detach().clone().requires_grad_() for p in params]
    groups = [{"params": [params[0]], "lr": 0.01}, {"params": [params[1]], "lr": 0.003}]
    opt = adam(groups, eps=1e-15)
    assert opt.param_groups[0]["fused"] is True
    loop = torch.optim.Adam([{"params": [ref_params[0]], "lr": 0.01}, {"params": [ref_params[1]], "lr": 0.003}],
                            eps=1e-15, foreach=False)
    got, want = _run(opt, params, grads), _run(loop, ref_params, grads)
    moved = sum(float((w - p0).abs().max()) for w, p0 in zip(want, _problem(0)[0]))
    assert moved > 0.01  # the steps did something the comparison can see
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_a_checkpoint_of_the_loop_adam_resumes_as_it_was_trained():
    """A state dict saved by the per-tensor Adam (runs from before the change) loads into ``adam`` and the
    run continues exactly as the loop would have continued it (the saved group keeps its own settings)."""
    params, grads = _problem(1)
    a = [p.detach().clone().requires_grad_() for p in params]
    loop = torch.optim.Adam(a, lr=0.01, eps=1e-15, foreach=False)
    _run(loop, a, grads[:10])
    b = [p.detach().clone().requires_grad_() for p in a]
    fused = adam(b, lr=0.01, eps=1e-15)
    fused.load_state_dict(copy.deepcopy(loop.state_dict()))  # as a checkpoint file does
    for a_, b_ in zip(_run(loop, a, grads[10:]), _run(fused, b, grads[10:])):
        torch.testing.assert_close(a_, b_, rtol=0, atol=0)
