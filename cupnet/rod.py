"""A straight metal rod across the image (the cup's inserter during impaction), found and
painted over.

The inserter leaves the cup's dome along its axis, through the opening, and out of the field:
in the image a straight band of metal contrast from inside the rim's ellipse to the field's
edge. It cuts the opening in two, and a flagged cup with an inserter was mostly a rim fitted
to one of the halves (docs/training.md, item 70). Painted over from its sides, the opening
is whole again, and the rim stages see the rim the band had hidden.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# The band's edges: Canny on the image smoothed by this sigma (px), at these thresholds of
# the 8-bit display stretched between its 1st and 99th percentiles.
EDGE_SIGMA = 1.5
EDGE_THRESHOLDS = (20, 60)
# A rod's edges are the image's longest straight lines: each at least this fraction of the
# short side, with gaps of at most GAP of it.
MIN_LENGTH = 0.2
GAP = 0.02
# Its width (8-16 mm on 300-500 mm of magnified anatomy) as a fraction of the short side.
WIDTH = (0.01, 0.08)
PARALLEL_DEG = 2.0
# Its inside differs from both sides by at least this (of the stretched display's range),
# in the same direction: a rod, not the edge between two regions.
CONTRAST = 0.05
# The band grows along the rod by this much a step while it stays a rod (:func:`_extended`).
EXTEND_STEP_PX = 4.0
# Pixels painted beyond the edges (the edges' own blur) and the inpainting's radius.
MARGIN_PX = 3
INPAINT_RADIUS_PX = 5


def _stretched(image: np.ndarray) -> np.ndarray:
    """``image`` ``(H, W)`` float, scaled to [0, 1] between its 1st and 99th percentiles
    (float32, as OpenCV samples it)."""
    low, high = np.percentile(image, (1, 99))
    return np.clip((image - low) / max(float(high - low), 1e-12), 0, 1).astype(np.float32)


def _segments(display: np.ndarray) -> np.ndarray:
    """Long straight edge segments ``(S, 4)`` ``(x0, y0, x1, y1)`` px of ``display``."""
    side = min(display.shape)
    u8 = (255 * display).astype(np.uint8)
    edges = cv2.Canny(cv2.GaussianBlur(u8, (0, 0), EDGE_SIGMA), *EDGE_THRESHOLDS)
    lines = cv2.HoughLinesP(edges, 1, np.pi / 360, threshold=int(0.75 * MIN_LENGTH * side),
                            minLineLength=int(MIN_LENGTH * side), maxLineGap=int(GAP * side))
    return np.zeros((0, 4)) if lines is None else lines.reshape(-1, 4).astype(float)


def _side_means(display: np.ndarray, start: np.ndarray, along: np.ndarray,
                normal: np.ndarray, length: float, offsets: tuple[float, ...]) -> list[float]:
    """Mean of ``display`` along the line ``start + s along`` (``s`` in ``[0, length]``)
    shifted by each of ``offsets`` px along ``normal``."""
    s = np.linspace(0, length, max(int(length), 2))
    means = []
    for offset in offsets:
        x, y = (start[:, None] + along[:, None] * s + normal[:, None] * offset)
        inside = (x >= 0) & (y >= 0) & (x <= display.shape[1] - 1) & (y <= display.shape[0] - 1)
        if not inside.any():
            means.append(math.nan)
            continue
        values = cv2.remap(display, x[inside].astype(np.float32)[None],
                           y[inside].astype(np.float32)[None], cv2.INTER_LINEAR)
        means.append(float(values.mean()))
    return means


def _band_contrast(display: np.ndarray, start: np.ndarray, along: np.ndarray,
                   normal: np.ndarray, width: float, length: float) -> float:
    """How much both sides of the band ``start + s along + w normal`` (``s`` in ``[0,
    length]``, ``w`` in ``[0, width]`` px) differ from its inside, in the same direction:
    the smaller difference (side less inside; negative where the band is brighter), 0
    where the two sides differ in opposite directions (the edge between two regions, not
    a rod), NaN where a line leaves the image."""
    inner, side_a, side_b = _side_means(display, start, along, normal, length,
                                        (width / 2, -2 * MARGIN_PX - 2, width + 2 * MARGIN_PX + 2))
    a, b = side_a - inner, side_b - inner
    if not np.isfinite([a, b]).all():
        return math.nan
    return min(a, b, key=abs) if np.sign(a) == np.sign(b) else 0.0


def find_rod(image: np.ndarray) -> np.ndarray | None:
    """The band of a straight rod across ``image``, or None where it shows none.

    Args:
        image: ``(H, W)`` float, either display (metal dark or bright).
    Returns:
        ``(4, 2)`` px, the band's corners in order (along one edge, back along the other),
        from where its edges start to where they end, or None.
    """
    display = _stretched(image)
    side = min(display.shape)
    lines = _segments(display)
    if len(lines) < 2:
        return None
    starts, ends = lines[:, :2], lines[:, 2:]
    lengths = np.linalg.norm(ends - starts, axis=1)
    alongs = (ends - starts) / lengths[:, None]
    best: tuple[float, np.ndarray, np.ndarray, np.ndarray, float, float, float] | None = None
    for i in range(len(lines)):
        along, normal = alongs[i], np.array([-alongs[i][1], alongs[i][0]])
        for j in range(i + 1, len(lines)):
            if abs(float(along @ alongs[j])) < math.cos(math.radians(PARALLEL_DEG)):
                continue
            width = float((starts[j] - starts[i]) @ normal)
            if not WIDTH[0] * side < abs(width) < WIDTH[1] * side:
                continue
            # The two edges' common stretch along the band.
            s_j = sorted(((starts[j] - starts[i]) @ along, (ends[j] - starts[i]) @ along))
            low, high = max(0.0, s_j[0]), min(lengths[i], s_j[1])
            if high - low < MIN_LENGTH * side / 2:
                continue
            contrast = _band_contrast(display, starts[i] + along * low, along,
                                      normal * math.copysign(1.0, width), abs(width),
                                      high - low)
            if not abs(contrast) >= CONTRAST:  # NaN too
                continue
            if best is None or high - low > best[0]:
                best = (high - low, starts[i], along, normal * width, low, high, contrast)
    if best is None:
        return None
    _, origin, along, across, low, high, contrast = best
    low, high = _extended(display, origin, along, across, (low, high), contrast)
    return np.array([origin + along * low, origin + along * high,
                     origin + along * high + across, origin + along * low + across])


def _extended(display: np.ndarray, origin: np.ndarray, along: np.ndarray, across: np.ndarray,
              stretch: tuple[float, float], contrast: float) -> tuple[float, float]:
    """The band ``origin + s along + w across`` (``w`` in [0, 1]) from ``stretch`` ``(low,
    high)`` in ``s`` out along the rod, step by step, while its inside keeps at least half
    its ``contrast`` against both sides: its edges break up where the rod crosses the cup
    or nears the field's edge, and a piece of rod left there cuts the opening as before."""
    width = float(np.linalg.norm(across))
    normal = across / width
    ends = list(stretch)
    for end, step in ((0, -EXTEND_STEP_PX), (1, EXTEND_STEP_PX)):
        while True:
            s = ends[end] + step
            here = _band_contrast(display, origin + along * min(s, s - step), along, normal,
                                  width, EXTEND_STEP_PX)
            if not here * np.sign(contrast) >= abs(contrast) / 2:  # NaN too
                break
            ends[end] = s
        # At the image's border its sides leave the image first: the rod goes on to it.
        centre = origin + along * ends[end] + across / 2
        if min(*centre, display.shape[1] - 1 - centre[0],
               display.shape[0] - 1 - centre[1]) < width:
            ends[end] += math.copysign(width, step)
    return ends[0], ends[1]


def rod_mask(shape: tuple[int, int], band: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 mask (255 inside) of ``band`` (:func:`find_rod`'s corners), widened
    by ``MARGIN_PX`` each side."""
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(band).astype(np.int32), 255)
    kernel = np.ones((2 * MARGIN_PX + 1, 2 * MARGIN_PX + 1), np.uint8)
    return cv2.dilate(mask, kernel)


def without_rod(image: np.ndarray) -> np.ndarray | None:
    """``image`` ``(H, W)`` float with the rod :func:`find_rod` finds painted over from its
    sides (OpenCV's Telea inpainting; every other pixel as it was), or None where it finds
    none."""
    band = find_rod(image)
    if band is None:
        return None
    mask = rod_mask(image.shape, band)
    # 16 bits: OpenCV's inpainting of float images strays outside their range.
    low, high = float(image.min()), float(image.max())
    scale = max(high - low, 1e-12) / 65535
    counts = np.round((image - low) / scale).astype(np.uint16)
    painted = cv2.inpaint(counts, mask, INPAINT_RADIUS_PX, cv2.INPAINT_TELEA) * scale + low
    return np.where(mask > 0, painted, image).astype(image.dtype)
