"""The first landmark sources of :meth:`CupNet.detect`, for a whole batch at once.

``detect`` follows each cup through its fallbacks, outline refinement and verification, with
the geometry on the CPU between network calls: accurate, and 5-10 images a second on a GPU.
:func:`batched_cups` keeps the part of it that runs with a fixed structure, every cup of a
batch at once on the model's device (a few sync points a stage, none per cup; the round
fields and locator blobs on the CPU's cores), for throughput on a GPU:

1. the locator with its retry and round field (:meth:`CupNet.rough_ellipses`), the blobs
   :meth:`CupNet.kept_blobs` keeps;
2. ``refine_passes`` refiner passes, each re-framed on the last pass's fit
   (:meth:`CupNet.refiner_passes`);
3. ``detect``'s landmark sources in its order (:meth:`CupNet.rim_sources`), each solved with
   the ML refinement on the cups still without a pose within ``max_theta_deg``: the fine
   rim stage from the refiner's fit, framed on the coarse stage's fit, the refiner's own
   landmarks, the thin-rim hypotheses; each cup keeps the pose ``detect`` would pick.

With ``outline=True``, 4. ``detect``'s outline stage (:func:`outlined`): each solved pose
refined with the dome's outline, each ambiguous pair ordered by the rim network's doubt.

The metal's display is judged per image as ``detect`` judges it (``metal: auto``,
:func:`cupnet.polarity.metals_show_bright`). No verification, search, later looks, cut of a
narrow round field to its square (the batch keeps one image size), enlargement of small
images (``enlarge_below``) or reduction of large ones (``reduce_above``), or non-local
means for noisy images (``denoise_above``, on the CPU at 0.07-0.25 s an image), so it is
less accurate than ``detect`` (docs/benchmarks.md, `CupNet throughput`); ``detect``'s
grown-rim source made it no better (64 DRRs, session 30: theta MAE 3.48 -> 3.51 deg) and is
left out.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from cupnet.geometry import Geometry
from cupnet.model import (
    CupNet,
    check_usable_geometry,
    checked_pixels,
    cup_diameters,
    evaluating,
    geometry_rows,
    rim_second_poses,
    takes_pick,
)
from cupnet.polarity import metals_show_bright
from cupnet.pose import PoseSolution, ellipse_of_pose


class BatchedCups(NamedTuple):
    """The cups :func:`batched_cups` finds in ``B`` images, ``K`` in all.

    Attributes:
        cup_index: ``(K, 2)`` (image, locator slot) of each cup.
        pose: ``(K, 5)`` (theta_deg, phi_deg, k_mm, l_mm, h_mm), NaN where no source gave one.
        ellipse: ``(K, 5)`` (cx, cy, a, b, alpha_deg) original-image pixels.
        valid: ``(K,)`` bool, whether ``pose`` is a solved pose.
        alt_pose: ``(K, 5)`` the second pose of an ambiguous cup (the same rim from the
            other side; of the landmarks' fit, or of ``pose``'s rim), NaN for the others.
    """

    cup_index: Tensor
    pose: Tensor
    ellipse: Tensor
    valid: Tensor
    alt_pose: Tensor


@torch.inference_mode()
def batched_cups(model: CupNet, images: Tensor, geometry: Geometry, cup_diameter: Tensor,
                 outline: bool = False) -> BatchedCups:
    """Cups of a batch of images, every stage on all of them at once (module docstring).

    Args:
        model: a CupNet on the images' device (run in eval mode, its mode restored after).
        images: ``(B, 1, H, W)`` floats in [0, 1] (cast to the model's dtype).
        geometry: fields ``(B,)`` or scalars, principal point in image pixels.
        cup_diameter: ``(B,)`` or scalar, mm.
        outline: refine the solved poses with the dome's outline and order each ambiguous
            pair by the rim network's doubt, as ``detect`` does (:func:`outlined`).
    Returns:
        :class:`BatchedCups`, on the images' device.
    Raises:
        ValueError: images of another shape, or not in [0, 1], or NaN
            (:func:`cupnet.model.checked_pixels`: a NaN image had given no cup), geometry or
            diameters of other than one value or one per image or that cannot be used
            (:func:`cupnet.model.check_usable_geometry`), as ``detect`` names them.

    With the networks in PyTorch, an image alone and the same image among others round
    the U-Nets' float32 convolutions differently (the batch's size decides their kernels):
    most poses move by 1e-5 to 1e-3, a nearly edge-on cup's ``h`` by a millimetre or so.
    """
    if (not isinstance(images, Tensor) or images.ndim != 4 or images.shape[1] != 1
            or len(images) == 0):
        raise ValueError("images must be a (B, 1, H, W) tensor with B >= 1, got "
                         f"{tuple(images.shape) if isinstance(images, Tensor) else type(images)}")
    checked_pixels(images)
    cup_diameter = cup_diameters(cup_diameter, len(images))
    check_usable_geometry(geometry, cup_diameter)  # here, before any network runs
    # In train mode the BatchNorms would take the batch's statistics, and keep them.
    with evaluating(model):
        return _batched_cups(model, images.to(model.dtype), geometry, cup_diameter, outline)


def _batched_cups(model: CupNet, images: Tensor, geometry: Geometry, cup_diameter: Tensor,
                  outline: bool) -> BatchedCups:
    """:func:`batched_cups` of checked inputs, ``cup_diameter`` ``(B,)`` float64."""
    cfg = model.config
    if cfg.metal == "bright":
        images = 1 - images
    rough, scores = model.rough_ellipses(list(images))
    if cfg.metal == "auto":  # as detect judges each image, after the locator
        bright = metals_show_bright(images, rough)[0]
        images = torch.where(bright[:, None, None, None], 1 - images, images)
    cup_index = model.kept_blobs(rough, scores).nonzero().to(images.device)
    index = cup_index[:, 0]
    frames = model.frames(model.first_pass_ellipses(
        rough.to(images.device)[index, cup_index[:, 1]]))
    # The stages take the batch as one tensor, not a list: off the CPU its crops and strips
    # are then sampled all at once (on the CPU they loop over views either way).
    frames, *crops = model.refiner_passes(images, frames, index)
    refiner_points, refiner_weights = model.crop_landmarks(*crops)

    def refiner(todo: Tensor) -> tuple[Tensor, Tensor]:
        return refiner_points[todo], refiner_weights[todo]

    sources = [refiner]
    if model.rim is not None:
        start = model.refiner_fit(refiner_points, refiner_weights, frames)
        sources = model.rim_sources(images, index, start, refiner)
    picks = _Picks.empty(len(cup_index), images.device)
    for source in sources:
        todo = (~(picks.valid & model.in_theta_range(picks.pose))).nonzero()[:, 0]
        if len(todo) == 0:
            break
        points, weights = source(todo)
        again = model.solve(points, weights, geometry, cup_diameter, cup_index[todo],
                            len(images), refine=True)
        took = takes_pick(again.valid, again.valid & model.in_theta_range(again.pose),
                          picks.valid[todo], source is refiner)
        picks.take(todo[took], again, took, points[took], weights[took])
    if outline and model.rim is not None and cfg.outline_passes:
        outlined(model, images, index, picks, geometry, cup_diameter)
    # As detect (cupnet.model.with_second_poses): a solved cup whose pose's rim has a second
    # pose in range is ambiguous, with that pose.
    single = (picks.valid & ~torch.isfinite(picks.alt_pose).all(-1)).nonzero()[:, 0]
    if len(single):
        other, in_range = rim_second_poses(picks.pose[single], index[single], geometry,
                                           cup_diameter)
        picks.alt_pose[single[in_range]] = other[in_range].to(picks.alt_pose)
    return BatchedCups(cup_index, picks.pose, picks.ellipse, picks.valid, picks.alt_pose)


class _Picks:
    """Each cup's pick of :func:`batched_cups` so far: pose, ellipse, validity, and what
    :func:`outlined` refines from (the landmarks, weights and residual it was solved from,
    whether ambiguous, the second pose)."""

    def __init__(self, pose: Tensor, valid: Tensor) -> None:
        self.pose, self.ellipse, self.alt_pose = pose, pose.clone(), pose.clone()
        self.residual = pose[:, 0].clone()
        self.valid, self.ambiguous = valid, valid.clone()
        self.landmarks: list[tuple[Tensor, Tensor, Tensor]] = []  # (rows, points, weights)

    @classmethod
    def empty(cls, count: int, device: torch.device) -> _Picks:
        return cls(torch.full((count, 5), math.nan, dtype=torch.float64, device=device),
                   torch.zeros(count, dtype=torch.bool, device=device))

    def take(self, rows: Tensor, solution: PoseSolution, took: Tensor, points: Tensor,
             weights: Tensor) -> None:
        """The cups ``rows`` take the ``took`` rows of ``solution``, solved from ``points``
        ``(k, n, 2)`` px and ``weights`` ``(k, n)`` (already those rows)."""
        self.pose[rows], self.ellipse[rows] = solution.pose[took], solution.ellipse[took]
        self.valid[rows], self.ambiguous[rows] = solution.valid[took], solution.ambiguous[took]
        self.alt_pose[rows] = solution.alt_pose[took]
        self.residual[rows] = solution.residual_px[took]
        self.landmarks.append((rows, points, weights))

    def padded_landmarks(self) -> tuple[Tensor, Tensor]:
        """Each cup's landmarks ``(K, N, 2)`` px and weights ``(K, N)``, the sources' sets
        zero-padded to the largest (as ``detect`` pads them), the last taken winning."""
        width = max((points.shape[1] for _, points, _ in self.landmarks), default=0)
        points = self.pose.new_zeros(len(self.pose), width, 2)
        weights = self.pose.new_zeros(len(self.pose), width)
        for rows, found, found_weights in self.landmarks:
            points[rows, :found.shape[1]] = found.to(points)
            weights[rows, :found.shape[1]] = found_weights.to(weights)
        return points, weights


def outlined(model: CupNet, images: Tensor, index: Tensor, picks: _Picks, geometry: Geometry,
             cup_diameter: Tensor) -> None:
    """``detect``'s outline stage on every solved cup at once, in place in ``picks``: each
    pose, and an ambiguous cup's second pose, refined with the dome's outline
    (:meth:`CupNet.outline_refined`, back at its start where the network doubts it more:
    :meth:`CupNet.unless_more_doubted`); with ``ambiguous_by_doubt``, each pair ordered by
    :meth:`CupNet.pose_doubt`; each solved cup's ellipse the rim of its refined pose.

    Args:
        images: ``(B, 1, H, W)``; index: ``(K,)`` image of each cup.
        geometry: fields ``(B,)`` or scalars; cup_diameter: ``(B,)`` mm.
    """
    batch = len(images)
    rows = geometry_rows(geometry, batch).to(images.device)
    diameter = torch.as_tensor(cup_diameter, dtype=torch.float64,
                               device=images.device).expand(batch)
    solved = picks.valid.nonzero()[:, 0]
    if len(solved) == 0:
        return
    paired = solved[picks.ambiguous[solved]]
    cups = torch.cat([solved, paired])
    points, weights = picks.padded_landmarks()
    start = torch.cat([picks.pose[solved], picks.alt_pose[paired]])
    image = index[cups]
    refined, doubt = model.unless_more_doubted(
        images, image, start,
        model.outline_refined(images, image, start, points[cups], weights[cups],
                              picks.residual[cups], rows[image], diameter[image]),
        rows[image], diameter[image])
    picks.pose[solved], picks.alt_pose[paired] = refined[:len(solved)], refined[len(solved):]
    finite = torch.isfinite(picks.alt_pose[paired]).all(-1)
    pairs = paired[finite]
    if model.config.ambiguous_by_doubt and len(pairs):
        if doubt is None:
            both = torch.stack([picks.pose[pairs], picks.alt_pose[pairs]], 1).flatten(0, 1)
            image = index[pairs].repeat_interleave(2)
            pair_doubt = model.pose_doubt(images, image, both, rows[image],
                                          diameter[image]).reshape(-1, 2, 2)
        else:  # as kept: the solved cups' poses, then their pairs' second poses
            pair_doubt = torch.stack([doubt[:len(solved)][picks.ambiguous[solved]],
                                      doubt[len(solved):]], 1)[finite]
        swap = pairs[pair_doubt.sum(-1).diff(dim=-1)[:, 0] < 0]
        picks.pose[swap], picks.alt_pose[swap] = picks.alt_pose[swap], picks.pose[swap]
    picks.ellipse[solved] = ellipse_of_pose(picks.pose[solved], diameter[index[solved]],
                                            Geometry.from_rows(rows[index[solved]]))
