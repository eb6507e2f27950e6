"""Rim stage: sub-pixel rim landmarks from strips sampled across an ellipse estimate.

The refiner U-Net sees each cup through a 128 px crop, several image pixels per crop pixel
for a large cup, so its landmarks are a few pixels off. The rim stage works at full
resolution on a narrow band instead: ``n`` outward normals of the current ellipse (at equal
parameter steps), each sampled at ``S`` offsets ``step`` image pixels apart, stacked into a strip
``(S, n)`` (rows: offset along the normal, columns: position around the rim, circular).
:class:`RimNet`, a small dilated CNN, gives each column a distribution over offsets (its
expectation places the landmark, differentiably) and a scale ``sigma`` (its landmark's
expected error along the normal, the weight of the ellipse fit being ``1 / sigma^2``). The rim
edge of a metal shell is not a symmetric step (the path through metal grows inwards from
the outer rim over several pixels, and a femoral head can hide part of the rim), so a
learned edge locator beats a gradient peak; the network learns where the rim lies in its
profile and when it cannot be seen.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cupnet.batchwise import hypot, matmul, quadratic_form, weighted_scatter
from cupnet.crops import lattice_bilinear
from cupnet.ellipse import ellipse_points, params_to_conic
from cupnet.parallel import map_on_cores

# Range of log(sigma / px): a landmark claims a precision of 0.05 px at best, and at worst
# 55 px, more than any strip reaches (its weight then all but vanishes).
_LOG_SIGMA_RANGE = (-3.0, 4.0)


def rim_frame(ellipse: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Points at ``n`` equally spaced parameters ``t`` around ellipses, and outward normals.

    Equal parameter steps, not equal arc length: on a thin (nearly edge-on) ellipse they
    crowd towards the two tips, where the only evidence of the major axis, and so of the
    cup's distance, lies.

    Args:
        ellipse: ``(K, 5)`` (cx, cy, a, b, alpha_deg), image pixels.
        n: points per ellipse.
    Returns:
        points ``(K, n, 2)`` pixels, normals ``(K, n, 2)`` unit vectors; point ``j`` is
        :func:`cupnet.ellipse.ellipse_points` at ``t = 2 pi j / n``.
    """
    t = torch.arange(n, dtype=ellipse.dtype, device=ellipse.device) * (2 * math.pi / n)
    points = ellipse_points(ellipse, t)
    _, _, a, b, alpha = (x[:, None] for x in ellipse.unbind(-1))
    ang = torch.deg2rad(alpha)
    nx, ny = b * torch.cos(t), a * torch.sin(t)  # the gradient of (x/a)^2 + (y/b)^2, scaled
    norm = hypot(nx, ny)
    nx, ny = nx / norm, ny / norm
    normals = torch.stack([nx * torch.cos(ang) - ny * torch.sin(ang),
                           nx * torch.sin(ang) + ny * torch.cos(ang)], -1)
    return points, normals


def normal_crossings(points: Tensor, normals: Tensor, ellipse: Tensor) -> Tensor:
    """Offsets along each normal line ``p + s n`` where it leaves another ellipse.

    The training target of a strip column: the larger root of the conic along the line (the
    rim on the column's side), or, for a line that misses the ellipse, its nearest approach
    (the root of the derivative), which continues the crossing smoothly.

    Args:
        points, normals: ``(K, n, 2)`` a strip frame, pixels; ellipse: ``(K, 5)`` the rim.
    Returns:
        ``(K, n)`` offsets ``s``, pixels.
    """
    conic = params_to_conic(ellipse.to(points))
    hom = torch.cat([points, torch.ones_like(points[..., :1])], -1)
    direction = torch.cat([normals, torch.zeros_like(normals[..., :1])], -1)
    cd = matmul(direction, conic.transpose(-1, -2))
    quad = (direction * cd).sum(-1)  # q(s) = quad s^2 + 2 half s + const
    half = (hom * cd).sum(-1)
    const = quadratic_form(hom, conic)
    disc = half**2 - quad * const
    # The sign of a unit-norm conic is arbitrary: the larger root is where q turns from
    # inside to outside, whichever the sign.
    root = torch.sqrt(disc.clamp_min(0)) / quad.abs()
    return torch.where(disc >= 0, -half / quad + root, -half / quad)


