"""Rigid motion bases: the moving Gaussians carried by a few shared rigid trajectories after the warm-up.

Why: the deformation network gives every Gaussian its own offset from its canonical place, so nothing ties
a moving object's shape across times; at `small` the balls, the swinging crate and the mouse come out blurred
on the training views themselves (BENCHMARKS.md, "Part 3, the moving objects"). Here each of B bases is one
rigid motion over time (a rotation about a pivot and a translation per knot in time, linear in between),
and a Gaussian's position and rotation at time t are its canonical ones moved by the blend of the bases'
transforms (linear blend skinning): x_t = (sum_k w_k R_k(t)) mu + sum_k w_k b_k(t), q_t = (sum_k w_k q_k(t)) q.
Basis 0 is the identity (static Gaussians keep it). The weights are a softmax of per-Gaussian logits
(``basis_logit`` among the Gaussian tensors, so density control copies them). With ``network`` the blend
has one more option, the deformation network's own offset, for what no rigid basis fits (an articulated
figure's limbs): bases alone lost 2.6 dB on jumpingjacks where the network option gained (BENCHMARKS.md,
"rigid motion bases").

Initialised from what the network learned in the warm-up: the moving Gaussians' trajectories at the
knots clustered by k-means, and each cluster's rigid motion per knot fitted to its members by
Kabsch's method; each Gaussian's logits from how well each basis explains its trajectory, the network's option scored
as a misfit of the Gaussian's own size (Shape of Motion, Wang et al. 2024, uses SE(3) motion bases with
per-Gaussian coefficients the same way). The bases are sampled at a few knots in time, not at every
training time: with one camera per time, a knot per time is fitted by one view.
"""
from __future__ import annotations

import torch
from torch import nn

from method.clustering import kmeans
from method.model.nodes import row_softmax


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of w-x-y-z quaternions (broadcasting)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) w-x-y-z (normalised here) -> (..., 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 4) unit w-x-y-z quaternions with w >= 0 (Shepperd's method, via the
    largest of the four squared components)."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    cands = torch.stack([
        torch.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
        torch.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1)], -2)  # (..., 4, 4)
    diag = torch.stack([cands[..., 0, 0], cands[..., 1, 1], cands[..., 2, 2], cands[..., 3, 3]], -1)
    best = diag.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(q[..., :1] < 0, -q, q)


