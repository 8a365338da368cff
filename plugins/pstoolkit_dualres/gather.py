"""Weighted sums of gathered rows, ``out[n] = Σ_f w[n, f]·source[index[n, f]]``, differentiable with
respect to ``source`` (``gather_sum``): the event-grid materials read at the frame pixels through
their bilinear taps, and the neighbour differences of the TV term (weights 1 and −1).

Torch's advanced indexing differentiates into ``index_put_`` with accumulation, which on the CPU
takes a few milliseconds per million rows on one thread and was a quarter of a training step; here
the forward gathers in parallel and the backward adds each row's gradient in one compiled loop, in
index order, so the result does not depend on the thread count either (a parallel scatter into a
buffer per share of the rows, summed after, was slower at 512²: zeroing and summing the buffers).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor


@numba.njit(cache=True, parallel=True, nogil=True)
def _gather(source: np.ndarray, index: np.ndarray, weight: np.ndarray, out: np.ndarray) -> None:
    n, f = index.shape
    c = source.shape[1]
    for i in prange(n):
        for ch in range(c):
            total = 0.0
            for j in range(f):
                total += weight[i, j] * source[index[i, j], ch]
            out[i, ch] = total


@numba.njit(cache=True, nogil=True)
def _scatter(grad: np.ndarray, index: np.ndarray, weight: np.ndarray, out: np.ndarray) -> None:
    n, f = index.shape
    c = grad.shape[1]
    for i in range(n):
        for j in range(f):
            w = weight[i, j]
            row = index[i, j]
            for ch in range(c):
                out[row, ch] += w * grad[i, ch]


class _GatherSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx, source: Tensor, index: Tensor, weight: Tensor) -> Tensor:
        rows = source.detach().contiguous().numpy()
        index_np, weight_np = index.contiguous().numpy(), weight.detach().to(source.dtype).contiguous().numpy()
        out = np.empty((index.shape[0], rows.shape[1]), dtype=rows.dtype)
        _gather(rows, index_np, weight_np, out)
        ctx.saved = (index_np, weight_np, rows.shape, source.dtype)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: Tensor):
        index_np, weight_np, shape, dtype = ctx.saved
        out = np.zeros(shape, dtype=weight_np.dtype)
        _scatter(grad.detach().to(dtype).contiguous().numpy(), index_np, weight_np, out)
        return torch.from_numpy(out), None, None


def gather_sum(source: Tensor, index: Tensor, weight: Tensor) -> Tensor:
    """(N, C) rows ``Σ_f weight[n, f]·source[index[n, f]]`` of ``source`` (G, C), with ``index`` (N, F)
    int64 in [0, G) and ``weight`` (N, F) (constants: no gradient reaches them).

    On CPU tensors through the compiled kernels above; on other devices, and where ``torch.compile``
    traces it (the kernels are opaque to it), through torch's indexing."""
    if source.device.type != "cpu" or torch.compiler.is_compiling():
        return gather_sum_torch(source, index, weight)
    return _GatherSum.apply(source, index, weight)


def gather_sum_torch(source: Tensor, index: Tensor, weight: Tensor) -> Tensor:
    """``gather_sum`` through torch's indexing, on any device."""
    return torch.sum(source[index] * weight[..., None].to(source.dtype), dim=1)
