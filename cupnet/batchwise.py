"""Batched operations that round each item as it would alone, whatever shares its batch.

:meth:`cupnet.model.CupNet.detect` solves a batch's cups together, and its dome-outline
passes can amplify a last-digit difference into another pose: one image's pose had depended
on which other images shared its batch (docs/training.md, item 58). Two kinds of CPU kernel
round an item by the batch around it:

- ``torch.matmul``, ``bmm`` and ``einsum`` choose their kernels by the batch's size (one
  matrix product for a single item, a batched one for several). The products here multiply
  elementwise and sum along the last dimension instead.
- Some elementwise functions (``atan2``, ``hypot``, ``sigmoid``, a power of a fractional
  exponent) take their vectorised path for most elements and a scalar one, rounding
  differently, for the last few of a tensor, so for whichever item lies last. ``atan2``
  and ``hypot`` here pad the flattened tensor to a whole number of vectors first (the
  model's ``sigmoid`` and powers are of whole maps, whole vectors already).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

# A multiple of every kernel's unrolled vector length (two 512-bit vectors of float32: 32).
_LANES = 64


def matmul(first: Tensor, second: Tensor) -> Tensor:
    """``first @ second`` for ``(..., I, K)`` and ``(..., K, J)`` (batch dimensions
    broadcast) -> ``(..., I, J)``, each item rounded as alone."""
    return (first.unsqueeze(-2) * second.transpose(-1, -2).unsqueeze(-3)).sum(-1)


def weighted_scatter(weights: Tensor, first: Tensor, second: Tensor) -> Tensor:
    """``sum_n w_n x_n y_n^T``: ``(B, N)`` weights, ``(B, N, I)`` and ``(B, N, J)`` ->
    ``(B, I, J)`` (``einsum("bn,bni,bnj->bij")``), each item rounded as alone."""
    return matmul((weights[..., None] * first).transpose(-1, -2), second)


def quadratic_form(vectors: Tensor, matrices: Tensor) -> Tensor:
    """``x^T M x`` of ``(B, N, I)`` vectors under ``(B, I, I)`` matrices -> ``(B, N)``
    (``einsum("bni,bij,bnj->bn")``), each item rounded as alone."""
    return (matmul(vectors, matrices.transpose(-1, -2)) * vectors).sum(-1)


def _whole_vectors(function: Callable[..., Tensor], *tensors: Tensor) -> Tensor:
    """``function`` of the broadcast ``tensors``, flattened and padded to whole vectors (with
    0.5, inside every function's domain here), so that no element takes the scalar tail."""
    if any(tensor.shape != tensors[0].shape for tensor in tensors[1:]):
        tensors = tuple(torch.broadcast_tensors(*tensors))  # torch.broadcast_shapes is Python
    shape, count = tensors[0].shape, tensors[0].numel()
    if count % _LANES == 0 and all(tensor.is_contiguous() for tensor in tensors):
        return function(*tensors)  # whole vectors already
    flat = [F.pad(tensor.reshape(-1), (0, -count % _LANES), value=0.5) for tensor in tensors]
    return function(*flat)[:count].reshape(shape)


def atan2(y: Tensor, x: Tensor) -> Tensor:
    """``torch.atan2(y, x)`` (rad), each item rounded as alone."""
    return _whole_vectors(torch.atan2, y, x)


def hypot(x: Tensor, y: Tensor) -> Tensor:
    """``torch.hypot(x, y)``, each item rounded as alone."""
    return _whole_vectors(torch.hypot, x, y)

