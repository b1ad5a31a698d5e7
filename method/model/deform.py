"""The deformation network and the static/dynamic variable P (paper section "Stage 1").

MLP(enc(mu), timenet(enc(t))) -> (d mu, d r, d c); mu' = mu + P d mu, r' = r + P d r, c' = c (1 - d c)
with d c clamped to <= 1 (no activation). The heads start at zero, so an untrained network leaves
every Gaussian at its canonical state (and the dynamic model equals the static one).

``precision`` ("fp32" or "bf16", the ``model.mlp_precision`` setting): the trunk's matrix products in
bfloat16 (torch autocast; fp32 accumulation, fp32 weights and optimiser). The encodings, the three heads
and everything downstream stay fp32. On a CPU with native bf16 (AVX512-BF16, AMX) the trunk's forward and
backward run about 3x faster, and the trunk is most of a stage-1 iteration (BENCHMARKS.md).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

PRECISIONS = ("fp32", "bf16")


def positional_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """[x, sin(2^k x), cos(2^k x)] for k < freqs (NeRF / Deformable 3DGS; no pi factor): the column order
    the network's weights are stored in."""
    parts = [x]
    for k in range(freqs):
        s = x * (2.0 ** k)
        parts += [torch.sin(s), torch.cos(s)]
    return torch.cat(parts, -1)


def blocked_order(dims: int, freqs: int) -> list[int]:
    """Column j of ``blocked_encoding``'s output is column ``blocked_order(...)[j]`` of
    ``positional_encoding``'s."""
    width = 2 * dims
    sines = [dims + width * k + d for k in range(freqs) for d in range(dims)]
    return list(range(dims)) + sines + [c + dims for c in sines]


class _BlockedEncoding(torch.autograd.Function):
    """[x, sin(S), cos(S)] with S = [2^k x]_k (N, freqs * dims): the encoding's values in three blocks, from
    two whole-tensor transcendental calls; the backward reuses them (d sin(a x) = a cos(a x) dx, d cos(a x) =
    -a sin(a x) dx) and folds the 2^k and the sum over k into one small product. The op-by-op encoding is
    ~50 small ops forward and backward (one thin concatenation of 13 pieces among them): ~1.8 ms a `small`
    step at 4,096 points on one thread (BENCHMARKS.md, session 41)."""

    @staticmethod
    def forward(ctx, x, freqs):
        n, d = x.shape
        scales = 2.0 ** torch.arange(freqs, dtype=x.dtype, device=x.device)  # exact powers of two
        s = (x.unsqueeze(1) * scales.unsqueeze(-1)).reshape(n, freqs * d)
        sn, cs = torch.sin(s), torch.cos(s)
        ctx.save_for_backward(sn, cs)
        ctx.fold = torch.kron(scales.unsqueeze(-1), torch.eye(d, dtype=x.dtype, device=x.device))  # (freqs d, d)
        return torch.cat([x, sn, cs], -1)

    @staticmethod
    def backward(ctx, g):
        sn, cs = ctx.saved_tensors
        d = ctx.fold.shape[1]
        m = sn.shape[1]
        g_s = g[:, d:d + m] * cs - g[:, d + m:] * sn
        return g[:, :d] + g_s @ ctx.fold, None


def blocked_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """``positional_encoding(x, freqs)``'s values (x: (N, dims)) in the column order ``blocked_order``."""
    if freqs <= 0:
        return x
    return _BlockedEncoding.apply(x, freqs)