def kabsch(src: torch.Tensor, dst: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The rotation R and translation T with R (src - c) + c + T closest to dst in least squares, c the
    centroid of src: (R (3, 3), T (3,))."""
    c, cd = src.mean(0), dst.mean(0)
    h = (src - c).T @ (dst - cd)
    u, _, vt = torch.linalg.svd(h)
    corr = torch.ones(3, dtype=h.dtype, device=h.device)
    if float(torch.linalg.det(vt.T @ u.T)) < 0:
        corr[2] = -1.0  # the best proper rotation, not a reflection
    r = vt.T @ torch.diag(corr) @ u.T
    return r, cd - c


class MotionBasis(nn.Module):
    """B rigid trajectories sampled at the knots ``times`` (sorted), linear in between and held constant
    outside them; plus the identity as basis 0 and, with ``network``, the network's offset as the last
    option."""

    def __init__(self, times: list[float], bases: int, network: bool = False):
        super().__init__()
        j = len(times)
        self.network = bool(network)  # a last weight column: the network's own offset (non-rigid parts)
        self.register_buffer("times", torch.tensor(sorted(times), dtype=torch.float32))
        self.register_buffer("pivot", torch.zeros(bases, 3))
        self.quat = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(bases, j, 1))
        self.trans = nn.Parameter(torch.zeros(bases, j, 3))

    def state(self) -> dict:
        return {**{k: v.detach().cpu() for k, v in self.state_dict().items()}, "network": self.network}

    @staticmethod
    def from_state(state: dict) -> "MotionBasis":
        state = dict(state)
        network = bool(state.pop("network", False))
        basis = MotionBasis(state["times"].tolist(), int(state["quat"].shape[0]), network)
        basis.load_state_dict(state)
        return basis

    @property
    def bases(self) -> int:
        return self.quat.shape[0]

    def at(self, t: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each basis's (linear part (B + 1, 3, 3), offset (B + 1, 3), quaternion (B + 1, 4)) at time t, the
        identity first: x -> A x + b."""
        ts = self.times
        if ts.numel() > 1:
            i = int(torch.searchsorted(ts, torch.tensor(float(t), dtype=ts.dtype, device=ts.device)).clamp(1, ts.numel() - 1))
            f = float(min(max((float(t) - float(ts[i - 1])) / max(float(ts[i] - ts[i - 1]), 1e-12), 0.0), 1.0))
            q = (1 - f) * self.quat[:, i - 1] + f * self.quat[:, i]
            tr = (1 - f) * self.trans[:, i - 1] + f * self.trans[:, i]
        else:
            q, tr = self.quat[:, 0], self.trans[:, 0]
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        r = quat_to_matrix(q)
        b = self.pivot + tr - (r @ self.pivot[:, :, None])[..., 0]
        eye = torch.eye(3, dtype=r.dtype, device=r.device)[None]
        ident_q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=q.dtype, device=q.device)
        return torch.cat([eye, r]), torch.cat([b.new_zeros(1, 3), b]), torch.cat([ident_q, q])

    def offsets(self, means: torch.Tensor, quats: torch.Tensor, logits: torch.Tensor, t: float,
                field: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(d mu, d r) of every Gaussian at time t, in the additive form the scene applies with P:
        mu' = mu + P d mu, r' = r + P d r. ``field``: the network's (d mu, d r), the last option of the blend
        when the bases were built with ``network``."""
        a, b, q = self.at(t)
        from method.splat.backend import resolve

        if resolve(None, means.device) == "numba":  # the compiled blend (method/model/basis_numba.py)
            from method.model.basis_numba import basis_offsets

            return basis_offsets(means, quats, logits, a, b, q, field if self.network else None)
        return self.offsets_reference(means, quats, logits, (a, b, q), field)

    def offsets_reference(self, means: torch.Tensor, quats: torch.Tensor, logits: torch.Tensor,
                          bases: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                          field: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``offsets`` in torch ops, from the bases' ``at(t)``: the reference the compiled blend is held to,
        and the CUDA path."""
        a, b, q = bases
        w = row_softmax(logits)                             # (N, B + 1 [+ 1])
        wr = w[:, :a.shape[0]]
        m = (wr @ a.reshape(-1, 9)).reshape(-1, 3, 3)
        x = (m @ means[:, :, None])[..., 0] + wr @ b
        qb = wr @ q
        qb = qb / qb.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        s = wr.sum(-1, keepdim=True)
        d_mu, d_rot = x - s * means, s * (quat_mul(qb, quats) - quats)
        if self.network:
            wn = w[:, -1:]
            d_mu, d_rot = d_mu + wn * field[0], d_rot + wn * field[1]
        return d_mu, d_rot

    @torch.no_grad()
    def fit(self, means: torch.Tensor, traj: torch.Tensor, moving: torch.Tensor, generator: torch.Generator,
            sharpness: float = 2.0, network_err: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
        """Initialise the bases from trajectories and return each Gaussian's logits (N, B + 1; B + 2 with
        ``network``).

        ``means`` (N, 3): the canonical means the bases will move; ``traj`` (N, J, 3): each Gaussian's
        position at the J knots (what the network drew in the warm-up); ``moving`` (N,): the
        Gaussians the P split marked dynamic, whose trajectories are clustered. A Gaussian's logit for basis
        k is -sharpness x its mean squared distance from basis k's prediction over the times, divided by the
        median over the moving Gaussians of their best basis's; with ``network``, ``network_err`` (N,) is the
        network option's misfit in the same units."""
        n, j, _ = traj.shape
        idx = torch.nonzero(moving).squeeze(1)
        info = {"moving": int(idx.numel())}
        if idx.numel() >= self.bases:
            labels = kmeans(traj[idx].reshape(idx.numel(), -1), self.bases, generator)
            for k in range(self.bases):
                mem = idx[labels == k]
                if mem.numel() < 3:
                    continue
                src = means[mem]
                self.pivot[k] = src.mean(0)
                prev = None
                for jj in range(j):
                    r, tr = kabsch(src.double(), traj[mem, jj].double())
                    q = matrix_to_quat(r).to(self.quat)
                    if prev is not None and float((q * prev).sum()) < 0:
                        q = -q  # the hemisphere of the previous time: the interpolation stays short
                    self.quat[k, jj] = q
                    self.trans[k, jj] = tr.to(self.trans)
                    prev = q
            info["cluster_sizes"] = torch.bincount(labels, minlength=self.bases).tolist()
        err = means.new_zeros(n, self.bases + 1)
        for jj in range(j):
            a, b, _ = self.at(float(self.times[jj]))
            pred = torch.einsum("kab,nb->nka", a, means) + b[None]      # (N, B + 1, 3)
            err += ((pred - traj[:, jj, None]) ** 2).sum(-1)
        err = err / j
        best = err[idx, 1:].min(1).values if idx.numel() else err[:, 0]
        if self.network:  # the network's option: what a rigid basis must beat (its own fit is exact)
            if network_err is None:
                raise ValueError("MotionBasis.fit: bases with the network option need network_err")
            err = torch.cat([err, network_err.to(err)[:, None]], 1)
            info["network_share"] = float((err[idx].argmin(1) == err.shape[1] - 1).float().mean()) if idx.numel() else 0.0
        scale = float(best.median().clamp_min(1e-12)) if best.numel() else 1.0
        logits = -sharpness * (err - err.min(1, keepdim=True).values) / scale
        info["median_residual"] = scale ** 0.5
        return logits.clamp_min(-30.0), info
