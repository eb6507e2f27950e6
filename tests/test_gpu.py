"""CupNet on a CUDA device against the same model on the CPU (skipped without CUDA).

A lent GPU machine runs these (``benchmarks/gpu_check.sh``); CI has none. TF32 is turned
off so that the two devices differ only by their kernels' summation order (about 1e-6 of
the networks' outputs), which the poses must not notice.
``CUPNET_TEST_DEVICE=cpu`` runs them on the CPU against itself, to test the tests.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np
import pytest
import torch

from benchmarks.model import samples
from benchmarks.throughput import stacked
from cupnet.batched import batched_cups
from cupnet.fold import fold_batchnorm
from cupnet.model import load_model
from cupnet.offload import networks_on

DEVICE = torch.device(os.environ.get("CUPNET_TEST_DEVICE", "cuda"))
pytestmark = pytest.mark.skipif(DEVICE.type == "cuda" and not torch.cuda.is_available(),
                                reason="no CUDA device")
# Per pose parameter (theta, phi deg; k, l, h mm): h is the most sensitive to a landmark.
POSE_TOLERANCE = np.array([0.02, 0.02, 0.01, 0.01, 0.2])


@pytest.fixture(autouse=True)
def no_tf32() -> Iterator[None]:
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


@pytest.fixture(scope="module")
def drrs() -> list[dict]:
    """Eight 512 px DRRs with the CT background, as the throughput benchmark's."""
    return samples("configs/synth_speed.yaml", 4242, 8)


def test_detect_with_networks_on_the_device_matches_the_cpu(drrs: list[dict]) -> None:
    model = fold_batchnorm(load_model())
    images, geometry, diameter = stacked(drrs, torch.device("cpu"))
    on_cpu = model.detect(images, geometry, diameter, return_masks=False)
    on_device = networks_on(model, DEVICE).detect(images, geometry, diameter,
                                                  return_masks=False)
    assert sum(map(len, on_cpu)) >= len(drrs)  # every DRR holds a cup: none lost on either
    for ours, theirs in zip(on_device, on_cpu, strict=True):
        assert [c.status for c in ours] == [c.status for c in theirs]
        for a, b in zip(ours, theirs, strict=True):
            np.testing.assert_array_less(np.abs(a.pose - b.pose), POSE_TOLERANCE)


def test_batched_forward_on_the_device_matches_the_cpu_and_backpropagates(
        drrs: list[dict]) -> None:
    """``CupNet.forward`` (the training path) with the model and images on the device: the
    same poses as on the CPU, and the pose's gradient reaches the rim network's first layer
    (the shipped model's landmarks are the rim network's)."""
    model = load_model().eval()
    images, geometry, diameter = stacked(drrs[:4], torch.device("cpu"))
    with torch.no_grad():
        expected = model(images, geometry, diameter).solution.pose
    model = model.to(DEVICE)
    images, geometry, diameter = stacked(drrs[:4], DEVICE)
    out = model(images, geometry, diameter)
    assert out.solution.pose.device.type == DEVICE.type
    assert out.solution.pose.shape == expected.shape
    np.testing.assert_array_less((out.solution.pose.detach().cpu() - expected).abs().numpy(),
                                 np.broadcast_to(POSE_TOLERANCE, expected.shape))
    out.solution.pose.nan_to_num().sum().backward()
    first = next(model.rim.parameters()).grad
    assert first is not None and torch.isfinite(first).all() and first.abs().sum() > 0


@pytest.mark.parametrize("outline", [False, True])
def test_batched_cups_on_the_device_match_the_cpu(drrs: list[dict], outline: bool) -> None:
    """:func:`cupnet.batched.batched_cups` (with its outline stage or without) with the model
    and images on the device: the CPU's cups, with their poses."""
    model = fold_batchnorm(load_model())
    images, geometry, diameter = stacked(drrs, torch.device("cpu"))
    expected = batched_cups(model, images, geometry, diameter, outline=outline)
    found = batched_cups(model.to(DEVICE), *stacked(drrs, DEVICE), outline=outline)
    assert found.pose.device.type == DEVICE.type
    assert torch.equal(found.cup_index.cpu(), expected.cup_index)
    assert torch.equal(found.valid.cpu(), expected.valid)
    assert int(expected.valid.sum()) >= len(drrs) - 1
    ok = expected.valid.numpy()
    np.testing.assert_array_less(np.abs(found.pose.cpu().numpy() - expected.pose.numpy())[ok],
                                 np.broadcast_to(POSE_TOLERANCE, (int(ok.sum()), 5)))
