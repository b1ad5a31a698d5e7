"""Segmented scans over packed lists (pairs sorted by segment), the core of batched front-to-back compositing.

Sums run in float64: a global cumsum over ~1e6 float32 values loses the per-segment differences.
"""
from __future__ import annotations

import torch


class Segments:
    """Segment bookkeeping for a packed list whose segment ids ``seg`` are sorted (non-decreasing)."""

    def __init__(self, seg: torch.Tensor, num_segments: int):
        self.seg = seg
        self.num = int(num_segments)
        counts = torch.bincount(seg, minlength=self.num)
        ends = torch.cumsum(counts, 0)
        self.counts = counts
        self.starts = ends - counts
        self.start_of = self.starts[seg]  # first index of each element's segment

    def exclusive_cumsum(self, x: torch.Tensor) -> torch.Tensor:
        """Per-segment exclusive prefix sum along dim 0 (float64 internally, returned in x's dtype)."""
        if x.shape[0] == 0:
            return x.clone()
        x64 = x.double()
        excl = torch.cumsum(x64, 0) - x64
        return (excl - excl[self.start_of]).to(x.dtype)

    def sum(self, x: torch.Tensor) -> torch.Tensor:
        """Per-segment sum, shape (num_segments, *x.shape[1:])."""
        out = x.new_zeros((self.num,) + tuple(x.shape[1:]))
        return out.index_add(0, self.seg, x)
