"""Image formation: attenuation line integrals -> a display-ready fluoroscopy frame.

Beer-Lambert transmission, focal-spot blur and scatter (a low-passed copy of the primary
beam), image-intensifier vignetting, Poisson quantum noise at a dose set the way automatic
exposure control does (mean counts inside the field), electronic noise, veiling glare, log
display with a window from the field's percentiles, gamma and contrast, optional inversion,
the circular field with its dark surround, and 8- or 16-bit quantisation.
"""

from __future__ import annotations

import math
from functools import lru_cache

import kornia
import numpy as np
import torch
from torch import Tensor

from data_synth.config import SynthConfig
from data_synth.scene import uniform

_WINDOW_QUANTILES = torch.tensor([0.003, 0.997])
# Scatter is a broad halo: low-pass at 1/8 resolution, blurred by ~16 full-resolution pixels.
_SCATTER_POOL = 8
_SCATTER_SIGMA = 2.0


@lru_cache(maxsize=8)
def _radius_grid(height: int, width: int) -> Tensor:
    """``(H, W)`` distance (px) of each pixel centre from the image centre."""
    v = torch.arange(height, dtype=torch.float32) - (height - 1) / 2
    u = torch.arange(width, dtype=torch.float32) - (width - 1) / 2
    return torch.sqrt(v[:, None] ** 2 + u[None, :] ** 2)


def gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """Blur ``(B, C, H, W)`` with a Gaussian of ``sigma`` px (kernel +-3 sigma)."""
    size = 2 * max(1, math.ceil(3 * sigma)) + 1
    return kornia.filters.gaussian_blur2d(image, (size, size), (sigma, sigma),
                                          border_type="replicate")


def add_scatter(primary: Tensor, fraction: float) -> Tensor:
    """Replace ``fraction`` of ``(B, 1, H, W)`` ``primary`` by its broad low-pass (scatter)."""
    height, width = primary.shape[-2:]
    low = torch.nn.functional.avg_pool2d(primary, _SCATTER_POOL, ceil_mode=True)
    low = gaussian_blur(low, _SCATTER_SIGMA)
    low = torch.nn.functional.interpolate(low, size=(height, width), mode="bilinear",
                                          align_corners=False)
    return (1 - fraction) * primary + fraction * low


def form_image(line_integral: Tensor, field_radius: float, config: SynthConfig,
               rng: np.random.Generator, generator: torch.Generator) -> Tensor:
    """Fluoroscopy frame from attenuation line integrals.

    Args:
        line_integral: ``(H, W)`` total attenuation ``sum mu L`` (dimensionless) per pixel.
        field_radius: radius (px) of the circular image-intensifier field (inf: none).
        config: ranges of the formation parameters.
        rng: draws the parameters; generator: draws the noise.
    Returns:
        ``(1, H, W)`` float32 in ``[0, 1]``, quantised to 8 or 16 bits; attenuating material
        dark unless inverted.
    """
    height, width = line_integral.shape
    radius = _radius_grid(height, width)
    in_field = radius <= field_radius
    x = torch.exp(-line_integral)[None, None]
    sigma = uniform(rng, config.blur_sigma_px)
    if sigma > 0.05:
        x = gaussian_blur(x, sigma)
    scatter = uniform(rng, config.scatter_fraction)
    if scatter > 0:
        x = add_scatter(x, scatter)
    reach = field_radius if math.isfinite(field_radius) else float(radius.max())
    x = x * (1 - uniform(rng, config.vignetting) * (radius / reach).clamp(max=1) ** 2)
    # Automatic exposure control: the dose gives a mean of `photons` counts inside the field;
    # from here on x is in units of that mean.
    x = x / float(x[0, 0][in_field].mean() if in_field.any() else x.mean())
    photons = uniform(rng, config.photons)
    x = torch.poisson(x * photons, generator=generator) / photons
    electronic = uniform(rng, config.electronic_noise)
    if electronic > 0:
        x = x + electronic * torch.randn(x.shape, generator=generator)
    # Veiling glare of the intensifier: light spread over the output screen, a floor under
    # the darkest (metal) pixels.
    x = x + uniform(rng, config.veiling_glare)
    x = torch.log(x.clamp_min(0.5 / photons))[0, 0]
    # Window on a subsample of the field's pixels (a quantile of all of them costs a sort).
    sample = x[in_field][::5] if in_field.any() else x.reshape(-1)[::5]
    low, high = torch.quantile(sample, _WINDOW_QUANTILES)
    x = ((x - low) / (high - low).clamp_min(1e-6)).clamp(0, 1)
    contrast = uniform(rng, config.contrast)
    x = ((x - 0.5) * contrast + 0.5).clamp(0, 1) ** uniform(rng, config.gamma)
    if rng.random() < config.p_invert:
        x = 1 - x
    if math.isfinite(field_radius):
        # The intensifier's round field with a soft ~1 px edge over a dark surround.
        edge = torch.sigmoid((field_radius - radius) / 0.7)
        x = x * edge + rng.uniform(0.0, 0.08) * (1 - edge)
    levels = 255.0 if rng.random() < config.p_8bit else 65535.0
    return (torch.round(x * levels) / levels)[None].float()
