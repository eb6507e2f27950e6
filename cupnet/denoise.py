"""Images noisier than the networks' training: their noise measured, and taken down first.

The training DRRs carry quantum and electronic noise at 300-20,000 photons a pixel, drawn
uniformly, so most are clean: :func:`noise_sigma` (display units, the image in [0, 1]) has a
median of 0.0029 over the four seed sets' 2,880 images, 99 % below 0.012. White noise of
0.01 more (2.5 grey levels of 255) raised the anteversion MAE from 0.70 to 1.13 deg and of
0.03 more the inclination's from 0.28 to 2.03 deg, mostly through gross failures
(docs/benchmarks.md, `CupNet on degraded images`; docs/training.md, item 55). Non-local
means (OpenCV's) at a strength set by the measured noise takes most of those failures away
(0.93 / 0.54 deg at 0.03 more), where a Gaussian blur moves the rim and with it ``h``; so
:meth:`cupnet.model.CupNet.detect` takes images noisier than ``CupNetConfig.denoise_above``
through it first (deciding by :func:`noise_above`: 3.4 ms a 512 px image, 9 ms at 1024 px).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

# Immerkaer's Laplacian-difference mask: it cancels any local plane, so on a smooth image
# its response is the noise alone, with standard deviation 6 sigma.
_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float64)
# Pixels that count: clipped ones (the black surround of an intensifier's field, saturated
# metal) carry no noise and would pull the estimate down.
_INSIDE = (0.05, 0.95)
# Non-local means' patch and search windows (px): on the degraded images (item 55) OpenCV's
# (7, 21) took 3 times as long for no better poses, (5, 7) half as long for worse ones.
_TEMPLATE, _SEARCH = 7, 11
_SCALE = 6 * 0.6745  # the mask's response is 6 sigma N(0, 1), whose |.| has median 0.6745


def _responses(image: Tensor | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The magnitudes of the mask's response, ``(H - 2, W - 2)``, each ``6 sigma |N(0, 1)|``
    where the image is smooth but for its noise, and the pixels that count (bool, the
    same shape)."""
    pixels = np.asarray(image.detach().cpu() if isinstance(image, Tensor) else image,
                        dtype=np.float64).reshape(image.shape[-2:])
    response = np.abs(cv2.filter2D(pixels, -1, _MASK)[1:-1, 1:-1])
    inner = pixels[1:-1, 1:-1]
    return response, (inner > _INSIDE[0]) & (inner < _INSIDE[1])


def _median_sigma(response: np.ndarray, inside: np.ndarray) -> float:
    """:func:`noise_sigma` from :func:`_responses`' output."""
    values = response[inside]
    if values.size < 9:
        return math.nan
    # The median of |N(0, s^2)| is 0.6745 s, and the mask's response has s = 6 sigma. The
    # median, not Immerkaer's mean: edges (a rim, bone, the field's border) are few pixels
    # of large response, which move a mean and hardly a median.
    return float(np.median(values) / _SCALE)


def noise_sigma(image: Tensor | np.ndarray) -> float:
    """An image's white-noise standard deviation, after Immerkaer (1996), robust to edges.

    Args:
        image: ``(H, W)`` or ``(1, H, W)`` in [0, 1].
    Returns:
        sigma in the image's units (display range [0, 1]); NaN where fewer than 9 pixels
        lie inside ``_INSIDE`` (a flat or saturated image).
    """
    return _median_sigma(*_responses(image))


def noise_above(image: Tensor | np.ndarray, sigma: float) -> float | None:
    """``noise_sigma(image)`` where it exceeds ``sigma``, else None (NaN counts as under).

    Whether it does is decided by counting, not by the median's selection (which takes 2-10
    ms of a 512-1024 px image, half the estimate's time or more), so a clean image costs one
    filter pass and no median; a noisy one the median too, on the same filter pass.

    Args:
        image: ``(H, W)`` or ``(1, H, W)`` in [0, 1]; sigma: display units.
    """
    response, inside = _responses(image)
    count = int(np.count_nonzero(inside))
    if count < 9:
        return None
    level = sigma * _SCALE
    higher = response > level
    above, half = int(np.count_nonzero(higher & inside)), count // 2
    if count % 2 or above != half:
        # The middle value (odd count) or both middle values (even) lie on one side.
        noisy = above > half
    else:
        # An even count whose two middle values straddle the level: their mean decides.
        middle = (response[inside & ~higher].max() + response[inside & higher].min()) / 2
        noisy = bool(middle / _SCALE > sigma)
    return _median_sigma(response, inside) if noisy else None


def denoised(image: Tensor, sigma: float) -> Tensor:
    """``image`` through non-local means of strength ``sigma`` (its :func:`noise_sigma`).

    Args:
        image: ``(1, H, W)`` float in [0, 1].
        sigma: the noise's standard deviation, display units.
    Returns:
        ``(1, H, W)`` of ``image``'s dtype and device, quantised to 8 bits (far below such
        an image's noise).
    """
    grey = np.round(image[0].detach().cpu().clamp(0, 1).numpy() * 255).astype(np.uint8)
    out = cv2.fastNlMeansDenoising(grey, None, h=255.0 * sigma, templateWindowSize=_TEMPLATE,
                                   searchWindowSize=_SEARCH)
    return torch.from_numpy(out.astype(np.float32) / 255).to(image)[None]
