"""cupnet.denoise: the noise estimate against known noise, and non-local means against it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cupnet.denoise import denoised, noise_above, noise_sigma


def _scene(size: int = 256) -> np.ndarray:
    """A smooth shaded background with a dark disc (a cup's opening): ``(H, W)`` in [0, 1]."""
    v, u = np.mgrid[:size, :size] / size
    image = 0.4 + 0.3 * u + 0.1 * np.sin(3 * v)
    disc = np.hypot(u - 0.5, v - 0.5) < 0.25
    return np.where(disc, 0.2, image)


@pytest.mark.parametrize("sigma", [0.005, 0.01, 0.03])
def test_noise_sigma_finds_the_added_white_noise(sigma: float) -> None:
    noisy = _scene() + np.random.default_rng(0).normal(0, sigma, (256, 256))
    # Immerkaer's estimate on a smooth scene: the noise alone, but for the disc's edge.
    assert noise_sigma(noisy) == pytest.approx(sigma, rel=0.12)
    assert noise_sigma(torch.from_numpy(noisy).float()[None]) == pytest.approx(sigma, rel=0.12)


def test_clipped_pixels_do_not_count() -> None:
    noisy = _scene() + np.random.default_rng(1).normal(0, 0.02, (256, 256))
    framed = np.zeros((384, 384))  # a black surround, as outside an intensifier's field
    framed[64:320, 64:320] = noisy
    assert noise_sigma(framed) == pytest.approx(noise_sigma(noisy), rel=0.05)
    assert math.isnan(noise_sigma(np.ones((64, 64))))  # saturated: nothing to measure


def test_non_local_means_takes_the_noise_and_keeps_the_edge() -> None:
    clean = _scene()
    noisy = clean + np.random.default_rng(2).normal(0, 0.03, clean.shape)
    image = torch.from_numpy(noisy.clip(0, 1)).float()[None]
    out = denoised(image, noise_sigma(noisy))
    assert out.shape == image.shape and out.dtype == image.dtype
    residual = out[0].double().numpy() - clean
    assert residual.std() < 0.4 * 0.03
    # The disc's edge stays where it was: along the middle row, the 50 % crossings of the
    # step between the disc (0.2) and its surround lie within half a pixel of the clean
    # image's, where a Gaussian blur of the same noise reduction would round the step off.
    row = 128

    def crossings(values: np.ndarray) -> np.ndarray:
        level = (values[20] + 0.2) / 2
        below = values < level
        return np.flatnonzero(below[1:] != below[:-1])

    clean_edges = crossings(clean[row])
    smooth = out[0, row - 2:row + 3].double().numpy().mean(0)  # five rows against the rest
    assert len(crossings(smooth)) == len(clean_edges) == 2
    assert np.abs(crossings(smooth) - clean_edges).max() <= 1


def test_noise_above_decides_as_the_median_does() -> None:
    rng = np.random.default_rng(4)
    for sigma in (0.004, 0.008, 0.02):
        noisy = _scene(64) + rng.normal(0, sigma, (64, 64))
        estimate = noise_sigma(noisy)
        for bar in (0.5 * estimate, estimate * (1 - 1e-9), estimate, estimate * (1 + 1e-9),
                    2 * estimate):
            assert noise_above(noisy, bar) == (estimate if estimate > bar else None)
    # An odd count of pixels inside, and an image with none.
    odd = _scene(65) + rng.normal(0, 0.01, (65, 65))
    assert noise_above(odd, noise_sigma(odd) * 0.999) == noise_sigma(odd)
    assert noise_above(odd, noise_sigma(odd)) is None
    assert noise_above(np.zeros((32, 32)), 0.0) is None