def ellipse_step_basis(ellipse: Tensor, normals: Tensor) -> Tensor:
    """How far each strip column's edge moves along its normal per unit change of each
    ellipse parameter, to first order.

    Args:
        ellipse: ``(K, 5)`` (cx, cy, a, b px, alpha deg); normals: ``(K, n, 2)`` its
            :func:`rim_frame` normals (column ``j`` at ``t = 2 pi j / n``; other normals,
            a sphere outline's say, give a wrong basis).
    Returns:
        ``(K, n, 5)`` pixels per (px, px, px, px, deg).
    """
    n = normals.shape[1]
    t = torch.arange(n, dtype=ellipse.dtype, device=ellipse.device) * (2 * math.pi / n)
    _, _, a, b, alpha = (x[:, None] for x in ellipse.unbind(-1))
    ang = torch.deg2rad(alpha)
    cos_a, sin_a = torch.cos(ang), torch.sin(ang)
    nu, nv = normals.unbind(-1)
    along_major = nu * cos_a + nv * sin_a  # the normal in the ellipse's own axes
    along_minor = -nu * sin_a + nv * cos_a
    cos_t, sin_t = torch.cos(t), torch.sin(t)
    # d point / d alpha is the point's offset from the centre turned by 90 deg.
    turn = (a * cos_t * along_minor - b * sin_t * along_major) * (math.pi / 180)
    return torch.stack([nu, nv, cos_t * along_major, sin_t * along_minor, turn], -1)


def settled_offsets(offset: Tensor, sigma: Tensor, ellipse: Tensor, normals: Tensor,
                    iterations: int = 2) -> Tensor:
    """Strip landmarks' offsets ``(K, n)`` px less the ellipse step that best explains them.

    A pose a few pixels off its rim (a coarse grid's) has large offsets that one fit of its
    landmarks would take out; what is left says whether an ellipse lies there at all. The
    step is the linearised weighted least-squares fit of the five ellipse parameters
    (:func:`ellipse_step_basis`): ``iterations`` fits, the first weighted ``1 / sigma^2``,
    each later one reweighted for Laplace errors (``1 / (sigma (|r| + sigma))``, ``r`` the
    last fit's residual) so that a few columns on another edge pull it less.

    Args:
        offset, sigma: ``(K, n)`` px, :class:`RimLandmarks`' fields; ellipse: ``(K, 5)``
            (cx, cy, a, b px, alpha deg) the strips' ellipse; normals: ``(K, n, 2)`` its
            :func:`rim_frame` normals.
        iterations: at least 1.
    Returns:
        ``(K, n)`` px.
    """
    if iterations < 1:
        raise ValueError(f"settled_offsets needs at least one fit, got iterations={iterations}")
    basis = ellipse_step_basis(ellipse.to(offset), normals.to(offset))
    # A circle's orientation moves no edge (its alpha column is zero): a ridge of a millionth
    # of the matrix's scale keeps the system solvable there without biasing the rest.
    eye = torch.eye(5, dtype=offset.dtype, device=offset.device)
    residual = torch.zeros_like(offset)
    for _ in range(iterations):
        weights = 1 / (sigma * (residual.abs() + sigma))  # 1 / sigma^2 at first
        normal = weighted_scatter(weights, basis, basis)
        ridge = 1e-6 * normal.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None]
        step = torch.linalg.solve(normal + ridge * eye,
                                  (basis * (weights * offset)[..., None]).sum(-2))
        residual = offset - (basis * step[:, None]).sum(-1)
    return residual


