"""Exact resampling between an original image and network inputs (letterbox, square crops).

Every resampled view is described by an affine ``crop_to_image`` ``(..., 2, 3)`` that maps a
pixel ``(u, v)`` of the view to the original image: ``(u', v') = A[:, :2] @ (u, v) + A[:, 2]``,
pixel centres at integers in both (CONVENTIONS.md), so landmarks found in a view map back to
original-image pixels exactly with :func:`to_image`. The views used here are axis-aligned
similarities (uniform scale, translation).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.geometry.transform import invert_affine_transform, warp_affine
from torch import Tensor


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


def square_crop_affine(centre: Tensor, side: Tensor, size: int) -> Tensor:
    """crop_to_image ``(..., 2, 3)`` of a square crop of ``side`` image px centred on ``centre``.

    Args:
        centre: ``(..., 2)`` image pixels (u, v).
        side: ``(...)`` image pixels covered by the crop's ``size`` pixels.
        size: crop size in pixels.
    """
    step = side / size
    half = (size - 1) / 2
    return similarity(step, centre[..., 0] - step * half, centre[..., 1] - step * half)


def to_image(points: Tensor, crop_to_image: Tensor) -> Tensor:
    """View pixels ``(..., N, 2)`` -> original-image pixels with ``(..., 2, 3)`` affines."""
    return points @ crop_to_image[..., :2].transpose(-1, -2) + crop_to_image[..., None, :, 2]


def to_view(points: Tensor, crop_to_image: Tensor) -> Tensor:
    """Original-image pixels ``(..., N, 2)`` -> view pixels (inverse of :func:`to_image`)."""
    lin = crop_to_image[..., :2]
    return (points - crop_to_image[..., None, :, 2]) @ torch.linalg.inv(lin).transpose(-1, -2)


def resample(image: Tensor, crop_to_image: Tensor, size: int, antialias: bool = True) -> Tensor:
    """Resample one image into a ``size x size`` view (zeros outside the image).

    Downsampling by ``step`` image px per view px first box-filters the covered region by
    ``floor(step)`` (an average pool with an exactly known pixel-centre shift), then samples
    bilinearly, so views of large images are not aliased.

    Args:
        image: ``(C, H, W)``.
        crop_to_image: ``(2, 3)`` affine (similarity).
        size: view size in pixels.
    Returns:
        ``(C, size, size)`` in the image's dtype.
    """
    affine = crop_to_image.to(image.dtype)
    step = float(torch.sqrt(torch.linalg.det(affine[:, :2]).abs()))
    pool = max(1, math.floor(step)) if antialias else 1
    if pool > 1:
        corners = to_image(torch.tensor([[0.0, 0.0], [size - 1.0, size - 1.0]],
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


def resample_batch(images: Tensor | list[Tensor], crop_to_image: Tensor, size: int,
                   index: Tensor | None = None, antialias: bool = True) -> Tensor:
    """Views of several images: ``(K, 2, 3)`` affines, view ``k`` taken from ``images[index[k]]``.

    Args:
        images: ``(B, C, H, W)`` or a list of ``(C, H_i, W_i)``.
        crop_to_image: ``(K, 2, 3)``.
        size: view size.
        index: ``(K,)`` image of each view (default ``arange(K)``).
    Returns:
        ``(K, C, size, size)``.
    """
    index = torch.arange(crop_to_image.shape[0]) if index is None else index
    views = [resample(images[int(i)], a, size, antialias) for i, a in zip(index, crop_to_image,
                                                                          strict=True)]
    if not views:
        channels = images[0].shape[0] if len(images) else 1
        return crop_to_image.new_zeros(0, channels, size, size)
    return torch.stack(views)
