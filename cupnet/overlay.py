"""Overlay images for checking results by eye: rim ellipse, landmarks, the dome's outline,
pose as text.

Drawn with OpenCV on a contrast-stretched 8-bit copy of the image, scaled so the longer side
lies between ``min_side`` (small images are enlarged, so the text stays readable) and
``max_side`` pixels (writing stays fast on 4096 px images); coordinates are drawn with
sub-pixel precision.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from cupnet.crops import rescaled_pixels
from cupnet.ellipse import ellipse_points
from cupnet.io.results import atomic_write

# BGR colours by status.
STATUS_COLOURS = {"ok": (80, 220, 80), "ambiguous": (0, 215, 255)}
ERROR_COLOUR = (60, 60, 255)
CHECK_COLOUR = (255, 0, 255)  # a pose the model doubts: look before trusting it
TEXT_COLOUR = (255, 255, 255)
_SHIFT = 4  # fractional bits of OpenCV's sub-pixel drawing
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_PANEL_CHARS = 48  # a text panel's least width, in characters


@dataclass
class CupDrawing:
    """What to draw for one cup (original-image pixels, public units).

    Attributes:
        ellipse: ``(5,)`` (cx, cy, a, b, alpha_deg), or None / NaN where there is none.
        landmarks: ``(N, 2)`` (u, v) or None.
        weights: ``(N,)`` in [0, 1] (landmark shading) or None.
        lines: text lines describing the cup.
        status: ``ok``, ``ambiguous`` or ``error: ...`` (sets the colour) ...
        outline: ``(M, 2)`` (u, v) along the dome's outline (an open curve, drawn thin), or
            None.
        check: ... unless the model doubts the pose (drawn in ``CHECK_COLOUR``).
        number: the label drawn at its centre, results.csv's ``cup`` (a landmark file's own
            labels under ``--landmarks``); None: its place in the list, from 0.
    """

    ellipse: np.ndarray | None
    landmarks: np.ndarray | None
    weights: np.ndarray | None
    lines: list[str]
    status: str = "ok"
    outline: np.ndarray | None = None
    check: bool = False
    number: int | None = None


def display_image(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` [0, 1] image -> uint8 with a 1st-99th percentile contrast stretch."""
    step_v, step_u = max(1, image.shape[0] // 256), max(1, image.shape[1] // 256)
    lo, hi = np.percentile(image[::step_v, ::step_u], (1, 99))
    if hi <= lo:
        lo, hi = 0.0, 1.0
    # One saturating pass; values below lo are raised to it first, so the absolute value
    # convertScaleAbs takes changes nothing.
    return cv2.convertScaleAbs(np.maximum(image, lo, dtype=np.float32), alpha=255 / (hi - lo),
                               beta=-255 * lo / (hi - lo))


def pose_lines(index: int, status: str, pose: Sequence[float], residual_px: float,
               alt_pose: Sequence[float] | None = None, doubt: float | None = None,
               check: bool = False, pose_sd: Sequence[float] | None = None) -> list[str]:
    """Text lines of one cup: its status (and the model's doubt), pose (deg, mm) with its
    standard errors where given (``+-``: OpenCV's fonts have no plus-minus sign), residual
    and the second pose."""
    lines = [f"cup {index}: {status}"]
    if doubt is not None and math.isfinite(doubt):
        lines[0] += f", doubt {doubt:.2f}" + (" - CHECK BY EYE" if check else "")
    if all(math.isfinite(v) for v in pose):
        errors = (pose_sd if pose_sd is not None and all(math.isfinite(v) for v in pose_sd)
                  else [None] * len(pose))
        theta, phi, k_mm, l_mm, h_mm = (f"{v:.1f}" if e is None else f"{v:.1f} +-{e:.1f}"
                                        for v, e in zip(pose, errors, strict=True))
        lines.append(f"  anteversion {theta} deg, inclination {phi} deg")
        lines.append(f"  k {k_mm}, l {l_mm}, h {h_mm} mm; residual {residual_px:.2f} px")
    if alt_pose is not None and all(math.isfinite(v) for v in alt_pose):
        lines.append(f"  or: anteversion {alt_pose[0]:.1f} deg, inclination {alt_pose[1]:.1f} "
                     f"deg, h {alt_pose[4]:.1f} mm")
    return lines


def _fixed(value: float) -> int:
    return int(round(value * (1 << _SHIFT)))


def draw_overlay(image: np.ndarray, cups: Sequence[CupDrawing], title: str,
                 max_side: int = 1024, min_side: int = 768) -> np.ndarray:
    """Overlay of the cups on ``image``.

    Args:
        image: ``(H, W)`` float in [0, 1].
        cups: what to draw, in original-image pixels.
        title: first text line (image name and status).
        max_side, min_side: bounds of the overlay's longer side (pixels).
    Returns:
        ``(h, w, 3)`` uint8 BGR: ``H, W`` scaled by ``clip(L, min_side, max_side) / L`` with
        ``L = max(H, W)``; an image too oblong to hold its text gets it on a panel below
        (then ``h`` and ``w`` are larger; the image keeps the top left).
    """
    longer = max(image.shape)
    scale = min(max_side, max(min_side, longer)) / longer
    gray = display_image(image)
    if scale != 1.0:
        size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA if scale < 1
                          else cv2.INTER_LINEAR)
    canvas = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    unit = max(canvas.shape[:2]) / 512  # line widths and text grow with the overlay
    thickness = max(1, round(unit))
    to_view = lambda p: rescaled_pixels(np.asarray(p, np.float64), scale)  # noqa: E731
    for index, cup in enumerate(cups):
        colour = CHECK_COLOUR if cup.check else STATUS_COLOURS.get(cup.status, ERROR_COLOUR)
        # Landmarks first and small, so the fitted ellipse drawn over them stays visible.
        if cup.landmarks is not None:
            weights = np.ones(len(cup.landmarks)) if cup.weights is None else cup.weights
            for (u, v), w in zip(to_view(cup.landmarks), weights, strict=True):
                if not (np.isfinite(u) and np.isfinite(v)):
                    continue
                shade = tuple(int(c * (0.3 + 0.7 * float(np.clip(w, 0, 1)))) for c in (255, 80, 0))
                cv2.circle(canvas, (_fixed(u), _fixed(v)), _fixed(thickness), shade, -1,
                           cv2.LINE_AA, _SHIFT)
        if cup.outline is not None and np.isfinite(cup.outline).all():
            curve = np.round(to_view(cup.outline) * (1 << _SHIFT)).astype(np.int32)
            cv2.polylines(canvas, [curve], False, colour, max(1, thickness // 2), cv2.LINE_AA,
                          _SHIFT)
        if cup.ellipse is not None and np.isfinite(cup.ellipse).all():
            cx, cy = to_view(cup.ellipse[:2])
            axes = (_fixed(cup.ellipse[2] * scale), _fixed(cup.ellipse[3] * scale))
            cv2.ellipse(canvas, (_fixed(cx), _fixed(cy)), axes, float(cup.ellipse[4]), 0, 360,
                        colour, thickness, cv2.LINE_AA, _SHIFT)
            label = str(index if cup.number is None else cup.number)
            cv2.putText(canvas, label, (round(cx), round(cy)), _FONT, 0.5 * unit, colour,
                        thickness, cv2.LINE_AA)
    lines = [title] + [line for cup in cups for line in cup.lines]
    drawn = [to_view(points) for cup in cups for points in _drawn_points(cup)]
    return _with_text(canvas, lines, 0.4 * unit, thickness,
                      np.concatenate(drawn) if drawn else np.zeros((0, 2)))


def _drawn_points(cup: CupDrawing) -> list[np.ndarray]:
    """``(M, 2)`` original-image pixels along what is drawn of ``cup``: its ellipse (every 5
    deg), landmarks and outline, which the text must not cover."""
    parts = [p for p in (cup.landmarks, cup.outline) if p is not None]
    if cup.ellipse is not None and np.isfinite(cup.ellipse).all():
        t = torch.deg2rad(torch.arange(0, 360, 5, dtype=torch.float64))
        parts.append(ellipse_points(torch.as_tensor(cup.ellipse, dtype=torch.float64), t))
    return [np.asarray(p, np.float64).reshape(-1, 2) for p in parts]


def _wrap(line: str, width: int, font_scale: float, thickness: int) -> list[str]:
    """Greedy word wrap of one line to ``width`` pixels (continuations indented)."""
    words, out = line.split(" "), []
    current = words[0]
    for word in words[1:]:
        candidate = f"{current} {word}"
        if cv2.getTextSize(candidate, _FONT, font_scale, thickness)[0][0] > width:
            out.append(current)
            current = f"    {word}"
        else:
            current = candidate
    return [*out, current]


def _with_text(canvas: np.ndarray, lines: list[str], font_scale: float,
               thickness: int, drawn: np.ndarray) -> np.ndarray:
    """``canvas`` with the lines of text in a corner on a dark band, readable on any image:
    the first of top left, top right, bottom left and bottom right that covers none of the
    ``drawn`` points ``(M, 2)`` (canvas pixels; a cup in the top left had been dimmed under
    the text), else the one covering fewest. Where they would cover more than half of it (a
    very wide or tall image: a 4000 x 300 strip's text had covered it whole, and been cut
    off), on a panel below it instead, at least :data:`_PANEL_CHARS` characters wide."""
    (_, height), baseline = cv2.getTextSize("Ag", _FONT, font_scale, thickness)
    step = height + baseline + 2
    wrapped = _wrapped(lines, canvas.shape[1], font_scale, thickness)
    band_h, band_w = _band_size(wrapped, font_scale, thickness, step)
    if band_h <= canvas.shape[0] // 2:
        rows, cols = canvas.shape[0] - band_h, canvas.shape[1] - band_w
        corners = [(0, 0), (0, cols), (rows, 0), (rows, cols)]
        covered = [int(((drawn[:, 0] >= x - 2) & (drawn[:, 0] <= x + band_w + 2)
                        & (drawn[:, 1] >= y - 2) & (drawn[:, 1] <= y + band_h + 2)).sum())
                   for y, x in corners]
        top, left = corners[int(np.argmin(covered))]  # the first of the least covered
        _draw_text_block(canvas, wrapped, font_scale, thickness, height, step,
                         (top, left, band_h, band_w))
        return canvas
    width = max(canvas.shape[1], 12 + cv2.getTextSize("x" * _PANEL_CHARS, _FONT, font_scale,
                                                      thickness)[0][0])
    wrapped = _wrapped(lines, width, font_scale, thickness)
    panel = np.zeros((step * len(wrapped) + 4, width, 3), np.uint8)
    _draw_text_block(panel, wrapped, font_scale, thickness, height, step, (0, 0, *panel.shape[:2]))
    picture = np.zeros((canvas.shape[0], width, 3), np.uint8)
    picture[:, :canvas.shape[1]] = canvas
    return np.vstack([picture, panel])


def _wrapped(lines: list[str], width: int, font_scale: float, thickness: int) -> list[str]:
    """``lines`` each wrapped (:func:`_wrap`) to ``width`` pixels less a margin."""
    return [part for line in lines for part in _wrap(line, width - 12, font_scale, thickness)]


def _band_size(lines: list[str], font_scale: float, thickness: int, step: int
               ) -> tuple[int, int]:
    """Height and width in pixels of the dark band under wrapped ``lines``."""
    if not lines:
        return 0, 0
    width = max(cv2.getTextSize(line, _FONT, font_scale, thickness)[0][0] for line in lines)
    return step * len(lines) + 4, width + 8


def _draw_text_block(canvas: np.ndarray, lines: list[str], font_scale: float, thickness: int,
                     height: int, step: int, band: tuple[int, int, int, int]) -> None:
    """Wrapped ``lines`` on ``canvas`` (in place), a line every ``step`` pixels (``height``:
    the font's), on the dark ``band`` (top, left, height, width; :func:`_band_size`)."""
    top, left, band_h, band_w = band
    dark = canvas[top:top + band_h, left:left + band_w]
    dark[:] = (dark * 0.35).astype(np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(canvas, line, (left + 4, top + 2 + height + i * step), _FONT, font_scale,
                    TEXT_COLOUR, thickness, cv2.LINE_AA)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write a PNG atomically, creating the folder.

    Fast settings: zlib level 1 with the 'up' filter encodes a 1024 px overlay about twice as
    fast as OpenCV's default at a similar size.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1,
                                            cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP])
    if not ok:
        raise OSError(f"cannot encode {path}")
    atomic_write(path, lambda f: f.write(data.tobytes()), binary=True)
