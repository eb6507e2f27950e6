"""Exact resampling between an original image and network inputs (letterbox, cup crops).

Every resampled view is described by an affine ``crop_to_image`` ``(..., 2, 3)`` that maps a
pixel ``(u, v)`` of the view to the original image: ``(u', v') = A[:, :2] @ (u, v) + A[:, 2]``,
pixel centres at integers in both (CONVENTIONS.md), so landmarks found in a view map back to
original-image pixels exactly with :func:`to_image`. The letterbox is a similarity; a cup crop
is rotated onto the rim ellipse's axes and may stretch its minor axis, so a rim seen almost
edge-on still spans many crop pixels across (affine maps keep ellipses ellipses).
"""

from __future__ import annotations

import math
from typing import TypeVar

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.transform import invert_affine_transform, warp_affine
from torch import Tensor

from cupnet.batchwise import matmul

T = TypeVar("T")


def similarity(scale: Tensor, offset_u: Tensor, offset_v: Tensor) -> Tensor:
    """``(...)`` scale (image px per view px) and offsets -> ``(..., 2, 3)`` crop_to_image."""
    zero = torch.zeros_like(scale)
    return torch.stack([torch.stack([scale, zero, offset_u], -1),
                        torch.stack([zero, scale, offset_v], -1)], -2)


def letterbox_affine(height: int, width: int, size: int, dtype: torch.dtype = torch.float32
                     ) -> Tensor:
    """crop_to_image ``(2, 3)`` of the ``size x size`` letterbox of an ``height x width`` image.

    The image is scaled by ``size / max(height, width)`` (pixel areas map onto pixel areas,
    as in ``cv2.resize``) and centred; the rest is padding.
    """
    step = max(height, width) / size  # image pixels per letterbox pixel
    # Centre of the letterbox <-> centre of the image.
    centre = (size - 1) / 2
    off_u = (width - 1) / 2 - step * centre
    off_v = (height - 1) / 2 - step * centre
    return similarity(torch.tensor(step, dtype=dtype), torch.tensor(off_u, dtype=dtype),
                      torch.tensor(off_v, dtype=dtype))


def enlargement(height: int, width: int, below: int | None, to: int) -> float:
    """The factor (>= 1) that brings an ``height x width`` image's shorter side to ``to``
    px where it is under ``below`` px: 1 where it is not, or ``below`` is None."""
    short = min(height, width)
    if below is None or short >= below:
        return 1.0
    return max(1.0, to / short)


def reduction(height: int, width: int, above: int | None, to: int) -> float:
    """The factor (<= 1) that brings an ``height x width`` image's shorter side to ``to``
    px where it is over ``above`` px: 1 where it is not, or ``above`` is None."""
    short = min(height, width)
    if above is None or short <= above:
        return 1.0
    return min(1.0, to / short)


def rescaled_pixels(u: T, factor: float | Tensor) -> T:
    """Pixel positions ``u`` (px: an array, tensor or number) in the image resized ``factor``
    times, pixel centres at integers in both: ``(u + 0.5) * factor - 0.5``."""
    return (u + 0.5) * factor - 0.5


def resized(image: Tensor, factor: float) -> Tensor:
    """``image`` ``(C, H, W)`` in [0, 1] resized ``factor`` times: enlarged (> 1) by Lanczos
    (OpenCV's 8 x 8 kernel), reduced (< 1) by area averaging (each new pixel the mean of
    the old ones it covers: no aliasing, and the noise averaged down as a detector's
    larger pixels would), clipped to [0, 1]: ``(C, round(H f), round(W f))``.

    Pixel centres at integers in both: the image's ``u`` lies at ``(u + 0.5) f - 0.5``, with
    ``f`` the factor itself whatever the sizes' rounding (OpenCV scales so where it is given
    ``fx`` and no size), so a principal point and a pixel spacing map exactly.
    """
    dtype = np.float64 if image.dtype == torch.float64 else np.float32
    how = cv2.INTER_LANCZOS4 if factor > 1 else cv2.INTER_AREA
    planes = [cv2.resize(plane.numpy().astype(dtype, copy=False), None, fx=factor, fy=factor,
                         interpolation=how)
              for plane in image.detach().cpu()]
    return torch.from_numpy(np.stack(planes).clip(0, 1)).to(image.device, image.dtype)


