"""Which way an image shows metal: dark (the fluoroscopy display the networks learnt) or bright.

A cup's metal attenuates more than anything around it, so in the usual fluoroscopy display
(and in most of the training images: ``data_synth`` inverts 15 % of them) the cup is darker
than its surroundings; a radiograph-style display (metal white, as many DICOM exports and
screenshots show it) has it brighter. The networks find bright-metal cups, but place their
rims worse, so :meth:`cupnet.model.CupNet.detect` turns such images over after the locator
(``CupNetConfig.metal``: ``"auto"`` in the shipped model; docs/training.md, item 20).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from cupnet.ellipse import ellipse_points

# Where the two intensity samples lie: within each cup's opening (fractions of its ellipse;
# behind the opening lies the shell's back wall), and on circles around its centre beyond
# the shell's outline (fractions of the ellipse's semi-major axis, the outline's radius).
_INSIDE_SCALES = (0.2, 0.4, 0.6, 0.8)
_AROUND_SCALES = (1.2, 1.35, 1.5)
_SPOKES = 32
# How images may show metal (cupnet.config.CupNetConfig.metal).
METAL_DISPLAYS = ("dark", "bright", "auto")
# How much brighter (in the image's 5-95 % intensity range) the inside must be to count:
# near-ties are mostly a locator blob on something else, and keep the image as it is. On
# four 60-image sets of one display each (seeds 777 and 4242), the inside-minus-around
# difference ran from -2.0 to 0.5 with metal dark (2 of 114 images above 0.1) and from
# -0.3 to 1.8 with metal bright (about a dozen of 109 below 0.15, left as given).
_MARGIN = 0.15
# The margin for reporting the display once the cups are found (CupNet.with_image_displays):
# no image is turned over by it, so a near-tie goes by its sign. On 120 images of each
# display and one fresh seed of configs/synth_eval.yaml, 425 of 439 cups reported their
# display rightly against 412 with _MARGIN (docs/training.md, item 66).
REPORT_MARGIN = 0.0


def metal_shows_bright(image: Tensor, ellipses: Tensor, margin: float = _MARGIN
                       ) -> bool | None:
    """Whether ``image`` shows its cups brighter than their surroundings.

    Compares the median intensity within the cups' rough ellipses with the median on
    circles around them (pixels inside the image only): brighter by more than ``margin``
    of the image's 5-95 % intensity range.

    Args:
        image: ``(1, H, W)`` or ``(H, W)``.
        ellipses: ``(C, 5)`` (cx, cy, a, b, alpha_deg) image pixels; rows with NaN are no cup.
        margin: the default is the one :meth:`cupnet.model.CupNet.detect` turns images
            over by; :data:`REPORT_MARGIN` the one it reports the display by.
    Returns:
        True (metal bright), False (metal dark), or None where there is no cup to judge by.
    """
    bright, judged = metals_show_bright(image.reshape(1, *image.shape[-2:]), ellipses[None],
                                        margin)
    return bool(bright[0]) if bool(judged[0]) else None


def metals_show_bright(images: Tensor, ellipses: Tensor, margin: float = _MARGIN
                       ) -> tuple[Tensor, Tensor]:
    """:func:`metal_shows_bright` of a batch of images of one size, all at once on their
    device.

    Args:
        images: ``(B, 1, H, W)`` or ``(B, H, W)``.
        ellipses: ``(B, C, 5)`` (cx, cy, a, b, alpha_deg) image pixels; rows with NaN are
            no cup.
        margin: as :func:`metal_shows_bright`'s.
    Returns:
        ``(B,)`` bool each: whether the metal shows bright, and whether the image had a cup
        to judge by (where not, bright is False).
    """
    planes = images.reshape(len(images), *images.shape[-2:])
    height, width = planes.shape[-2:]
    if len(planes) == 0 or ellipses.shape[1] == 0:  # no image, or no cup in any
        unjudged = torch.zeros(len(planes), dtype=torch.bool, device=planes.device)
        return unjudged, unjudged
    ellipses = ellipses.to(planes.device, torch.float64)
    cup = torch.isfinite(ellipses).all(-1)  # (B, C)
    ellipses = torch.where(cup[..., None], ellipses, 0.0)
    t = torch.arange(_SPOKES, dtype=torch.float64, device=planes.device) * (2 * math.pi
                                                                           / _SPOKES)

    def median(rings: Tensor) -> Tensor:
        """Median intensity ``(B,)`` at ``rings`` ``(B, C, R, 5)`` ellipses' points inside
        the image (NaN where none is)."""
        points = ellipse_points(rings, t).round()  # (B, C, R, S, 2)
        inside = ((points >= 0).all(-1) & (points[..., 0] < width) & (points[..., 1] < height)
                  & cup[:, :, None, None])
        u = points[..., 0].clamp(0, width - 1).long()
        v = points[..., 1].clamp(0, height - 1).long()
        values = planes.flatten(1).gather(1, (v * width + u).flatten(1))
        return torch.where(inside.flatten(1), values, math.nan).nanmedian(1).values

    scales = torch.tensor(_INSIDE_SCALES, dtype=torch.float64, device=planes.device)[:, None]
    within = ellipses[:, :, None].repeat(1, 1, len(scales), 1)
    within[..., 2:4] *= scales
    circles = ellipses[:, :, None].repeat(1, 1, len(_AROUND_SCALES), 1)
    radii = ellipses[:, :, None, 2] * torch.tensor(_AROUND_SCALES, dtype=torch.float64,
                                                   device=planes.device)
    circles[..., 2], circles[..., 3] = radii, radii
    inner, outer = median(within), median(circles)
    judged = inner.isfinite() & outer.isfinite()
    low, high = torch.quantile(planes[:, ::4, ::4].flatten(1).double(),
                               torch.tensor([0.05, 0.95], dtype=torch.float64,
                                            device=planes.device), dim=1)
    return judged & (inner - outer > margin * (high - low)), judged