def laplace_nll(offset: Tensor, sigma: Tensor) -> Tensor:
    """Negative log-likelihood, less a constant, of Laplace errors of scale ``sigma`` px at
    ``offset`` px, elementwise: the rim network's training loss and its doubt of a pose."""
    return offset.abs() / sigma + sigma.log()


def strip_offsets(samples: int, step: float, dtype: torch.dtype = torch.float64,
                  device: torch.device | None = None) -> Tensor:
    """``(S,)`` offsets (image pixels, outward positive) of a strip's rows, centred on 0."""
    return (torch.arange(samples, dtype=dtype, device=device) - (samples - 1) / 2) * step


def scaled_offsets(samples: int, ellipse: Tensor, reach: float) -> Tensor:
    """``(K, S)`` offsets of strips reaching ``reach`` semi-major axes either side of each
    ellipse ``(K, 5)``: the coarse rim stage sees every cup at the same relative scale, as the
    refiner's crops do, so it can correct an error proportional to the cup's size."""
    unit = strip_offsets(samples, 2 / (samples - 1), ellipse.dtype, ellipse.device)
    return reach * ellipse[:, 2:3] * unit


def thin_rim_starts(ellipse: Tensor, angles: int, ratio: float) -> Tensor:
    """``(K, A, 5)`` thin ellipses sharing each ellipse's ``(K, 5)`` centre and semi-major
    axis, semi-minor axis ``ratio a``, at ``A = angles`` orientations evenly spread over 180
    degrees.

    Where a nearly edge-on cup holds a femoral head, cup and head show as one round disc, which
    a segmentation takes for the opening; the rim is a thin ellipse along that disc's diameter,
    at an orientation the disc does not show. These are the starts from which the rim stage
    looks for it (:meth:`cupnet.model.CupNet.thin_rim_landmarks`).
    """
    count = ellipse.shape[0]
    turn = torch.arange(angles, dtype=ellipse.dtype, device=ellipse.device) * (180.0 / angles)
    major = ellipse[:, None, 2:3].expand(count, angles, 1)
    return torch.cat([ellipse[:, None, :2].expand(count, angles, 2), major, ratio * major,
                      turn[None, :, None].expand(count, angles, 1)], -1)


def sample_strips(images: Tensor | list[Tensor], index: Tensor, points: Tensor, normals: Tensor,
                  offsets: Tensor) -> Tensor:
    """Bilinear samples of each image along each normal: the strips.

    Args:
        images: ``(B, 1, H, W)`` or a list of ``(1, H_i, W_i)``.
        index: ``(K,)`` image of each strip.
        points: ``(K, n, 2)`` pixels; normals: ``(K, n, 2)``; offsets: ``(S,)`` pixels, or
            ``(K, S)``, each cup's own.
    Returns:
        ``(K, 1, S, n)`` in the images' dtype (border values outside an image; the points'
        dtype for ``K = 0``). Off the CPU, strips of a ``(B, 1, H, W)`` tensor are sampled
        all at once (:func:`cupnet.crops.lattice_bilinear`, the same samples to float
        rounding): one ``grid_sample`` a strip is bound by kernel launches there.
    """
    offsets = offsets.expand(points.shape[0], -1)
    grid = points[:, None] + offsets[:, :, None, None] * normals[:, None]  # (K, S, n, 2)
    if isinstance(images, Tensor) and images.device.type != "cpu" and len(points):
        count, device = len(points), images.device
        size = torch.tensor(images.shape[-1:-3:-1], device=device)  # (W, H)
        samples = lattice_bilinear(
            images, index.to(device), grid.flatten(1, 2).to(device, images.dtype),
            torch.zeros(count, 2, dtype=torch.long, device=device),
            torch.ones(count, dtype=torch.long, device=device), size.expand(count, 2),
            border=True)
        return samples.reshape(count, images.shape[1], *grid.shape[1:3])
    strips = []
    for k in range(points.shape[0]):
        image = images[int(index[k])]
        height, width = image.shape[-2:]
        # grid_sample with align_corners=True: -1 and +1 are the centres of the edge pixels.
        scale = grid.new_tensor([2 / max(width - 1, 1), 2 / max(height - 1, 1)])
        strips.append(F.grid_sample(image[None], (grid[k:k + 1] * scale - 1).to(image.dtype),
                                    mode="bilinear", padding_mode="border",
                                    align_corners=True)[0])
    if not strips:
        return points.new_zeros(0, 1, offsets.shape[0], points.shape[1])
    return torch.stack(strips)


