"""The first landmark sources of :meth:`CupNet.detect`, for a whole batch at once.

``detect`` follows each cup through its fallbacks, outline refinement and verification, with
the geometry on the CPU between network calls: accurate, and 5-10 images a second on a GPU.
:func:`batched_cups` keeps the part of it that runs with a fixed structure, every cup of a
batch at once on the model's device (a few sync points a stage, none per cup; the round
fields and locator blobs on the CPU's cores), for throughput on a GPU:

1. the locator with its retry and round field (:meth:`CupNet.rough_ellipses`), the blobs
   :meth:`CupNet.kept_blobs` keeps;
2. ``refine_passes`` refiner passes, each re-framed on the last pass's fit;
3. ``detect``'s landmark sources in its order (:meth:`CupNet.rim_sources`), each solved with
   the ML refinement on the cups still without a pose within ``max_theta_deg``: the fine
   rim stage from the refiner's fit, framed on the coarse stage's fit, the refiner's own
   landmarks, the thin-rim hypotheses; each cup keeps the pose ``detect`` would pick.

The metal's display is judged per image as ``detect`` judges it (``metal: auto``,
:func:`cupnet.polarity.metals_show_bright`). No outline refinement, verification, search or
later looks, so it is less accurate than ``detect`` (docs/benchmarks.md, `CupNet
throughput`); its grown-rim source made it no better (64 DRRs, session 30: theta MAE 3.48 ->
3.51 deg) and is left out.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from cupnet.geometry import Geometry
from cupnet.model import CupNet
from cupnet.polarity import metals_show_bright


class BatchedCups(NamedTuple):
    """The cups :func:`batched_cups` finds in ``B`` images, ``K`` in all.

    Attributes:
        cup_index: ``(K, 2)`` (image, locator slot) of each cup.
        pose: ``(K, 5)`` (theta_deg, phi_deg, k_mm, l_mm, h_mm), NaN where no source gave one.
        ellipse: ``(K, 5)`` (cx, cy, a, b, alpha_deg) original-image pixels.
        valid: ``(K,)`` bool, whether ``pose`` is a solved pose.
    """

    cup_index: Tensor
    pose: Tensor
    ellipse: Tensor
    valid: Tensor


@torch.inference_mode()
def batched_cups(model: CupNet, images: Tensor, geometry: Geometry, cup_diameter: Tensor
                 ) -> BatchedCups:
    """Cups of a batch of images, every stage on all of them at once (module docstring).

    Args:
        model: a CupNet in eval mode, on the images' device.
        images: ``(B, 1, H, W)`` float32 in [0, 1].
        geometry: fields ``(B,)`` or scalars, principal point in image pixels.
        cup_diameter: ``(B,)`` mm.
    Returns:
        :class:`BatchedCups`, on the images' device.
    """
    if images.ndim != 4 or len(images) == 0:
        raise ValueError(f"images must be (B, 1, H, W) with B >= 1, got {tuple(images.shape)}")
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
    for _ in range(cfg.refine_passes - 1):
        frames = model.frames(model.refiner_fit(
            *model.crop_landmarks(*model.segment_crops(images, frames, index)), frames))
    refiner_points, refiner_weights = model.crop_landmarks(
        *model.segment_crops(images, frames, index))

    def refiner(todo: Tensor) -> tuple[Tensor, Tensor]:
        return refiner_points[todo], refiner_weights[todo]

    sources = [refiner]
    if model.rim is not None:
        start = model.refiner_fit(refiner_points, refiner_weights, frames)
        sources = model.rim_sources(images, index, start, refiner)
    count = len(cup_index)
    pose = torch.full((count, 5), math.nan, dtype=torch.float64, device=images.device)
    ellipse = pose.clone()
    valid = torch.zeros(count, dtype=torch.bool, device=images.device)
    for source in sources:
        todo = (~(valid & model.in_theta_range(pose))).nonzero()[:, 0]
        if len(todo) == 0:
            break
        again = model.solve(*source(todo), geometry, cup_diameter, cup_index[todo],
                            len(images), refine=True)
        # As detect picks: a pose in range; else the first pose found; else the refiner's
        # failure (its ellipse is the one its mask shows).
        unsolved = ~valid[todo]
        took = again.valid & (model.in_theta_range(again.pose) | unsolved)
        if source is refiner:
            took |= unsolved
        rows = todo[took]
        pose[rows], ellipse[rows], valid[rows] = (again.pose[took], again.ellipse[took],
                                                  again.valid[took])
    return BatchedCups(cup_index, pose, ellipse, valid)
