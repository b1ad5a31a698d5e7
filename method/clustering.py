"""k-means, shared by the two places that cluster points: the motion bases (trajectories, k-means++ seeding)
and the env fit's regions (positions, centres drawn at random). One Lloyd loop for both, so a fix to it
reaches both."""
from __future__ import annotations

import torch


@torch.no_grad()
def lloyd(x: torch.Tensor, centres: torch.Tensor, updates: int) -> torch.Tensor:
    """(N,) labels of the rows of ``x`` after at most ``updates`` Lloyd steps from ``centres`` (k, D; updated
    in place): each step moves every centre to its members' mean (an empty cluster keeps its centre) and
    re-assigns. Stops early when an assignment repeats, which is a fixed point: further steps change nothing."""
    labels = torch.cdist(x, centres).argmin(1)
    for _ in range(updates):
        for j in range(centres.shape[0]):
            member = labels == j
            if bool(member.any()):
                centres[j] = x[member].mean(0)
        new = torch.cdist(x, centres).argmin(1)
        if torch.equal(new, labels):
            break
        labels = new
    return labels


@torch.no_grad()
def kmeans(x: torch.Tensor, k: int, generator: torch.Generator, iterations: int = 30) -> torch.Tensor:
    """Cluster labels (N,) of the rows of ``x`` by k-means with k-means++ seeding (seeded): ``iterations``
    assignments at most."""
    n = x.shape[0]
    k = min(k, n)
    first = int(torch.randint(n, (1,), generator=generator))
    centres = [x[first]]
    d2 = ((x - centres[0]) ** 2).sum(-1)
    for _ in range(1, k):
        p = d2 / d2.sum().clamp_min(1e-30)
        i = int(torch.multinomial(p.cpu(), 1, generator=generator))
        centres.append(x[i])
        d2 = torch.minimum(d2, ((x - x[i]) ** 2).sum(-1))
    return lloyd(x, torch.stack(centres), iterations - 1)
