"""Soft rim landmarks: differentiable sub-pixel boundary points of a probability map.

The network predicts the cup opening as an area-coverage map ``p`` (the fraction of each
pixel inside the rim ellipse). Along a ray from a point inside the region, the integral of
``p`` is the distance to the boundary, exactly for a coverage map of a convex region and to
sub-pixel accuracy for a blurred one: that integral is the soft landmark, and its gradient
reaches every probability the ray crosses. Rays are cast in the frame normalised by the
region's second moments, so they are spread evenly along the boundary even for thin
ellipses (cups seen almost edge-on).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from cupnet.batchwise import matmul
from cupnet.ellipse import params_to_conic


def soft_moments(prob: Tensor, eps: float = 1e-6) -> tuple[Tensor, Tensor, Tensor]:
    """Mass, centroid and covariance of probability maps.

    Args:
        prob: ``(B, 1, H, W)`` in [0, 1].
    Returns:
        mass ``(B,)`` (pixels), centre ``(B, 2)`` pixels (u, v), covariance ``(B, 2, 2)`` px^2.
    """
    _, _, height, width = prob.shape
    u = torch.arange(width, dtype=prob.dtype, device=prob.device)
    v = torch.arange(height, dtype=prob.dtype, device=prob.device)
    # Products summed, not matmul or einsum: those take batch-size-dependent kernels, so a
    # map's moments (and every landmark after them) would round differently with the batch.
    rows, cols = prob[:, 0].sum(-1), prob[:, 0].sum(-2)  # (B, H), (B, W) marginals
    mass = rows.sum(-1)
    norm = mass + eps
    mu_u, mu_v = (cols * u).sum(-1) / norm, (rows * v).sum(-1) / norm
    var_u = (cols * u**2).sum(-1) / norm - mu_u**2
    var_v = (rows * v**2).sum(-1) / norm - mu_v**2
    cov_uv = ((prob[:, 0] * u).sum(-1) * v).sum(-1) / norm - mu_u * mu_v
    centre = torch.stack([mu_u, mu_v], -1)
    cov = torch.stack([torch.stack([var_u, cov_uv], -1), torch.stack([cov_uv, var_v], -1)], -2)
    return mass, centre, cov


def component_moments(prob: np.ndarray, labels: np.ndarray, count: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`soft_moments` of each labelled component of one map, all at once (the
    locator's blobs, on the CPU: a few sums over the labelled pixels, not a map each).

    Args:
        prob: ``(H, W)`` float64 probabilities.
        labels: ``(H, W)`` integer labels ``0 .. count - 1``, 0 the background (as
            ``cv2.connectedComponents`` gives them).
        count: number of labels, the background included.
    Returns:
        for components ``1 .. count - 1``: mass ``(n,)`` (the sum of ``prob`` over the
        component, px), pixels ``(n,)`` (its size), centre ``(n, 2)`` px (u, v), covariance
        ``(n, 2, 2)`` px^2, float64.
    """
    v, u = np.nonzero(labels)
    label = labels[v, u] - 1
    n = max(count - 1, 0)
    weight = prob[v, u]

    def total(values: np.ndarray | None) -> np.ndarray:
        return np.bincount(label, values, minlength=n)[:n].astype(np.float64)

    mass = total(weight)
    norm = mass + 1e-6  # as soft_moments: an empty map has its centre at 0
    mu_u, mu_v = total(weight * u) / norm, total(weight * v) / norm
    var_u = total(weight * u**2) / norm - mu_u**2
    var_v = total(weight * v**2) / norm - mu_v**2
    cov_uv = total(weight * u * v) / norm - mu_u * mu_v
    cov = np.stack([np.stack([var_u, cov_uv], -1), np.stack([cov_uv, var_v], -1)], -2)
    return mass, total(None), np.stack([mu_u, mu_v], -1), cov


def sqrtm_2x2(matrix: Tensor) -> Tensor:
    """Square root of symmetric positive-definite ``(..., 2, 2)`` matrices, closed form.

    ``sqrt(M) = (M + sqrt(det M) I) / sqrt(tr M + 2 sqrt(det M))``: smooth even where the
    eigenvalues coincide (a circle), unlike a gradient through ``eigh``.
    """
    root_det = torch.sqrt(torch.linalg.det(matrix))
    trace = matrix.diagonal(dim1=-2, dim2=-1).sum(-1)
    eye = torch.eye(2, dtype=matrix.dtype, device=matrix.device)
    return (matrix + root_det[..., None, None] * eye) / torch.sqrt(trace + 2 * root_det)[..., None,
                                                                                          None]