def square_windows(height: int, width: int, size: int, overlap: float = 0.5,
                   dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """crop_to_image ``(n, 2, 3)`` of ``size x size`` views of the square windows of an
    ``height x width`` image, and each view's place ``(n, 2)`` (columns, rows) on the grid
    they share.

    The locator learnt square images whose field of view fills them; a letterbox of an
    oblong image shows its cups smaller (by the aspect ratio) than it learnt. Windows as wide
    as the image's short side keep the scale: they slide along the long side, from one end
    to the other, overlapping by at least ``overlap`` of their side, their offsets snapped
    to whole view pixels, so that their views tile one grid. An image whose sides differ by
    less than half a view pixel has one window, its letterbox (:func:`letterbox_affine`).
    """
    short, long = min(height, width), max(height, width)
    step = short / size  # image pixels per view pixel
    extra = round((long - short) / step)  # view pixels the long side adds
    if extra == 0:
        return (letterbox_affine(height, width, size, dtype)[None],
                torch.zeros(1, 2, dtype=torch.long))
    count = math.ceil(extra / (size * (1 - overlap))) + 1
    places = torch.linspace(0, extra, count, dtype=torch.float64).round()
    base = letterbox_affine(short, short, size, torch.float64)
    affines = base.repeat(count, 1, 1)
    axis = 0 if width >= height else 1  # the long side: u or v
    affines[:, axis, 2] += places * step
    grid = torch.zeros(count, 2, dtype=torch.long)
    grid[:, axis] = places.long()
    return affines.to(dtype), grid


def ellipse_crop_affine(frame: Tensor, size: int) -> Tensor:
    """crop_to_image ``(..., 2, 3)`` of a crop framed on an ellipse.

    Args:
        frame: ``(..., 5)`` (cx, cy, major_side, minor_side, angle_deg): the crop's centre in
            image pixels, the image lengths its width (along the angle) and height cover, and
            the angle of its width axis from +u towards +v.
        size: crop size in pixels.
    """
    step_u, step_v = frame[..., 2] / size, frame[..., 3] / size
    ang = torch.deg2rad(frame[..., 4])
    c, s = torch.cos(ang), torch.sin(ang)
    half = (size - 1) / 2
    lin = torch.stack([torch.stack([c * step_u, -s * step_v], -1),
                       torch.stack([s * step_u, c * step_v], -1)], -2)
    offset = frame[..., :2] - half * lin.sum(-1)
    return torch.cat([lin, offset[..., None]], -1)


def frame_ellipse(ellipse: Tensor, fill: float, min_ratio: float, max_stretch: float) -> Tensor:
    """Crop frames ``(..., 5)`` for ellipses ``(..., 5)`` (cx, cy, a, b, alpha_deg).

    The major axis spans ``fill`` of the crop; the minor direction is stretched so the
    ellipse's axis ratio in the crop is at least ``min_ratio``, by ``max_stretch`` at most.
    """
    a, b = ellipse[..., 2], ellipse[..., 3]
    major = 2 * a / fill
    ratio = (b / (min_ratio * a)).clamp(1 / max_stretch, 1.0)
    return torch.stack([ellipse[..., 0], ellipse[..., 1], major, major * ratio, ellipse[..., 4]],
                       -1)


def ellipse_to_view(ellipse: Tensor, crop_to_image: Tensor) -> Tensor:
    """Image ellipses ``(..., 5)`` -> the same ellipses in view pixels (``(..., 2, 3)`` affines)."""
    from cupnet.ellipse import conic_to_params, params_to_conic

    bottom = torch.zeros_like(crop_to_image[..., :1, :])
    bottom[..., 0, 2] = 1
    hom = torch.cat([crop_to_image, bottom], -2)  # view -> image, homogeneous
    conic = params_to_conic(ellipse)
    return conic_to_params(matmul(matmul(hom.transpose(-1, -2), conic), hom))


def to_image(points: Tensor, crop_to_image: Tensor) -> Tensor:
    """View pixels ``(..., N, 2)`` -> original-image pixels with ``(..., 2, 3)`` affines."""
    return matmul(points, crop_to_image[..., :2].transpose(-1, -2)) + crop_to_image[..., None, :, 2]


def to_view(points: Tensor, crop_to_image: Tensor) -> Tensor:
    """Original-image pixels ``(..., N, 2)`` -> view pixels (inverse of :func:`to_image`)."""
    lin = crop_to_image[..., :2]
    return matmul(points - crop_to_image[..., None, :, 2], torch.linalg.inv(lin).transpose(-1, -2))


def resample(image: Tensor, crop_to_image: Tensor, size: int, antialias: bool = True) -> Tensor:
    """Resample one image into a ``size x size`` view (zeros outside the image).

    Downsampling by ``step`` image px per view px (the smaller singular value of the affine)
    first box-filters the covered region by ``floor(step)`` (an average pool with an exactly
    known pixel-centre shift), then samples bilinearly, so views of large images are not
    aliased.

    Args:
        image: ``(C, H, W)``.
        crop_to_image: ``(2, 3)`` affine.
        size: view size in pixels.
    Returns:
        ``(C, size, size)`` in the image's dtype. Computed with autocast off: the affines are
        geometry, and in bfloat16 they would move the samples by pixels.
    """
    with torch.autocast(image.device.type, enabled=False):
        affine = crop_to_image.to(image.dtype)
        # Box-filter only by the smaller scale: a stretched direction must keep its detail.
        step = float(torch.linalg.svdvals(affine[:, :2])[-1])
        pool = max(1, math.floor(step)) if antialias else 1
        if pool > 1:
            last = size - 1.0
            corners = to_image(torch.tensor([[0.0, 0.0], [last, 0.0], [0.0, last], [last, last]],
                                            dtype=image.dtype, device=image.device), affine)
            lo = (corners.min(0).values - pool).floor().clamp_min(0).long()
            hi = (corners.max(0).values + pool + 1).ceil().long()
            u0, v0 = int(lo[0]), int(lo[1])
            u1, v1 = min(int(hi[0]), image.shape[-1]), min(int(hi[1]), image.shape[-2])
            if u1 - u0 < pool or v1 - v0 < pool:  # the view lies outside the image
                return image.new_zeros(image.shape[0], size, size)
            region = F.avg_pool2d(image[None, :, v0:v1, u0:u1], pool)[0]
            # Pooled pixel j covers region pixels [j p, j p + p - 1]: centre u0 + j p + (p - 1) / 2.
            shift = torch.tensor([u0 + (pool - 1) / 2, v0 + (pool - 1) / 2], dtype=image.dtype,
                                 device=image.device)
            affine = torch.cat([affine[:, :2] / pool, ((affine[:, 2] - shift) / pool)[:, None]], 1)
            image = region
        image_to_crop = invert_affine_transform(affine[None])
        return warp_affine(image[None], image_to_crop, (size, size), align_corners=True)[0]


def lattice_bilinear(images: Tensor, index: Tensor, coords: Tensor, origin: Tensor,
                     stride: Tensor, extent: Tensor, border: bool = False) -> Tensor:
    """Bilinear samples of regular lattices of pixels, for ``K`` views at once.

    Lattice point ``(i, j)`` of view ``k`` is pixel ``origin[k] + stride[k] * (i, j)`` of
    ``images[index[k]]``, for ``0 <= i < extent[k, 0]``, ``0 <= j < extent[k, 1]``; a sample
    at lattice coordinates ``(x, y)`` weighs its four neighbours as ``F.grid_sample`` with
    ``align_corners=True`` does: a neighbour off the lattice counts as zero, or with
    ``border`` the coordinates are first clamped onto it (``padding_mode="border"``).

    Args:
        images: ``(B, C, H, W)``.
        index: ``(K,)`` long, the image of each view.
        coords: ``(K, M, 2)`` lattice coordinates (x, y) of the samples.
        origin: ``(K, 2)`` long pixel (u, v) of lattice point (0, 0).
        stride: ``(K,)`` long pixels between lattice points.
        extent: ``(K, 2)`` long lattice points along u and v (at most 0: none, all zeros).
    Returns:
        ``(K, C, M)`` in ``images``' dtype.
    """
    channels, height, width = images.shape[1:]
    if border:
        last = (extent - 1).clamp_min(0).to(coords.dtype)[:, None]
        coords = torch.minimum(coords.clamp_min(0), last)
    corner = coords.floor()
    frac = (coords - corner).to(images.dtype)
    corner = corner.long()
    # Element of (image, channel) planes in the flattened images: (K, C, 1).
    plane = ((index[:, None] * channels + torch.arange(channels, device=index.device))
             * (height * width))[..., None]
    flat = images.reshape(-1)
    out = images.new_zeros(coords.shape[0], channels, coords.shape[1])
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        i, j = corner[..., 0] + du, corner[..., 1] + dv
        weight = ((frac[..., 0] if du else 1 - frac[..., 0])
                  * (frac[..., 1] if dv else 1 - frac[..., 1]))
        inside = (i >= 0) & (i < extent[:, None, 0]) & (j >= 0) & (j < extent[:, None, 1])
        # Off-lattice neighbours (weight 0) are clamped onto some pixel, to be gathered.
        u = (origin[:, None, 0] + stride[:, None] * i).clamp(0, width - 1)
        v = (origin[:, None, 1] + stride[:, None] * j).clamp(0, height - 1)
        pixel = (v * width + u)[:, None]
        out += flat[plane + pixel] * (weight * inside)[:, None]
    return out


def resample_stacked(images: Tensor, crop_to_image: Tensor, size: int, index: Tensor,
                      antialias: bool) -> Tensor:
    """:func:`resample` of every view at once, from equal-size images ``(B, C, H, W)``: the
    same box filter (each view's region pooled from its own corner, so the same pooled
    lattice) and bilinear samples, one gather per neighbour instead of a few dozen kernels
    a view (on an accelerator the per-view loop is bound by launches)."""
    height, width = images.shape[-2:]
    with torch.autocast(images.device.type, enabled=False):
        affine = crop_to_image.to(images.dtype)
        steps = torch.linalg.svdvals(affine[:, :, :2])[:, -1]
        pool = steps.floor().long().clamp_min(1) if antialias else torch.ones_like(
            index, dtype=torch.long)
        last = size - 1.0
        corners = to_image(affine.new_tensor([[0.0, 0.0], [last, 0.0], [0.0, last],
                                              [last, last]]).expand(len(affine), 4, 2), affine)
        pad = pool[:, None].to(images.dtype)
        lo = (corners.min(1).values - pad).floor().clamp_min(0).long()
        hi = (corners.max(1).values + pad + 1).ceil().long()
        hi = torch.minimum(hi, torch.tensor([width, height], device=hi.device))
        # Without pooling the view samples the whole image, as resample does.
        pooled = pool > 1
        whole = torch.tensor([width, height], device=lo.device)
        origin = torch.where(pooled[:, None], lo, 0)
        extent = torch.where(pooled[:, None], torch.div(hi - lo, pool[:, None],
                                                        rounding_mode="floor"), whole)
        shift = origin.to(images.dtype) + (pad - 1) / 2
        lattice = torch.cat([affine[:, :, :2] / pad[..., None],
                             ((affine[:, :, 2] - shift) / pad)[..., None]], -1)
        axis = torch.arange(size, dtype=images.dtype, device=images.device)
        view = torch.stack(torch.meshgrid(axis, axis, indexing="xy"), -1).reshape(-1, 2)
        coords = to_image(view.expand(len(affine), -1, -1), lattice)  # (K, size^2, 2)
        out = images.new_zeros(len(affine), images.shape[1], size * size)
        for p in pool.unique().tolist():  # one box-filtered image per pooling step
            box = F.avg_pool2d(images, p, stride=1) if p > 1 else images
            mine = pool == p
            out[mine] = lattice_bilinear(box, index[mine], coords[mine], origin[mine],
                                         pool[mine], extent[mine])
        return out.reshape(len(affine), -1, size, size)


def resample_batch(images: Tensor | list[Tensor], crop_to_image: Tensor, size: int,
                   index: Tensor | None = None, antialias: bool = True) -> Tensor:
    """Views of several images: ``(K, 2, 3)`` affines, view ``k`` taken from ``images[index[k]]``.

    Off the CPU, views of equal-size images are taken all at once
    (:func:`resample_stacked`, the same samples to float rounding); on the CPU, one
    :func:`resample` each, which pools only each view's region.

    Args:
        images: ``(B, C, H, W)`` or a list of ``(C, H_i, W_i)``.
        crop_to_image: ``(K, 2, 3)``.
        size: view size.
        index: ``(K,)`` image of each view (default ``arange(K)``).
    Returns:
        ``(K, C, size, size)``.
    """
    index = torch.arange(crop_to_image.shape[0]) if index is None else index
    if (len(index) and images[0].device.type != "cpu"
            and all(image.shape == images[0].shape for image in images)):
        stack = images if isinstance(images, Tensor) else torch.stack(list(images))
        return resample_stacked(stack, crop_to_image.to(stack.device), size,
                                 index.to(stack.device), antialias)
    views = [resample(images[int(i)], a, size, antialias) for i, a in zip(index, crop_to_image,
                                                                          strict=True)]
    if not views:
        channels = images[0].shape[0] if len(images) else 1
        return crop_to_image.new_zeros(0, channels, size, size)
    return torch.stack(views)
