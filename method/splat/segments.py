"""Segmented scans over packed lists (pairs sorted by segment), the core of batched front-to-back compositing.

Prefix sums run in float64 over 1-D contiguous tensors: a global cumsum over ~1e6 float32 values loses
the per-segment differences, and cumsum along dim 0 of a (P, K) tensor is several times slower on CPU.
"""
from __future__ import annotations

import torch


class Segments:
    """Segment bookkeeping for a packed list whose segment ids ``seg`` are sorted (non-decreasing)."""

    def __init__(self, seg: torch.Tensor, num_segments: int):
        self.seg = seg
        self.num = int(num_segments)
        self.counts = torch.bincount(seg, minlength=self.num)
        self.starts = torch.cumsum(self.counts, 0) - self.counts
        self.start_of = self.starts.index_select(0, seg)  # first index of each element's segment

    def exclusive_cumsum(self, x: torch.Tensor) -> torch.Tensor:
        """Per-segment exclusive prefix sum of a 1-D tensor (float64 internally, returned in x's dtype)."""
        if x.shape[0] == 0:
            return x.clone()
        x64 = x.double()
        excl = torch.cumsum(x64, 0) - x64
        return (excl - excl.index_select(0, self.start_of)).to(x.dtype)

    def sum(self, x: torch.Tensor) -> torch.Tensor:
        """Per-segment sum along dim 0, shape (num_segments, *x.shape[1:])."""
        if x.shape[0] == 0:
            return x.new_zeros((self.num,) + tuple(x.shape[1:]))
        return torch.segment_reduce(x, "sum", lengths=self.counts, axis=0, unsafe=True)

    def gather(self, per_segment: torch.Tensor) -> torch.Tensor:
        """Broadcast per-segment values back to the elements."""
        return per_segment.index_select(0, self.seg)