def ray_landmarks(prob: Tensor, n_rays: int = 64, n_samples: int = 128, extent: float = 1.6
                  ) -> tuple[Tensor, Tensor]:
    """Boundary landmarks of the region in each probability map, one per ray.

    Rays leave the soft centroid ``c`` along ``u_k = 2 S^(1/2) (cos t_k, sin t_k)`` (``S`` the
    region's covariance, so for a filled ellipse ``s = 1`` is its boundary); the landmark is
    ``c + r_k u_k`` with ``r_k = int_0^extent p(c + s u_k) ds`` (trapezoid rule, bilinear
    samples). Everything is differentiable w.r.t. ``p``, the rays' origin and directions
    included (through the moments). A ray's weight ``p_start (1 - p_end)`` is 1 when it
    starts inside the region and ends outside it, and falls towards 0 otherwise (a ray that
    never leaves the region, or a region too faint to start in).

    On the coverage map of a filled ellipse the landmarks recover it to about 0.05 px while
    ``b^2 / a >= 1`` px; a thinner region covers its tips' pixels only in part, so its
    semi-major axis comes out short (``a`` = 50 px: by 0.1 px at ``b`` = 7, 0.24 at 5, 0.7
    at 3, 1.7 at 2), whatever ``n_samples``. (CupNet's crops stretch the minor axis, and its
    rim stage places the landmarks it solves.) A region cut by the map's edge ends its rays
    there at full weight, landmarks on the edge, not on the region's boundary; weighting them
    down by the region's value past the edge was measured and not taken (docs/training.md,
    item 60: the shipped model's stages were tuned with these weights).

    Args:
        prob: ``(B, 1, H, W)`` coverage in [0, 1].
        n_rays: landmarks per map.
        n_samples: samples per ray.
        extent: how far rays go, in units of the moment ellipse (1 = its boundary).
    Returns:
        points ``(B, n_rays, 2)`` pixels of ``prob``, weights ``(B, n_rays)`` in [0, 1].
    """
    _, _, height, width = prob.shape
    _, centre, cov = soft_moments(prob)
    # Regularised so an empty or one-pixel region still gives finite, non-degenerate rays.
    root = 2 * sqrtm_2x2(cov + 0.25 * torch.eye(2, dtype=prob.dtype, device=prob.device))
    t = torch.arange(n_rays, dtype=prob.dtype, device=prob.device) * (2 * math.pi / n_rays)
    unit = torch.stack([torch.cos(t), torch.sin(t)], -1)  # (N, 2)
    direction = matmul(unit, root.transpose(-1, -2))  # (B, N, 2) pixels per unit s
    s = torch.linspace(0, extent, n_samples, dtype=prob.dtype, device=prob.device)
    samples = centre[:, None, None] + s[None, None, :, None] * direction[:, :, None]
    # grid_sample with align_corners=True: -1 and +1 are the centres of the edge pixels.
    scale = torch.tensor([2 / max(width - 1, 1), 2 / max(height - 1, 1)], dtype=prob.dtype,
                         device=prob.device)
    grid = samples * scale - 1
    profile = F.grid_sample(prob, grid, mode="bilinear", padding_mode="zeros",
                            align_corners=True)[:, 0]  # (B, N, S)
    step = extent / (n_samples - 1)
    radius = step * (profile.sum(-1) - 0.5 * (profile[..., 0] + profile[..., -1]))
    points = centre[:, None] + radius[..., None] * direction
    weights = profile[..., 0] * (1 - profile[..., -1])
    return points, weights


def ellipse_coverage(params: Tensor, height: int, width: int, supersample: int = 4) -> Tensor:
    """Area-coverage maps of filled ellipses (union over each item's ellipses).

    Args:
        params: ``(B, E, 5)`` ``(cx, cy, a, b, alpha_deg)`` pixels; rows with NaN are ignored.
        height, width: map size.
        supersample: sub-pixel samples per axis.
    Returns:
        ``(B, 1, height, width)`` in [0, 1].
    """
    dtype, device = params.dtype, params.device
    offsets = (torch.arange(supersample, dtype=dtype, device=device) + 0.5) / supersample - 0.5
    v = (torch.arange(height, dtype=dtype, device=device)[:, None] + offsets).reshape(-1)
    u = (torch.arange(width, dtype=dtype, device=device)[:, None] + offsets).reshape(-1)
    present = torch.isfinite(params).all(-1)  # (B, E)
    safe = torch.where(present[..., None], params,
                       torch.tensor([0.0, 0.0, 1.0, 1.0, 0.0], dtype=dtype, device=device))
    conic = params_to_conic(safe)[..., None]  # (B, E, 3, 3, 1), negative inside
    # Each sample row v meets the ellipse in one interval of u, the roots of the conic's
    # quadratic in u (NaN where it misses the row): two comparisons a sample, not a
    # quadratic form (a tenth of the time, the same samples inside).
    half = conic[:, :, 0, 1] * v + conic[:, :, 0, 2]  # (B, E, Hs)
    const = (conic[:, :, 1, 1] * v + 2 * conic[:, :, 1, 2]) * v + conic[:, :, 2, 2]
    root = torch.where(present[..., None], (half**2 - conic[:, :, 0, 0] * const).sqrt(),
                       math.nan)
    low = ((-half - root) / conic[:, :, 0, 0])[..., None]
    high = ((-half + root) / conic[:, :, 0, 0])[..., None]
    inside = ((u >= low) & (u <= high)).any(1)  # (B, Hs, Ws): the union of the ellipses
    # The counts of samples inside are exact in float32.
    return F.avg_pool2d(inside[:, None].float(), supersample).to(dtype)
