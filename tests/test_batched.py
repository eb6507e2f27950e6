"""``cupnet.batched.batched_cups`` against ``CupNet.detect`` following the same landmark sources."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from benchmarks.model import samples
from benchmarks.throughput import stacked
from cupnet.batched import batched_cups
from cupnet.config import apply_speed_preset
from cupnet.fold import fold_batchnorm
from cupnet.geometry import Geometry
from cupnet.model import load_model


@pytest.fixture(scope="module")
def drrs() -> list[dict]:
    """Twelve 512 px DRRs with the CT background, as the throughput benchmark's."""
    return samples("configs/synth_speed.yaml", 31_337, 12)


@pytest.mark.parametrize("thin_rims", [False, True])
def test_batched_cups_are_detects_with_the_same_sources(drrs: list[dict], thin_rims: bool
                                                        ) -> None:
    """``detect`` with the ``fastest`` preset and no grown-rim source (with the shipped
    thin-rim hypotheses or without) tries the same sources in the same order, one cup at
    a time: the same cups, poses and ellipses (a failed cup's the refiner's)."""
    model = fold_batchnorm(load_model())
    shipped = model.config
    model.config = apply_speed_preset(copy.copy(shipped), "fastest")
    model.config.grown_rim_scale = None
    if thin_rims:
        model.config.thin_rim_gate = shipped.thin_rim_gate
    images, geometry, diameter = stacked(drrs, torch.device("cpu"))
    found = batched_cups(model, images, geometry, diameter)
    detected = model.detect(images, geometry, diameter, return_masks=False)
    owner = found.cup_index[:, 0].numpy()
    assert len(owner) >= 10  # most DRRs hold a cup the locator finds
    for image, cups in enumerate(detected):
        rows = np.flatnonzero(owner == image)
        assert len(rows) == len(cups)
        for row, cup in zip(rows, cups, strict=True):
            np.testing.assert_allclose(found.pose[row].numpy(), cup.pose, atol=1e-6)
            np.testing.assert_allclose(found.ellipse[row].numpy(), cup.ellipse, atol=1e-6)
            assert bool(found.valid[row]) == np.isfinite(cup.pose).all()
    assert found.valid.float().mean() >= 0.9


def test_batched_cups_of_an_image_without_a_cup_and_of_bad_input() -> None:
    model = fold_batchnorm(load_model())
    blank = torch.full((1, 1, 256, 256), 0.5)
    geometry = Geometry.from_rows(torch.tensor([[1000.0, 0.3, 128.0, 128.0]]))
    found = batched_cups(model, blank, geometry, torch.tensor([50.0]))
    assert found.cup_index.shape == (0, 2) and found.pose.shape == (0, 5)
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        batched_cups(model, blank[0], geometry, torch.tensor([50.0]))


def test_batched_cups_turn_images_the_config_says_show_the_metal_bright(
        drrs: list[dict]) -> None:
    """``metal: bright`` on the images turned over gives what ``metal: dark`` gives on them
    as they are (the networks see the same pixels, but for 1 - (1 - x)'s float rounding)."""
    model = fold_batchnorm(load_model())
    images, geometry, diameter = stacked(drrs[:4], torch.device("cpu"))
    model.config = copy.copy(model.config)
    model.config.metal = "dark"
    expected = batched_cups(model, images, geometry, diameter)
    model.config.metal = "bright"
    found = batched_cups(model, 1 - images, geometry, diameter)
    assert torch.equal(found.cup_index, expected.cup_index) and len(found.cup_index) >= 3
    torch.testing.assert_close(found.pose, expected.pose, atol=1e-3, rtol=0, equal_nan=True)
