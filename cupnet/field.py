"""The image intensifier's round field: the part of a frame that was exposed at all.

An image intensifier's output is a disc, and frames grabbed from it (4:3 or 16:9 video,
secondary-capture DICOMs) hold that disc in a flat, featureless surround. No cup lies
outside the disc, yet the locator, trained on square images, takes the surround's dark
corners at the long ends of an oblong frame for cups (docs/training.md, item 23).
:func:`round_field` finds the disc from the surround's inner edge;
:func:`outside_field` tells which ellipses' centres lie beyond it.

The surround is told from the image by being flat (no noise, no anatomy) and holding an
image corner. The circle fitted to its edge must be wide, centred and hold the whole
exposed region, so a saturated stem or bright air reaching the border (flat too) neither
makes a field nor, being few of the edge's points, bends one; text burnt into the
surround is no part of its edge.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

from cupnet.batchwise import hypot

# Flat: the intensity range over a 5x5 window at most this (of the image's [0, 1]): exact
# plateaus of 8- and 16-bit images, where the field's quantum noise spans several levels.
FLAT_RANGE = 1e-3
# How near the circle an edge point or the exposed region's pixel counts as on it.
INLIER_PX = 2.0
# The circle at least this wide (its radius over the image's shorter side) ...
MIN_RADIUS = 0.25
# ... centred within this (of the shorter side) of the image's centre, as an
# intensifier's disc is framed (a short arc's fit, as of one corner, falls far off) ...
MAX_OFFSET = 0.15
# ... and holding the exposed region but this share of it (a short arc's circle can pass
# the checks above and still cut the field, and cups in it would be dropped).
MAX_EXPOSED_OUTSIDE = 0.01
# A field narrower than this (its diameter over the image's shorter side) is cut out before
# the networks look: the synthetic training frames' fields span 0.92-1.24 of the side
# (field_radius_frac 0.46-0.62), a screenshot's or secondary capture's within wide margins
# may span half, and there every cup looks small to the locator (docs/training.md, item 41).
CROP_BELOW = 0.9
# Trimming rounds at most (a stem's edge is gone after two or three), and edge points used
# (every k-th: a 4096 px frame's edge holds tens of thousands).
_TRIM_ROUNDS = 6
_MAX_POINTS = 4000
# Images up to twice this shorter side are looked at whole (px).
_FULL_SIDE = 1024
# The image's corner pixels' 5x5 windows, clipped to the image.
_CORNERS = [(rows, cols) for rows in (slice(0, 3), slice(-3, None))
            for cols in (slice(0, 3), slice(-3, None))]


def flat_corners(image: np.ndarray) -> np.ndarray:
    """The flat regions that hold a corner of ``image``.

    Args:
        image: ``(H, W)`` float in [0, 1].
    Returns:
        ``(H, W)`` bool: pixels of the 4-connected flat components (5x5 range at most
        :data:`FLAT_RANGE`) that contain one of the image's four corner pixels.
    """
    image = np.ascontiguousarray(image, np.float32)
    if not any(np.ptp(image[rows, cols]) <= FLAT_RANGE for rows, cols in _CORNERS):
        return np.zeros(image.shape, bool)  # the cheap answer for most images without one
    kernel = np.ones((5, 5), np.uint8)
    flat = (cv2.dilate(image, kernel) - cv2.erode(image, kernel)) <= FLAT_RANGE
    _, labels = cv2.connectedComponents(flat.astype(np.uint8), connectivity=4)
    corners = labels[[0, 0, -1, -1], [0, -1, 0, -1]]
    return np.isin(labels, corners[corners > 0])


def fit_circle(points: np.ndarray) -> tuple[float, float, float]:
    """Algebraic (Kasa) circle through ``points``: ``(N, 2)`` px -> ``(cx, cy, r)`` px."""
    x, y = points[:, 0], points[:, 1]
    design = np.stack([x, y, np.ones_like(x)], 1)
    (d, e, f), *_ = np.linalg.lstsq(design, -(x * x + y * y), rcond=None)
    cx, cy = -d / 2, -e / 2
    return float(cx), float(cy), float(np.sqrt(max(cx * cx + cy * cy - f, 0.0)))


def round_field(image: Tensor | np.ndarray) -> tuple[float, float, float] | None:
    """The exposed disc of an intensifier frame, or None where the image shows none.

    Args:
        image: ``(H, W)`` or ``(1, H, W)`` intensities in [0, 1] (any float dtype, any
            device).
    Returns:
        ``(cx, cy, r)`` image pixels (the circle through the flat surround's inner edge,
        fitted with its outliers trimmed), or None: no flat corner, or the circle is
        narrower than :data:`MIN_RADIUS` of the shorter side, centred farther than
        :data:`MAX_OFFSET` of it from the image's centre, or leaves more than
        :data:`MAX_EXPOSED_OUTSIDE` of the exposed region (by :data:`INLIER_PX`) outside:
        then the corners' edge is no circle holding the field (shutters, an iris, one
        corner's short arc), and cups in it could be dropped.
    Raises:
        ValueError: ``image`` is not ``(H, W)`` or ``(1, H, W)``.
    """
    if isinstance(image, Tensor):
        image = image.detach().float().cpu().numpy()
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[0] != 1):
        raise ValueError(f"round_field takes an (H, W) or (1, H, W) image, got {image.shape}")
    # Every k-th pixel of a large image (k = shorter side // 1024): the same surround and
    # circle to k px, at 1 / k^2 of the work (0.33 s on a 3000 x 4096 frame at full size).
    stride = max(1, min(image.shape[-2:]) // _FULL_SIDE)
    pixels = image.reshape(image.shape[-2:])[::stride, ::stride]
    height, width = pixels.shape
    surround = flat_corners(pixels)
    if not surround.any():
        return None
    # Its inner edge: surround pixels beside the largest exposed region (text burnt into
    # the surround leaves small ones; the image's border is no edge).
    count, labels, stats, _ = cv2.connectedComponentsWithStats((~surround).astype(np.uint8))
    if count < 2:
        return None
    exposed = (labels == 1 + np.argmax(stats[1:, cv2.CC_STAT_AREA])).astype(np.uint8)
    points = _some_points(surround.view(np.uint8) & cv2.dilate(exposed, np.ones((3, 3), np.uint8)))
    keep = np.ones(len(points), bool)
    for _ in range(_TRIM_ROUNDS):
        if keep.sum() < 16:
            return None
        cx, cy, radius = fit_circle(points[keep])
        off = np.abs(np.hypot(points[:, 0] - cx, points[:, 1] - cy) - radius)
        # Trim progressively: a stem joining the surround pulls the first fit far off.
        trimmed = off <= max(INLIER_PX, 3 * float(np.median(off[keep])))
        if (trimmed == keep).all():
            break
        keep = trimmed
    # On a grid of every 4th pixel: the share wanted, at a sixteenth of the work.
    inside = 4 * _some_points(np.ascontiguousarray(exposed[::4, ::4]))
    outside = (np.hypot(inside[:, 0] - cx, inside[:, 1] - cy) > radius + INLIER_PX).mean()
    short = min(height, width)
    offset = np.hypot(cx - (width - 1) / 2, cy - (height - 1) / 2)
    if radius < MIN_RADIUS * short or offset > MAX_OFFSET * short or outside > MAX_EXPOSED_OUTSIDE:
        return None
    return cx * stride, cy * stride, radius * stride


def _some_points(mask: np.ndarray) -> np.ndarray:
    """``(N, 2)`` float64 (u, v) px of ``mask``'s pixels (uint8), every k-th: at most about
    ``_MAX_POINTS``."""
    # (u, v) int32, several times np.nonzero's speed (OpenCV 4 gave (N, 1, 2), 5 gives (N, 2)).
    found = cv2.findNonZero(mask)
    if found is None:
        return np.zeros((0, 2))
    found = found.reshape(-1, 2)
    step = max(1, len(found) // _MAX_POINTS)
    return found[::step].astype(np.float64)


def field_crop(image: Tensor | np.ndarray) -> tuple[int, int, int] | None:
    """The square to cut from ``image`` (as :func:`round_field` takes it) so that its round
    field fills it as the training frames' fields fill theirs: :func:`crop_of_field` of its
    :func:`round_field`."""
    return crop_of_field(round_field(image), *image.shape[-2:])


def crop_of_field(field: tuple[float, float, float] | None, height: int, width: int
                  ) -> tuple[int, int, int] | None:
    """``(u0, v0, side)`` pixels (top-left corner, side): the bounding square of the round
    ``field`` ``(cx, cy, r)`` of an ``height`` x ``width`` image, kept within the image;
    None without a field or where it is at least :data:`CROP_BELOW` of the shorter side
    wide."""
    if field is None or 2 * field[2] >= CROP_BELOW * min(height, width):
        return None
    cx, cy, radius = field
    side = min(math.ceil(2 * radius) + 1, height, width)
    return (min(max(round(cx - radius), 0), width - side),
            min(max(round(cy - radius), 0), height - side), side)


def content_crop(image: Tensor | np.ndarray) -> tuple[int, int, int] | None:
    """The square to cut from an image with no round field whose flat surround frames a
    narrower picture (a frame pasted on a wide black canvas: a screenshot's window, a
    capture's padding), where the locator, seeing it whole, found cups too small to see.

    Args:
        image: ``(H, W)`` or ``(1, H, W)`` intensities in [0, 1].
    Returns:
        ``(u0, v0, side)`` pixels: the bounding square of what is not the corners' flat
        surround (:func:`flat_corners`, whose 5 x 5 window leaves 2 px), 2 px wider a
        side, kept within the image; None without a flat corner or where it is at least
        :data:`CROP_BELOW` of the shorter side (text burnt into the canvas widens it, to
        the whole image where it lies in far corners).
    """
    if isinstance(image, Tensor):
        image = image.detach().float().cpu().numpy()
    pixels = image.reshape(image.shape[-2:])
    height, width = pixels.shape
    stride = max(1, min(height, width) // _FULL_SIDE)  # as round_field looks
    surround = flat_corners(pixels[::stride, ::stride])
    rows, cols = np.flatnonzero(~surround.all(1)), np.flatnonzero(~surround.all(0))
    if not surround.any() or len(rows) == 0:
        return None
    v0, v1 = rows[0] * stride - 2, (rows[-1] + 1) * stride + 2
    u0, u1 = cols[0] * stride - 2, (cols[-1] + 1) * stride + 2
    side = min(max(v1 - v0, u1 - u0), height, width)
    if side >= CROP_BELOW * min(height, width):
        return None
    return (int(min(max((u0 + u1 - side) // 2, 0), width - side)),
            int(min(max((v0 + v1 - side) // 2, 0), height - side)), int(side))


def outside_field(centres: Tensor, field: tuple[float, float, float] | Tensor | None
                  ) -> Tensor:
    """Which ``centres`` (``(..., 2)`` px) lie beyond ``field`` ``(cx, cy, r)`` px, or each
    beyond its own (``(..., 3)``, NaN rows: no field). All False where ``field`` is None;
    NaN centres are not outside."""
    if field is None:
        return centres.new_zeros(centres.shape[:-1], dtype=bool)
    cx, cy, radius = torch.as_tensor(field, dtype=centres.dtype).unbind(-1)
    # Each image's blobs judged as alone, whatever shares the batch (cupnet.batchwise).
    return hypot(centres[..., 0] - cx, centres[..., 1] - cy) > radius
