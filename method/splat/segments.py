"""Segmented scans over packed lists (pairs sorted by segment), the core of batched front-to-back compositing.

Prefix sums run in float64 over 1-D contiguous tensors: a global cumsum over ~1e6 float32 values loses
the per-segment differences, and cumsum along dim 0 of a (P, K) tensor is several times slower on CPU.
"""
from __future__ import annotations

import torch

# Per-segment sums on CUDA through prefix sums (see Segments.sum); a switch for A/B benchmarks.
CUDA_PREFIX_SUMS = True


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
        """Per-segment sum along dim 0, shape (num_segments, *x.shape[1:]).

        On CUDA, 1-D float32 sums are differences of one float64 inclusive prefix sum at the segment ends
        (deterministic, no atomics): aten's segment_reduce took ~0.6 ms per call at 7.6M pairs on an
        H100 (profiled), 13 calls per raster step; with the CUDA span grouping this gave x0.76 at 800 px
        (measured together, BENCHMARKS.md). 2-D inputs (the tracer's features, often transposed
        views) stay on segment_reduce: a prefix sum along dim 0 of such a view was 3x slower there.
        Elsewhere segment_reduce, which is exact in any dtype.
        """
        if x.shape[0] == 0:
            return x.new_zeros((self.num,) + tuple(x.shape[1:]))
        if x.is_cuda and x.dim() == 1 and x.dtype != torch.float64 and CUDA_PREFIX_SUMS:
            return self.sum_by_prefix(x)
        return torch.segment_reduce(x, "sum", lengths=self.counts, axis=0, unsafe=True)

    def sum_by_prefix(self, x: torch.Tensor) -> torch.Tensor:
        """Per-segment sum as the difference of a float64 inclusive prefix sum at segment ends and starts."""
        c = torch.cumsum(x.double(), 0)
        c = torch.cat([c.new_zeros((1,) + tuple(c.shape[1:])), c], 0)
        ends = self.starts + self.counts
        return (c.index_select(0, ends) - c.index_select(0, self.starts)).to(x.dtype)

    def gather(self, per_segment: torch.Tensor) -> torch.Tensor:
        """Broadcast per-segment values back to the elements."""
        return per_segment.index_select(0, self.seg)


class _GatherCols(torch.autograd.Function):
    """Columns ``idx`` of a (K, N) tensor -> (K, len(idx)). Forward as K 1-D index_selects (3x faster
    on CPU than one torch.gather), backward as one (K, N) scatter-add."""

    @staticmethod
    def forward(ctx, mat, idx):
        ctx.save_for_backward(idx)
        ctx.n = mat.shape[1]
        return torch.stack([row.index_select(0, idx) for row in mat.unbind(0)], 0)

    @staticmethod
    def backward(ctx, grad):
        (idx,) = ctx.saved_tensors
        out = grad.new_zeros((grad.shape[0], ctx.n))
        return out.scatter_add_(1, idx[None, :].expand_as(grad), grad), None


def gather_cols(mat: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Columns ``idx`` of a (K, N) matrix: per-pair attributes gathered from per-splat rows (_GatherCols)."""
    mat = mat.contiguous()
    if torch.is_grad_enabled() and mat.requires_grad:
        return _GatherCols.apply(mat, idx)
    return torch.stack([row.index_select(0, idx) for row in mat.unbind(0)], 0)
