"""cupnet.batchwise: each item rounded as alone, against torch's own products and functions."""

from __future__ import annotations

import pytest
import torch

from cupnet import batchwise


@pytest.fixture
def matrices(generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A batch of 9 items: ``(9, 4, 3)``, ``(9, 3, 5)`` and weights ``(9, 4)``, float64."""
    return (torch.randn(9, 4, 3, generator=generator, dtype=torch.float64),
            torch.randn(9, 3, 5, generator=generator, dtype=torch.float64),
            torch.rand(9, 4, generator=generator, dtype=torch.float64))


def test_products_match_torch_and_round_items_as_alone(matrices: tuple) -> None:
    first, second, weights = matrices
    torch.testing.assert_close(batchwise.matmul(first, second), first @ second)
    torch.testing.assert_close(batchwise.weighted_scatter(weights, first, first),
                               torch.einsum("bn,bni,bnj->bij", weights, first, first))
    square = second[:, :, :3]
    torch.testing.assert_close(batchwise.quadratic_form(first, square),
                               torch.einsum("bni,bij,bnj->bn", first, square, first))
    # Broadcast batch dimensions, as a (N, 2) set against (B, 2, 2) frames.
    torch.testing.assert_close(batchwise.matmul(first[0], second), first[0] @ second)
    for size in range(1, 9):
        for function, args in ((batchwise.matmul, (first, second)),
                               (batchwise.weighted_scatter, (weights, first, first)),
                               (batchwise.quadratic_form, (first, square))):
            batch = function(*(arg[:size] for arg in args))
            alone = function(*(arg[size - 1:size] for arg in args))
            assert torch.equal(batch[size - 1:size], alone), function.__name__


def test_products_have_torch_gradients(matrices: tuple) -> None:
    first, second, _ = (m[:2].clone().requires_grad_() for m in matrices)
    assert torch.autograd.gradcheck(batchwise.matmul, (first, second))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_elementwise_functions_round_each_element_as_alone(generator: torch.Generator,
                                                          dtype: torch.dtype) -> None:
    """Every element of a tensor whose length is no whole number of vectors (so that torch
    takes a scalar path for its last ones) comes out as computed alone, and as torch's
    function gives it to the last bit or two."""
    x = (torch.rand(1000, generator=generator, dtype=torch.float64) * 4 - 2).to(dtype)
    y = (torch.rand(1000, generator=generator, dtype=torch.float64) * 4 - 2).to(dtype)
    functions = {
        "atan2": (batchwise.atan2, torch.atan2, (y, x)),
        "hypot": (batchwise.hypot, torch.hypot, (x, y)),
    }
    for name, (ours, theirs, args) in functions.items():
        whole = ours(*args)
        torch.testing.assert_close(whole, theirs(*args), rtol=4 * torch.finfo(dtype).eps,
                                   atol=0, msg=name)
        for i in [*range(0, 1000, 37), *range(990, 1000)]:
            assert torch.equal(whole[i:i + 1], ours(*(arg[i:i + 1] for arg in args))), (name, i)
        # Shapes broadcast and come back as given.
        assert ours(*(arg.reshape(40, 25) for arg in args)).shape == (40, 25)