class _StripConv(nn.Module):
    """3x3 convolution dilated by ``(along the normal, around the rim)``, padded circularly
    around the rim and by replication along the normal, then BatchNorm and ReLU."""

    def __init__(self, channels_in: int, channels_out: int, dilation: tuple[int, int]) -> None:
        super().__init__()
        self.pad_s, self.pad_n = dilation
        self.conv = nn.Conv2d(channels_in, channels_out, 3, dilation=dilation, bias=False)
        self.norm = nn.BatchNorm2d(channels_out)

    def forward(self, x: Tensor) -> Tensor:
        x = F.pad(x, (self.pad_n, self.pad_n, 0, 0), mode="circular")
        x = F.pad(x, (0, 0, self.pad_s, self.pad_s), mode="replicate")
        return F.relu(self.norm(self.conv(x)))


# The strips already run by each network within a memoised_strips() block: the same strip
# (same values) gives the same output, so it is run once.
_STRIP_MEMO: ContextVar[dict[tuple, tuple[Tensor, Tensor]] | None] = ContextVar(
    "rim_strip_memo", default=None)


@contextmanager
def memoised_strips() -> Iterator[None]:
    """Within the block, a :class:`RimNet` on a CPU without gradients runs each distinct
    strip once and reuses its output when the same strip comes again.

    :meth:`cupnet.model.CupNet.detect` re-evaluates about 12 % of its strips (a pose's doubt
    taken again by a later stage, a thin-rim hypothesis ranked twice); the outputs are the
    ones the network gives, so detection stays bit-identical. Per thread (a context
    variable), so concurrent detect calls keep their own.
    """
    token = _STRIP_MEMO.set({})
    try:
        yield
    finally:
        _STRIP_MEMO.reset(token)


def strips_one_by_one(run: Callable[[Tensor], tuple[Tensor, Tensor]], strips: Tensor,
                      owner: object) -> tuple[Tensor, Tensor]:
    """A rim network's ``run`` (strips ``(K, 1, S, n)`` -> logits ``(K, S, n)``, ``log sigma``
    ``(K, n)``) on CPU strips one at a time: one strip's activations stay in cache, a batch's
    do not (12 strips of 64 x 128: 43 ms one by one, 89 ms as a batch, on 2 cores); with
    several torch threads, one strip on each core (:mod:`cupnet.parallel`); within a
    :func:`memoised_strips` block without gradients, each distinct strip of ``owner`` (the
    network) once.
    """
    parts = strips.split(1)
    memo = _STRIP_MEMO.get()
    if memo is None or torch.is_grad_enabled():
        outputs = map_on_cores(run, parts)
    else:
        keys = [(id(owner), tuple(part.shape), hashlib.blake2b(
            part.numpy().tobytes(), digest_size=16).digest()) for part in parts]
        new = {key: part for key, part in zip(keys, parts, strict=True) if key not in memo}
        memo.update(zip(new, map_on_cores(run, list(new.values())), strict=True))
        outputs = [memo[key] for key in keys]
    logits, log_sigma = zip(*outputs, strict=True)
    return torch.cat(logits), torch.cat(log_sigma)


