"""Which implementation runs the splat kernels: the pure-torch reference or the compiled CPU backend.

``auto`` (the default) takes the compiled kernels (Numba) for CPU tensors when numba is installed, and
the torch path otherwise (CUDA tensors always use torch). ``torch`` forces the reference, ``numba`` the
compiled kernels (an error if numba is missing or the tensors are on a GPU). The process-wide default
comes from the environment variable LUMIBENCH_SPLAT_BACKEND or set_backend(); every rasterize() and
trace() call can also name one.
"""
from __future__ import annotations

import contextlib
import os

import torch

BACKENDS = ("auto", "torch", "numba")
_default = os.environ.get("LUMIBENCH_SPLAT_BACKEND", "auto")
_numba_ok: bool | None = None


def check_backend(name: str) -> str:
    if name not in BACKENDS:
        raise ValueError(f"splat backend must be one of {', '.join(BACKENDS)}, got {name!r}")
    return name


def set_backend(name: str) -> None:
    """Set the process-wide default backend."""
    global _default
    _default = check_backend(name)


def get_backend() -> str:
    return check_backend(_default)


def numba_available() -> bool:
    global _numba_ok
    if _numba_ok is None:
        try:
            import numba  # noqa: F401
            _numba_ok = True
        except ImportError:
            _numba_ok = False
    return _numba_ok


def resolve(name: str | None, device: torch.device) -> str:
    """The implementation to run, 'torch' or 'numba', for tensors on ``device``."""
    name = check_backend(get_backend() if name is None else name)
    if name == "torch":
        return "torch"
    if name == "numba":
        if device.type != "cpu":
            raise ValueError(f"the numba splat backend runs on the CPU only; the tensors are on {device}")
        if not numba_available():
            raise ValueError("the numba splat backend needs numba (pip install numba); or use backend 'torch'")
        return "numba"
    return "numba" if device.type == "cpu" and numba_available() else "torch"


_kernel_threads: int | None = None  # set inside kernels_take_the_threads(); None: as many as torch uses


def kernel_threads() -> int | None:
    """How many threads the compiled kernels should run on, if not torch's count (see below)."""
    return _kernel_threads


@contextlib.contextmanager
def kernels_take_the_threads(device: torch.device):
    """Within: torch on one thread, the compiled kernels on the threads torch had (CPU, compiled backend,
    torch on more than one thread: a training alone; a grid worker is on one already and nothing changes).

    Why: torch's many small ops at the `small` sizes (the loss on 128 x 128 images, Adam over ~20k
    Gaussians) ran twice as slow on two threads as on one, while the kernels gain from the second. A
    whole `make train PROFILE=small` alone on 2 cores: stage 2 1.20x faster (211 s against 253), stage 1
    level (442 against 428 s: the network lost on one thread what the loss and the step gained), 16 % less
    CPU in all (BENCHMARKS.md, "small alone on 2 cores"); the network now takes every thread back for its
    own products (``on_the_kernels_threads``). Yields the kernels' thread count."""
    global _kernel_threads
    budget = torch.get_num_threads()
    if device.type != "cpu" or budget <= 1 or resolve(None, device) != "numba" or _kernel_threads is not None:
        yield _kernel_threads or budget
        return
    _kernel_threads = budget
    torch.set_num_threads(1)
    try:
        yield budget
    finally:
        _kernel_threads = None
        torch.set_num_threads(budget)


class _SetThreadsOnBackward(torch.autograd.Function):
    """Identity on its tensors; its backward sets torch's thread count to ``n`` before passing the
    gradients on (so the ops upstream of it in the graph, backward, run on ``n`` threads)."""

    @staticmethod
    def forward(ctx, n, *xs):
        ctx.n = n
        return tuple(x.view_as(x) for x in xs)

    @staticmethod
    def backward(ctx, *grads):
        torch.set_num_threads(ctx.n)
        return (None,) + grads


_pending_hooks: list = []  # the thread switch's hooks on the network's parameters not yet fired


def _switch_back_after(params: list[torch.Tensor]) -> None:
    """Set torch back to one thread once the backward has every gradient of ``params`` (the network's
    weights: the last thing its backward computes), by a hook that removes itself when it fires. A hook
    from a forward whose backward never ran is removed by the next call."""
    while _pending_hooks:
        _pending_hooks.pop().remove()
    handle = None

    def fire(_grads):
        torch.set_num_threads(1)
        if handle is not None:
            handle.remove()
            if handle in _pending_hooks:
                _pending_hooks.remove(handle)

    handle = torch.autograd.graph.register_multi_grad_hook(params, fire, mode="all")
    _pending_hooks.append(handle)


def on_the_kernels_threads(net: torch.nn.Module, x: torch.Tensor, *args):
    """``net(x, *args)`` (a tuple of tensors: the deformation network) with torch on every thread of a
    training alone, forward and backward, where ``kernels_take_the_threads`` left torch one.

    Why: the network's products at 4,096 nodes are large enough to gain from a second core, unlike the
    small ops the one thread is for (a `small` stage-1 step: BENCHMARKS.md, issue 23, session 39). The
    backward switches by a marker after the network (its backward sets all threads before the network's
    backward runs) and back to one thread when the network's weights have their gradients (a hook on them),
    or, where the weights take none (frozen) and ``x`` needs a gradient, by a marker on ``x``. Until session
    56 the switch back was a marker on ``x`` fed by a throw-away leaf, which made the network form the
    gradient of its input and its encoding where nothing needed them: the network's forward and backward at
    4,096 nodes took 31.6 ms with it and 27.5 without on one thread, 20.2 and 17.3 on two (BENCHMARKS.md,
    issue 23, session 56)."""
    n = _kernel_threads
    if n is None or n <= 1:
        return net(x, *args)
    grad = torch.is_grad_enabled()
    weights = [p for p in net.parameters() if p.requires_grad] if grad else []
    if grad and not weights and x.requires_grad:
        x, = _SetThreadsOnBackward.apply(1, x)
    torch.set_num_threads(n)
    try:
        out = net(x, *args)
    finally:
        torch.set_num_threads(1)
    if grad and any(o.requires_grad for o in out):
        if weights:
            _switch_back_after(weights)
        out = _SetThreadsOnBackward.apply(n, *out)
    return out