class DeformNet(nn.Module):
    def __init__(self, depth: int = 8, width: int = 256, skip: int = 4, pos_freqs: int = 10, time_freqs: int = 6,
                 time_net_width: int = 256, time_net_out: int = 30, precision: str = "fp32"):
        super().__init__()
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)} (got {precision!r})")
        self.pos_freqs, self.time_freqs, self.skip = pos_freqs, time_freqs, skip
        self.precision = precision
        pos_dim = 3 * (1 + 2 * pos_freqs)
        t_dim = 1 + 2 * time_freqs
        self.time_net = nn.Sequential(nn.Linear(t_dim, time_net_width), nn.ReLU(), nn.Linear(time_net_width, time_net_out))
        in_dim = pos_dim + time_net_out
        layers = []
        for i in range(depth):
            d_in = in_dim if i == 0 else width + (in_dim if skip and i == skip else 0)
            layers.append(nn.Linear(d_in, width))
        self.layers = nn.ModuleList(layers)
        # the first and the skip layer read the position encoding in blocked_encoding's order: their
        # weight's encoding columns are gathered to match (the stored layout stays positional_encoding's)
        order = torch.tensor(blocked_order(3, pos_freqs))
        self.register_buffer("_enc_cols", order, persistent=False)
        self.d_mu = nn.Linear(width, 3)
        self.d_rot = nn.Linear(width, 4)
        self.d_col = nn.Linear(width, 3)
        for head in (self.d_mu, self.d_rot, self.d_col):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def forward(self, x_norm: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``x_norm``: canonical positions mapped to about [-1, 1] (scene box); ``t`` in [0, 1]."""
        return self.heads(self.trunk(x_norm, t))

    def heads(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(d mu, d r, d c) from the trunk's last features: the three heads as one product of h with their
        stacked weights (3 + 4 + 3 outputs), so h is read once forward and once backward rather than three
        times (about 1.1x the network's forward + backward at `small`, BENCHMARKS.md); the parameters stay
        the three layers checkpoints know."""
        heads = (self.d_mu, self.d_rot, self.d_col)
        out = F.linear(h, torch.cat([m.weight for m in heads]), torch.cat([m.bias for m in heads]))
        d_mu, d_rot, d_col = out.split([m.out_features for m in heads], dim=-1)
        return d_mu, d_rot, torch.clamp_max(d_col, 1.0)

    def trunk(self, x_norm: torch.Tensor, t: float) -> torch.Tensor:
        """The last hidden features (N, width, fp32): everything but the three heads."""
        if self.precision == "fp32":
            return self._trunk(x_norm, t)
        with torch.autocast(device_type=x_norm.device.type, dtype=torch.bfloat16):
            h = self._trunk(x_norm, t)
        return h.float()

    def _trunk(self, x_norm: torch.Tensor, t: float) -> torch.Tensor:
        """The MLP on [enc(mu), timenet(enc(t))], with the time features' share of the first and the skip
        layer's product taken once: every Gaussian of a call has the same ``t``, so W_t timenet(enc(t)) + b is
        one bias row rather than N products (the same sums in another order; 1.15x the network's forward
        and backward at `small`, BENCHMARKS.md)."""
        tt = torch.full((1, 1), float(t), dtype=x_norm.dtype, device=x_norm.device)
        tfeat = self.time_net(positional_encoding(tt, self.time_freqs))  # (1, time_net_out)
        enc = blocked_encoding(x_norm, self.pos_freqs)
        e = enc.shape[-1]
        first = self.layers[0]
        bias = F.linear(tfeat, first.weight[:, e:], first.bias)[0]
        h = torch.relu_(F.linear(enc, first.weight[:, self._enc_cols], bias))
        for i, layer in enumerate(self.layers[1:], 1):
            if self.skip and i == self.skip:
                # [h, enc] W^T as h W_h^T + enc W_e^T: no product has the odd width 167 (at `small` its
                # backward ran at half the speed of the 128-wide ones), and the encoding's gradient is only
                # formed where the positions need one (never at the nodes) (BENCHMARKS.md, issue 23, sessions
                # 55-56)
                w = h.shape[-1]
                bias = F.linear(tfeat, layer.weight[:, w + e:], layer.bias)[0]
                h = torch.addmm(F.linear(enc, layer.weight[:, w + self._enc_cols], bias), h, layer.weight[:, :w].t())
            else:
                h = layer(h)
            h = torch.relu_(h)  # in place: the products' backward needs their inputs, not their outputs
        return h

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def binary_concrete(logits: torch.Tensor, temperature: float, generator: torch.Generator | None = None,
                    training: bool = True) -> torch.Tensor:
    """P = sigmoid((logit + log u - log(1 - u)) / T), u ~ U(0, 1) in training and u = 0.5 at inference
    (the logistic noise vanishes, P = sigmoid(logit / T))."""
    if not training:
        return torch.sigmoid(logits / temperature)
    u = torch.rand(logits.shape, generator=generator, dtype=logits.dtype).to(logits.device)
    u = u.clamp(1e-6, 1 - 1e-6)
    return torch.sigmoid((logits + torch.log(u) - torch.log1p(-u)) / temperature)