class RimNet(nn.Module):
    """Strip ``(K, 1, S, n)`` -> offset logits ``(K, S, n)`` and ``log sigma`` ``(K, n)``.

    Dilations along the normal grow to cover the whole strip (receptive field ``2 sum d + 1``
    rows); around the rim they grow more slowly, so a column sees its neighbours' edges (a
    rim is smooth) without averaging across the ellipse.
    """

    def __init__(self, channels: int = 24,
                 dilations: tuple[tuple[int, int], ...] = ((1, 1), (2, 1), (4, 2), (8, 2),
                                                           (16, 4), (1, 1))) -> None:
        super().__init__()
        widths = [1] + [channels] * len(dilations)
        self.body = nn.Sequential(*(_StripConv(cin, cout, d) for cin, cout, d
                                    in zip(widths[:-1], widths[1:], dilations, strict=True)))
        self.offset_head = nn.Conv2d(channels, 1, 1)
        self.sigma_head = nn.Conv1d(channels + 1, 1, 1)

    @property
    def columns_seen(self) -> int:
        """How many columns either side of its own a column's output sees (around the rim)."""
        return sum(layer.pad_n for layer in self.body)

    def forward(self, strips: Tensor) -> tuple[Tensor, Tensor]:
        if self.training or strips.device.type != "cpu" or strips.shape[0] == 0:
            return self.forward_batch(strips)  # training keeps the batch (BatchNorm statistics)
        return strips_one_by_one(self.forward_batch, strips, self)

    def forward_batch(self, strips: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`forward` on the whole batch at once."""
        # Per-strip standardisation: exposure, windowing and polarity-free scale.
        mean = strips.mean((-2, -1), keepdim=True)
        std = strips.std((-2, -1), keepdim=True)
        features = self.body((strips - mean) / (std + 1e-3))
        logits = self.offset_head(features)[:, 0]  # (K, S, n)
        prob = torch.softmax(logits, 1)
        # Features where the column puts its landmark, and how peaked it is, give sigma.
        at_landmark = (features * prob[:, None]).sum(2)  # (K, C, n)
        peak = prob.max(1).values[:, None]  # (K, 1, n)
        log_sigma = self.sigma_head(torch.cat([at_landmark, peak], 1))[:, 0]
        return logits, log_sigma.clamp(*_LOG_SIGMA_RANGE)


class RimLandmarks(NamedTuple):
    """Output of the rim stage for ``K`` cups of ``n`` columns (float64).

    Attributes:
        landmarks: ``(K, n, 2)`` image pixels, ``points + offset * normals``.
        weights: ``(K, n)`` fit weights ``1 / sigma^2``, normalised to mean 1 per cup.
        sigma: ``(K, n)`` pixels, each landmark's predicted error along its normal.
        offset: ``(K, n)`` pixels along the normal.
        points, normals: ``(K, n, 2)`` the strips' frame.
        reach: ``(K, 1)`` pixels, how far each cup's strips reach either side of its frame.
    """

    landmarks: Tensor
    weights: Tensor
    sigma: Tensor
    offset: Tensor
    points: Tensor
    normals: Tensor
    reach: Tensor


def strip_landmarks(logits: Tensor, log_sigma: Tensor, points: Tensor, normals: Tensor,
                    offsets: Tensor) -> RimLandmarks:
    """Landmarks at each column's expected offset, and their fit weights.

    Args:
        logits: ``(K, S, n)``; log_sigma: ``(K, n)`` log pixels.
        points, normals: ``(K, n, 2)`` the strips' frame; offsets: ``(S,)`` or ``(K, S)``
            pixels.
    """
    prob = torch.softmax(logits.double(), 1)
    offsets = offsets.to(prob).expand(prob.shape[0], -1)  # (K, S)
    offset = (prob * offsets[..., None]).sum(1)  # (K, n)
    points, normals = points.double(), normals.double()
    sigma = log_sigma.double().exp()
    weights = sigma.pow(-2)
    return RimLandmarks(points + offset[..., None] * normals,
                        weights / weights.mean(-1, keepdim=True), sigma, offset, points, normals,
                        offsets.abs().amax(-1, keepdim=True))
