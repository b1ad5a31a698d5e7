"""Canonical 2D Gaussians: the learnable tensors, their activations, initialisation and an Adam that
follows the Gaussian count as density control clones, splits and prunes.

Raw tensors (one row per Gaussian): ``means`` (3), ``quats`` (4, w-x-y-z, normalised where used),
``log_scales`` (2), ``opacity_logit``, ``colour_logit`` (3; colour = sigmoid, display space, the
canonical colour that seeds stage 2's albedo) and ``p_logit`` (the static/dynamic variable).
"""
from __future__ import annotations

import math

import torch

from method.optim import adam

PER_GAUSSIAN = ("means", "quats", "log_scales", "opacity_logit", "colour_logit", "p_logit")
OPTIONAL = ("basis_logit",)  # (N, options) motion-basis weights' logits, from the warm-up's end (motion_basis.py)


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(1e-6, 1 - 1e-6)
    return torch.log(x / (1 - x))


def random_quats(n: int, generator: torch.Generator) -> torch.Tensor:
    """Uniformly distributed rotations (normalised Gaussian 4-vectors)."""
    q = torch.randn(n, 4, generator=generator)
    return q / q.norm(dim=-1, keepdim=True)


def nearest_distance(points: torch.Tensor, k: int = 3, chunk: int = 4096) -> torch.Tensor:
    """Mean distance to the ``k`` nearest other points (the initial splat size), chunked cdist."""
    n = points.shape[0]
    if n <= 1:
        return torch.ones(n, dtype=points.dtype)
    k = min(k, n - 1)
    out = []
    for i in range(0, n, chunk):
        d = torch.cdist(points[i:i + chunk], points)
        d[torch.arange(d.shape[0]), torch.arange(i, i + d.shape[0])] = float("inf")
        out.append(d.topk(k, largest=False).values.mean(1))
    return torch.cat(out)


class Gaussians:
    """The per-Gaussian tensors (leaf tensors with gradients) and their activations."""

    def __init__(self, tensors: dict[str, torch.Tensor]):
        missing = [k for k in PER_GAUSSIAN if k not in tensors]
        if missing:
            raise ValueError(f"missing Gaussian tensors: {missing}")
        self.t = {k: tensors[k].detach().clone().requires_grad_(True) for k in PER_GAUSSIAN + OPTIONAL
                  if k in tensors}

    @staticmethod
    def from_points(points: torch.Tensor, init_opacity: float, p_init_logit: float,
                    generator: torch.Generator, colours: torch.Tensor | None = None,
                    scale_factor: float = 1.0) -> "Gaussians":
        n = points.shape[0]
        scale = (nearest_distance(points) * scale_factor).clamp_min(1e-4)
        col = torch.full((n, 3), 0.5) if colours is None else colours
        return Gaussians({
            "means": points.float(),
            "quats": random_quats(n, generator),
            "log_scales": torch.log(scale)[:, None].repeat(1, 2),
            "opacity_logit": torch.full((n,), math.log(init_opacity / (1 - init_opacity))),
            "colour_logit": inverse_sigmoid(col.float()),
            "p_logit": torch.full((n,), float(p_init_logit)),
        })

    def __len__(self) -> int:
        return int(self.t["means"].shape[0])

    def to(self, device) -> "Gaussians":
        return Gaussians({k: v.to(device) for k, v in self.t.items()})

    @property
    def means(self) -> torch.Tensor:
        return self.t["means"]

    @property
    def quats(self) -> torch.Tensor:
        return self.t["quats"]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.t["log_scales"])

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.t["opacity_logit"])

    @property
    def colours(self) -> torch.Tensor:
        return torch.sigmoid(self.t["colour_logit"])

    def state(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().cpu() for k, v in self.t.items()}

    def num_parameters(self) -> int:
        return sum(v.numel() for v in self.t.values())


class GaussianAdam:
    """torch Adam over the Gaussian tensors (one group each, named) whose rows can be appended or kept.

    Rows added by density control start with zero moments; pruned rows drop theirs, as in 3DGS.
    """

    def __init__(self, gaussians: Gaussians, lrs: dict[str, float]):
        self.g = gaussians
        groups = [{"params": [gaussians.t[k]], "lr": lrs[k], "name": k} for k in gaussians.t if k in lrs]
        self.names = [grp["name"] for grp in groups]
        self.opt = adam(groups, lr=0.0, eps=1e-15)

    def add_tensor(self, name: str, values: torch.Tensor, lr: float) -> None:
        """A new per-Gaussian tensor (one of OPTIONAL) with its own rate and fresh moments."""
        self.g.t[name] = values.detach().clone().requires_grad_(True)
        self.opt.add_param_group({"params": [self.g.t[name]], "lr": lr, "name": name})
        self.names.append(name)

    def set_lr(self, name: str, lr: float) -> None:
        for grp in self.opt.param_groups:
            if grp.get("name") == name:
                grp["lr"] = lr

    def zero_grad(self) -> None:
        self.opt.zero_grad(set_to_none=True)

    def step(self) -> None:
        self.opt.step()

    def _replace(self, name: str, new: torch.Tensor, state_fn) -> None:
        old = self.g.t[name]
        new = new.detach().requires_grad_(True)
        for grp in self.opt.param_groups:
            if grp.get("name") == name:
                st = self.opt.state.pop(old, None)
                grp["params"][0] = new
                if st is not None:
                    st["exp_avg"] = state_fn(st["exp_avg"])
                    st["exp_avg_sq"] = state_fn(st["exp_avg_sq"])
                    self.opt.state[new] = st
        self.g.t[name] = new

    def keep(self, mask: torch.Tensor) -> None:
        """Keep the rows where ``mask`` is true (in every tensor and its Adam moments)."""
        for name in list(self.g.t):
            self._replace(name, self.g.t[name][mask], lambda s: s[mask])

    def append(self, rows: dict[str, torch.Tensor]) -> None:
        """Append rows (a value for every tensor) with zero Adam moments."""
        for name in list(self.g.t):
            extra = rows[name].to(self.g.t[name])
            self._replace(name, torch.cat([self.g.t[name].detach(), extra]),
                          lambda s, e=extra: torch.cat([s, torch.zeros_like(e)]))

    def reset_values(self, name: str, values: torch.Tensor) -> None:
        """Overwrite a tensor's values (opacity reset) and clear its moments."""
        self._replace(name, values, lambda s: torch.zeros_like(s))

    def state_dict(self) -> dict:
        return self.opt.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.opt.load_state_dict(state)
