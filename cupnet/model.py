"""CupNet: image + geometry -> cup poses, as one differentiable ``nn.Module``.

Two stages, both small segmentation-models-pytorch U-Nets predicting the cup opening (the
filled rim ellipse) as an area-coverage map:

1. the *locator* sees the whole image letterboxed to ``locator_size`` pixels; connected
   components of its map give 0, 1 or 2 cups and a rough ellipse for each;
2. the *refiner* segments a square crop around each cup, framed so the rim's major axis
   spans ``crop_fill`` of the ``crop_size`` crop (a second pass re-frames the crop on the
   first pass's ellipse). Soft landmarks (:func:`cupnet.landmarks.ray_landmarks`) are mapped
   back to original-image pixels through the crop's exact affine;
3. the optional *rim* stage (:mod:`cupnet.rim`, ``rim_passes > 0``) samples full-resolution
   strips across the refiner's ellipse and moves each landmark onto the rim with a learned,
   differentiable edge locator, weighting it by its predicted precision. An optional
   *coarse* rim stage (``coarse_rim_passes > 0``), its strips reaching a fixed fraction of
   each cup's size, re-frames the fine stage where the refiner's ellipse was too far off for
   the fine strips to reach the rim (a femoral head's outline taken for a thin rim).

The weighted ellipse fit and the pose solver (:func:`cupnet.pose.solve_pose`) then give the
pose, so a pose loss backpropagates into the last stage's network.

Images may have any size; every resampling is an exactly known affine (:mod:`cupnet.crops`).
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import segmentation_models_pytorch as smp
import torch
from kornia.geometry.transform import warp_affine
from torch import Tensor, nn
from torch.nn.utils.rnn import pad_sequence

from cupnet.batchwise import atan2
from cupnet.config import BLURRED_WITHOUT_BLUR_RIM, TARGET_ACCURACY, CupNetConfig
from cupnet.crops import (
    ellipse_crop_affine,
    enlargement,
    frame_ellipse,
    letterbox_affine,
    reduction,
    resample_batch,
    rescaled_pixels,
    resized,
    square_windows,
    to_image,
)
from cupnet.denoise import denoised, noise_above
from cupnet.detection import (
    CupDetection,
    distinct_cups,
    found_cup_status,
    later_look_cups,
    moved,
    same_place,
    unresized,
    wants_another_look,
    without_failed_pieces,
)
from cupnet.ellipse import fit_ellipse
from cupnet.errors import whole_reason
from cupnet.field import content_crop, crop_of_field, outside_field, round_field
from cupnet.geometry import Geometry, pose_to_degrees, pose_to_radians
from cupnet.landmarks import component_moments, ray_landmarks
from cupnet.outline import outline_distances, over_dome, sphere_outline
from cupnet.parallel import map_on_cores
from cupnet.polarity import REPORT_MARGIN, metal_shows_bright
from cupnet.pose import (
    PoseSolution,
    canonical_pose,
    check_geometry_batch,
    ellipse_of_pose,
    geometry_problems,
    other_circle_pose,
    refine_pose_with_outline,
    rim_residual,
    solve_pose,
)
from cupnet.rim import (
    RimLandmarks,
    RimNet,
    laplace_nll,
    memoised_strips,
    rim_frame,
    sample_strips,
    scaled_offsets,
    settled_offsets,
    strip_landmarks,
    strip_offsets,
    thin_rim_starts,
)
from cupnet.rod import without_rod

ASSETS = Path(__file__).resolve().parent / "assets"
DEFAULT_CHECKPOINT = ASSETS / "cupnet_default.safetensors"
# The shortest image side :meth:`CupNet.detect` is trusted on: on 30 DRRs a side at 512 / 384
# / 256 / 192 / 128 px the shipped model (enlarging those under 496 px to 512) has an
# anteversion MAE of 0.94 / 1.10 / 2.26 / 4.87 / 5.94 deg and finds 100 / 100 / 97 / 93 / 83 %
# of the cups (docs/benchmarks.md, `CupNet on small images`).
MIN_IMAGE_SIDE = 256


class RimAlternative(NamedTuple):
    """One of the fine rim stage's other starts (:meth:`CupNet.rim_alternatives`).

    Attributes:
        landmarks: ``(images, index, start) -> RimLandmarks``, as :meth:`CupNet.rim_landmarks`.
        gate: the mean ``log sigma`` of the first landmarks above which
            :meth:`CupNet.trusted_rim_landmarks` tries it (None: only as one of
            :meth:`CupNet.detect`'s later landmark sources) ...
        margin: ... replacing them where its mean ``log sigma`` is lower by more than this.
        after_refiner: :meth:`CupNet.detect` tries the refiner's own landmarks before it.
    """

    landmarks: Callable[..., RimLandmarks]
    gate: float | None
    margin: float
    after_refiner: bool


class Look(NamedTuple):
    """One of :meth:`CupNet.detect`'s looks at images (the default: the first, the images
    as they are): how the locator sees them and, for a later look, what it may change.

    Attributes:
        mirrored: the locator sees their mirror images (left to right), its blobs mirrored
            back ...
        gamma: ... the images raised to this power (None: as they are) ...
        turned: ... the images turned over (``1 - image``), so the display the config or
            the polarity check takes is the other one.
        below: a later look's detection replaces a flagged or failed cup only where doubted
            less than this (None: wherever not flagged).
        empty_images: a later look looks at the images where no cup was found too, and
            adds the cups it finds there that it would let replace one.
        partners: ... and at every image with fewer cups than ``max_cups`` (none
            included), adding such cups found elsewhere (``CupNetConfig.partner_look``) ...
        partners_below: ... where doubted less than this (None: wherever not flagged) ...
        partners_verified: ... verifying (where ``verified``) the images it sees for that
            alone.
        verified: the verification of doubtful cups runs in this look ...
        searched: ... and the search of those it leaves doubtful.
        rod_removed: every stage sees the images with the straight rod (a cup's inserter)
            :func:`cupnet.rod.without_rod` finds painted over; an image where it finds none
            is not looked at again.
    """

    mirrored: bool = False
    gamma: float | None = None
    turned: bool = False
    below: float | None = None
    empty_images: bool = False
    partners: bool = False
    partners_below: float | None = None
    partners_verified: bool = True
    verified: bool = True
    searched: bool = True
    rod_removed: bool = False


FIRST_LOOK = Look()


@dataclass
class CupNetOutput:
    """Differentiable outputs of :meth:`CupNet.forward` for ``K`` cups of ``B`` images (with
    the crops and strips held where they were placed: see :meth:`CupNet.forward`).

    Attributes:
        locator_logits: ``(B, 1, S, S)`` letterboxed opening logits.
        letterbox: ``(B, 2, 3)`` letterbox-to-image affines.
        crop_logits: ``(K, 1, s, s)`` opening logits of each cup's crop.
        crop_to_image: ``(K, 2, 3)`` crop-to-image affines.
        cup_index: ``(K, 2)`` (image, cup slot) of each crop.
        landmarks: ``(K, N, 2)`` original-image pixels; ``weights``: ``(K, N)``: the rim
            stage's when the model has one, else the refiner's.
        solution: pose solver output for the ``K`` cups (float64, public units).
        refiner_landmarks, refiner_weights: the refiner's own (the same as ``landmarks`` and
            ``weights`` without a rim stage).
        rim: the rim stage's output (None without a rim stage).
    """

    locator_logits: Tensor
    letterbox: Tensor
    crop_logits: Tensor
    crop_to_image: Tensor
    cup_index: Tensor
    landmarks: Tensor
    weights: Tensor
    solution: PoseSolution
    refiner_landmarks: Tensor
    refiner_weights: Tensor
    rim: RimLandmarks | None = None


def _unet(config: CupNetConfig) -> smp.Unet:
    try:
        return smp.Unet(config.encoder, encoder_weights=None, in_channels=1, classes=1,
                        encoder_depth=len(config.decoder_channels),
                        decoder_channels=tuple(config.decoder_channels))
    except (KeyError, RuntimeError) as err:  # smp's and timm's own: a traceback in training
        if isinstance(err, RuntimeError) and "Unknown model" not in str(err):
            raise
        raise ValueError(f"unknown encoder {config.encoder!r} (smp's names, or 'tu-' and a "
                         f"timm model's): {str(err)[:300]}") from err


def _standardise(views: Tensor) -> Tensor:
    """Per-view zero mean, unit variance: robust to exposure and windowing. ``(K, 1, h, w)``."""
    mean = views.mean((-2, -1), keepdim=True)
    std = views.std((-2, -1), keepdim=True)
    return (views - mean) / (std + 1e-3)


# Pixel values past these are no [0, 1] image: 8-, 12- or 16-bit counts not yet scaled, or
# pixels standardised to zero mean. The networks standardise each view and may still find the
# cup, but the noise measure and the gamma looks read [0, 1]: an 8-bit image's noise went
# unmeasured, and a noisy one was not denoised (theta 16.6 deg off, against 0.44 scaled).
# The margin leaves room for images a little outside the range (noise added, a filter's ring).
PIXEL_RANGE = (-0.5, 1.5)


def checked_pixels(images: Tensor, first: int = 0) -> None:
    """Raise a ValueError naming the first of ``images`` ``(B, ...)`` (numbered from
    ``first``) whose pixels are not floats in [0, 1] (:data:`PIXEL_RANGE`): an integer dtype,
    NaN or infinite values, or values far outside. One reduction and one host sync a batch."""
    if len(images) == 0:
        return
    if not images.is_floating_point():
        raise ValueError(f"image {first}: pixels of {images.dtype}, where floats in [0, 1] are "
                         f"needed (divide by the bit depth's full scale, such as 255 or "
                         f"4095, or read the file with cupnet.io.images.read_image)")
    lows, highs = (v.tolist() for v in images.detach().reshape(len(images), -1).aminmax(dim=-1))
    for index, (low, high) in enumerate(zip(lows, highs, strict=True), first):
        if not (math.isfinite(low) and math.isfinite(high)):
            raise ValueError(f"image {index}: contains NaN or infinite values")
        if low < PIXEL_RANGE[0] or high > PIXEL_RANGE[1]:
            raise ValueError(f"image {index}: pixels span [{low:.4g}, {high:.4g}], where [0, 1] "
                             f"is needed (unscaled counts? divide by the bit depth's full "
                             f"scale, or read the file with cupnet.io.images.read_image)")


def _as_image_list(images: Tensor | list, dtype: torch.dtype) -> list[Tensor]:
    """``(B, 1, H, W)`` tensor or a list of ``(H, W)`` / ``(1, H, W)`` arrays -> ``(1, H, W)``s
    of ``dtype``, each checked (:func:`checked_pixels`)."""
    items = list(images) if not isinstance(images, Tensor) or images.ndim == 4 else [images]
    out = []
    for i, image in enumerate(items):
        t = torch.as_tensor(np.asarray(image) if not isinstance(image, Tensor) else image)
        if t.ndim == 2:
            t = t[None]
        if t.ndim != 3 or t.shape[0] != 1:
            raise ValueError(f"image {i}: expected (1, H, W) or (H, W), got {tuple(t.shape)}")
        checked_pixels(t, i)
        out.append(t.to(dtype))
    return out


@contextlib.contextmanager
def evaluating(model: nn.Module) -> Iterator[None]:
    """``model`` in eval mode within the block, its mode restored after: in train mode its
    BatchNorms would use and update the batch's statistics. Switched only when needed (smp's
    ``train()`` walks every submodule, ~2 ms a call)."""
    was_training = model.training
    if was_training:
        model.eval()
    try:
        yield
    finally:
        if was_training:
            model.train()


def cup_diameters(cup_diameter: Tensor | float, batch: int) -> Tensor:
    """``(B,)`` float64 cup diameters (mm) of a batch from a scalar or ``(B,)``; another
    shape is a ValueError naming it."""
    diameter = torch.as_tensor(cup_diameter, dtype=torch.float64)
    diameter = diameter.expand(batch) if diameter.ndim == 0 else diameter
    if diameter.shape != (batch,):
        raise ValueError(f"cup_diameter must be a scalar or ({batch},), got "
                         f"{tuple(diameter.shape)}")
    return diameter


def check_usable_geometry(geometry: Geometry, diameter: Tensor) -> None:
    """A ValueError naming the first image whose geometry field or cup ``diameter`` ``(B,)``
    (mm) cannot be used: of other than one value or one per image, a source-to-detector
    distance, pixel spacing or diameter that is not a finite number > 0, or a principal
    point that is not finite. For a batch's images before any network runs: a field of the
    wrong count had failed deep, in a reshape, and an unusable value had run every network
    and then failed each cup found as "no pose from the rim found" (an image without a cup
    said nothing)."""
    check_geometry_batch(geometry, len(diameter))
    for i, size in enumerate(diameter.tolist()):
        if not (math.isfinite(size) and size > 0):
            raise ValueError(f"image {i}: cup diameter must be a finite number > 0 mm, got "
                             f"{size}")
    for i, problem in enumerate(geometry_problems(geometry, diameter / 2)):
        if problem is not None:
            raise ValueError(f"image {i}: {problem}")


def with_second_poses(found: list[list[CupDetection]], geometry: Geometry,
                      diameter: Tensor) -> list[list[CupDetection]]:
    """``found`` (per image, with its ``geometry`` and cup ``diameter`` ``(B,)`` mm), each
    ``ok`` cup whose reported rim has a second pose in range (:func:`other_circle_pose`)
    made ``ambiguous``, with that pose as its ``alt_pose``; its ``pose`` as it was.

    Ambiguity is first judged on the landmarks' fit, before the dome's outline moves the
    pose. Nearly edge-on, a rim whose fit's second pose fell just out of range can be moved
    to one whose second pose is in range, and on the four seed sets that second pose was the
    true one for 4 of the 6 gross failures reported ``ok`` that the ``check`` flag missed
    (docs/training.md, item 54): they gave no sign of it.
    """
    todo = [(i, j) for i, cups in enumerate(found) for j, cup in enumerate(cups)
            if cup.status == "ok" and np.isfinite(cup.pose).all()]
    if not todo:
        return found
    image = torch.tensor([i for i, _ in todo])
    pose = torch.from_numpy(np.stack([found[i][j].pose for i, j in todo])).double()
    other, in_range = rim_second_poses(pose, image, geometry, diameter)
    out = [list(cups) for cups in found]
    for (i, j), alt, take in zip(todo, other, in_range.tolist(), strict=True):
        if take:
            out[i][j] = replace(out[i][j], ambiguous=True, alt_pose=alt.numpy(),
                                status="ambiguous")
    return out


def rim_second_poses(pose: Tensor, image: Tensor, geometry: Geometry,
                     diameter: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`other_circle_pose` of cups' poses ``(K, 5)`` deg / mm (float64), each in the
    image ``image`` ``(K,)`` of a batch of ``geometry`` and cup ``diameter`` ``(B,)`` mm."""
    rows = geometry_rows(geometry, len(diameter)).to(pose.device)[image]
    return other_circle_pose(pose, diameter.to(pose)[image] / 2, Geometry.from_rows(rows))


def geometry_rows(geometry: Geometry, batch: int) -> Tensor:
    """``(B, 4)`` float64 rows (sdd, spacing, u0, v0) of a batch geometry (checked where
    it comes in: :meth:`CupNet.detect`, :func:`cupnet.batched.batched_cups`)."""
    return torch.stack([t.expand(batch) if t.ndim == 0 else t.reshape(batch)
                        for t in geometry.tensors(torch.float64)], -1)


# Poses of one image this near (deg, deg, mm, mm, mm) are one pose to the outline refinement.
_OUTLINE_TWINS = (0.5, 0.5, 0.5, 0.5, 4.0)
# One cup's landmarks (N, 2), weights (N,), the solution of its source's batch, and its row.
_Pick = tuple[Tensor, Tensor, PoseSolution, int]
# A landmark source of CupNet.detect: cups (K,) -> landmarks (K, N, 2), weights (K, N).
_Source = Callable[[Tensor], tuple[Tensor, Tensor]]


class CupNet(nn.Module):
    """Two-stage cup-opening segmentation, soft landmarks, ellipse fit and pose solver."""

    def __init__(self, config: CupNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or CupNetConfig()
        # Channels-last weights take oneDNN's faster convolution kernels on CPU (3-4 ms of the
        # 48 ms of a 512 px detect on the 2-core machine); the rim network's thin strips are
        # faster as they are.
        self.locator = _unet(self.config).to(memory_format=torch.channels_last)
        self.refiner = _unet(self.config).to(memory_format=torch.channels_last)
        self.rim = RimNet(self.config.rim_channels) if self.config.rim_passes > 0 else None
        self.coarse_rim = (RimNet(self.config.coarse_rim_channels or self.config.rim_channels)
                           if self.config.coarse_rim_passes > 0 else None)
        self.blur_rim = RimNet(self.config.rim_channels) if self.config.blur_rim else None
        if self.config.encoder_weights:
            state, _ = _read_checkpoint(Path(self.config.encoder_weights))
            for net in (self.locator, self.refiner):
                net.encoder.load_state_dict(state, strict=False)

    def fine_rim(self) -> nn.Module | None:
        """The fine rim network every rim stage runs (the poses' doubts too): the
        blur-trained one where the config says the images are ``blurred``, else the
        model's own."""
        if self.config.blurred and self.blur_rim is None:  # blur_rim set after the model was made
            raise ValueError(BLURRED_WITHOUT_BLUR_RIM)
        return self.blur_rim if self.config.blurred else self.rim

    @property
    def dtype(self) -> torch.dtype:
        return next(self.parameters()).dtype

    # -- stage 1 ---------------------------------------------------------------------------
    def letterbox(self, images: list[Tensor]) -> tuple[Tensor, Tensor]:
        """Letterboxed views ``(B, 1, S, S)`` and their crop-to-image affines ``(B, 2, 3)``."""
        size = self.config.locator_size
        affines = torch.stack([letterbox_affine(im.shape[-2], im.shape[-1], size)
                               for im in images]).to(images[0])
        return resample_batch(images, affines, size), affines

    def locator_logits(self, views: Tensor, gamma: float | Tensor | None = None) -> Tensor:
        """The locator on views ``(K, 1, S, S)`` in [0, 1]: opening logits ``(K, 1, S, S)``.

        ``gamma``: look at the views raised to this power, one or ``(K,)``.
        """
        if gamma is not None:
            views = views.clamp(0, 1) ** torch.as_tensor(gamma).to(views).reshape(-1, 1, 1, 1)
        return self.locator(_standardise(views))

    def locate(self, images: list[Tensor], gamma: float | Tensor | None = None
               ) -> tuple[Tensor, Tensor]:
        """Stage 1: letterboxed opening logits ``(B, 1, S, S)`` and affines ``(B, 2, 3)``.

        ``gamma``: look at the images (in [0, 1]) raised to this power, one or ``(B,)``.
        """
        views, affines = self.letterbox(images)
        return self.locator_logits(views, gamma), affines

    def locate_windows(self, images: list[Tensor], gamma: float | None = None
                       ) -> tuple[list[Tensor], Tensor]:
        """Stage 1 at inference: the locator on each image's square windows
        (:func:`cupnet.crops.square_windows`; a square image's one window is its letterbox).

        Returns:
            per image, opening logits ``(1, h, w)`` on its windows' grid (where windows
            overlap, the most confident); the grids' pixel-to-image affines ``(B, 2, 3)``.
        """
        size = self.config.locator_size
        windows = [square_windows(im.shape[-2], im.shape[-1], size) for im in images]
        affines = torch.cat([affine for affine, _ in windows]).to(images[0])
        index = torch.cat([torch.full((len(place),), i) for i, (_, place) in enumerate(windows)])
        logits = self.locator_logits(resample_batch(images, affines, size, index), gamma)
        if len(logits) == len(images):  # one window an image (square ones): nothing to merge
            return list(logits), affines
        merged = []
        for i, (_, place) in enumerate(windows):
            views = logits[index == i]
            if len(place) == 1:
                merged.append(views[0])
                continue
            width, height = (place.amax(0) + size).tolist()
            grid = views.new_full((1, height, width), -math.inf)
            for view, (u, v) in zip(views, place.tolist(), strict=True):
                grid[:, v:v + size, u:u + size] = torch.maximum(
                    grid[:, v:v + size, u:u + size], view)
            merged.append(grid)
        return merged, torch.stack([affine[0] for affine, _ in windows]).to(images[0])

    def rough_ellipses(self, images: list[Tensor], gamma: float | None = None,
                       fields: list[tuple[float, float, float] | None] | None = None
                       ) -> tuple[Tensor, Tensor]:
        """Stage 1 at inference: :meth:`ellipses_from_locator` of :meth:`locate_windows`
        (on the images raised to the power ``gamma``, None: as they are), looked for again
        with ``locator_retry_gamma`` in the images where no cup was found (no blob
        :meth:`kept_blobs` keeps); with ``round_field``, those centred outside the image's
        round field (``fields``, each image's :func:`cupnet.field.round_field` where known)
        are dropped."""
        if fields is None:
            fields = self.round_fields(images)
        rough, scores = self.ellipses_from_locator(*self.locate_windows(images, gamma), fields)
        retry = self.config.locator_retry_gamma
        empty = (~self.kept_blobs(rough, scores).any(-1)).nonzero()[:, 0]
        if retry is not None and len(empty):
            again = self.ellipses_from_locator(
                *self.locate_windows([images[i] for i in empty], retry),
                [fields[i] for i in empty])
            # An image keeps its weak blobs where the retry finds no better.
            found = self.kept_blobs(*again).any(-1)
            rough[empty[found]], scores[empty[found]] = again[0][found], again[1][found]
        return rough, scores

    def round_fields(self, images: list[Tensor]) -> list[tuple[float, float, float] | None]:
        """Each image's :func:`cupnet.field.round_field` with ``round_field``, else Nones."""
        # An image turned over (metal "bright") keeps its flat surround: no need to undo it.
        return (map_on_cores(round_field, _on_cpu(images)) if self.config.round_field
                else [None] * len(images))

    def kept_blobs(self, rough: Tensor, scores: Tensor) -> Tensor:
        """Which locator blobs are taken for cups ``(B, C)`` bool: found (rough ellipses
        ``(B, C, 5)`` finite) and, with ``min_score``, their scores ``(B, C)`` that high."""
        kept = torch.isfinite(rough).all(-1)
        return kept if self.config.min_score is None else kept & (scores >= self.config.min_score)

    def ellipses_from_locator(self, logits: Tensor | list[Tensor], letterbox: Tensor,
                              fields: list[tuple[float, float, float] | None] | None = None
                              ) -> tuple[Tensor, Tensor]:
        """Rough cup ellipses from the locator's components (their second moments).

        Args:
            logits: ``(B, 1, S, S)``, or per image ``(1, h, w)`` (:meth:`locate_windows`).
            letterbox: ``(B, 2, 3)`` their pixel-to-image affines.
            fields: per image its round field ``(cx, cy, r)`` px or None: components
                centred outside it are no cups (None: no image has one).
        Returns:
            ellipses ``(B, C, 5)`` (cx, cy, a, b, alpha_deg) image pixels, NaN where no cup,
            largest components first; scores ``(B, C)`` (mean probability of the component).
        """
        cfg = self.config
        maps = (torch.sigmoid(logits.detach()) if isinstance(logits, Tensor)
                else [torch.sigmoid(m.detach()) for m in logits])
        prob = [m.double().numpy()[0] for m in _on_cpu(list(maps))]
        ellipses = torch.full((len(prob), cfg.max_cups, 5), math.nan, dtype=torch.float64)
        scores = torch.zeros(len(prob), cfg.max_cups, dtype=torch.float64)

        def blobs(p: np.ndarray) -> tuple[np.ndarray, ...]:
            count, labels = cv2.connectedComponents((p > cfg.detect_threshold).astype(np.uint8))
            return component_moments(p, labels, count)

        # OpenCV releases the GIL: a large batch's maps labelled on every core.
        moments = map_on_cores(blobs, prob)
        owner = [i for i, parts in enumerate(moments) for _ in range(len(parts[0]))]
        if not owner:
            return ellipses, scores
        # Every image's components at once: a few operations a batch, not a few per blob.
        mass, pixels, centre, cov = (torch.from_numpy(np.concatenate(parts))
                                     for parts in zip(*moments, strict=True))
        affine = letterbox.detach().double().cpu()[owner]  # (n, 2, 3)
        centre = to_image(centre[:, None], affine)[:, 0]
        kept = mass >= cfg.min_cup_area
        if fields is not None:
            field = torch.tensor([f or (math.nan,) * 3 for f in fields], dtype=torch.float64)
            kept &= ~outside_field(centre, field[owner])
        evals, evecs = torch.linalg.eigh(cov)
        # A filled ellipse: 4 var = a^2 along each axis.
        axes = 2 * evals.clamp_min(1 / 12).sqrt().flip(-1) * affine[:, :1, 0]
        angle = torch.rad2deg(atan2(evecs[:, 1, 1], evecs[:, 0, 1])) % 180
        rows = torch.cat([centre, axes, angle[:, None]], -1)
        # Per image, its largest components first; ties in label order (a stable sort).
        image, slot, component = [], [], []
        for k in np.lexsort((-mass.numpy(), owner)):
            taken = image.count(owner[k])
            if kept[k] and taken < cfg.max_cups:
                image.append(owner[k])
                slot.append(taken)
                component.append(int(k))
        ellipses[image, slot] = rows[component]
        scores[image, slot] = mass[component] / pixels[component]  # mean probability
        return ellipses, scores

    def first_pass_ellipses(self, rough: Tensor) -> Tensor:
        """Locator ellipses ``(K, 5)`` -> the ellipses the first refiner pass is framed on."""
        major = rough[:, 2:3] * self.config.locator_scale
        minor = torch.maximum(rough[:, 3:4] * self.config.locator_scale, 0.8 * major)
        return torch.cat([rough[:, :2], major, minor, rough[:, 4:]], -1)

    def frames(self, ellipses: Tensor) -> Tensor:
        """Crop frames ``(..., 5)`` of (rough) ellipses ``(..., 5)``, see :func:`frame_ellipse`."""
        cfg = self.config
        return frame_ellipse(ellipses, cfg.crop_fill, cfg.crop_min_ratio, cfg.crop_max_stretch)

    # -- stage 2 ---------------------------------------------------------------------------
    def segment_crops(self, images: list[Tensor] | Tensor, frames: Tensor, index: Tensor
                      ) -> tuple[Tensor, Tensor]:
        """Stage 2: crop logits ``(K, 1, s, s)`` and crop-to-image affines ``(K, 2, 3)``.

        Args:
            images: ``(B, 1, H, W)`` or list of ``(1, H, W)``.
            frames: ``(K, 5)`` crop frames (see :func:`cupnet.crops.ellipse_crop_affine`).
            index: ``(K,)`` image of each frame.
        """
        size = self.config.crop_size
        affines = ellipse_crop_affine(frames, size).to(images[0].dtype)
        crops = resample_batch(images, affines, size, index)
        if crops.shape[0] == 0:  # no cup: no network call (BatchNorm needs a batch)
            return crops, affines
        return self.refiner(_standardise(crops)), affines

    def refiner_passes(self, images: list[Tensor] | Tensor, frames: Tensor, index: Tensor
                       ) -> tuple[Tensor, Tensor, Tensor]:
        """Stage 2 at inference: ``refine_passes`` passes from crop ``frames`` ``(K, 5)`` of
        the images ``index`` ``(K,)``, each re-framed on the last one's fit where it is
        usable (the old frame kept otherwise). Returns the last pass's frames ``(K, 5)``,
        crop logits ``(K, 1, s, s)`` and crop-to-image affines ``(K, 2, 3)``."""
        for _ in range(self.config.refine_passes - 1):
            frames = self.frames(self.refiner_fit(
                *self.crop_landmarks(*self.segment_crops(images, frames, index)), frames))
        return frames, *self.segment_crops(images, frames, index)

    def crop_landmarks(self, crop_logits: Tensor, crop_to_image: Tensor) -> tuple[Tensor, Tensor]:
        """Soft landmarks in original-image pixels ``(K, N, 2)`` float64 and weights ``(K, N)``."""
        points, weights = ray_landmarks(torch.sigmoid(crop_logits).double(), self.config.n_rays,
                                        self.config.ray_samples)
        return to_image(points, crop_to_image.double()), weights

    # -- stage 3 ---------------------------------------------------------------------------
    @property
    def rim_reach(self) -> float:
        """How far (image pixels) the rim stage looks either side of its ellipse, per pass."""
        return (self.config.rim_samples - 1) / 2 * self.config.rim_step

    def in_theta_range(self, poses: Tensor) -> Tensor:
        """``(...)`` whether each pose ``(..., 5)`` deg / mm has an anteversion within
        ``max_theta_deg`` (any but NaN without a limit): a more open pose counts as a
        failure of its landmark source."""
        limit = self.config.max_theta_deg
        return poses[..., 0] <= (math.inf if limit is None else limit)

    def rim_landmarks(self, images: list[Tensor] | Tensor, index: Tensor, start: Tensor,
                      passes: int | None = None, coarse: bool = False) -> RimLandmarks:
        """Rim stage: strip passes from ``start`` ellipses (gradients reach the last pass's
        network, not the ellipses its strips were framed on).

        Args:
            images: ``(B, 1, H, W)`` or list of ``(1, H, W)``.
            index: ``(K,)`` image of each cup.
            start: ``(K, 5)`` ellipses (cx, cy, a, b, alpha_deg), image pixels.
            passes: strip passes (None: ``rim_passes``, or ``coarse_rim_passes``).
            coarse: run the coarse rim stage (strips scaled to each cup) instead of the fine.
        Returns:
            the last pass's :class:`cupnet.rim.RimLandmarks`.
        """
        cfg = self.config
        net = self.coarse_rim if coarse else self.fine_rim()
        if net is None:
            raise ValueError(f"this CupNet has no {'coarse ' if coarse else ''}rim stage "
                             f"({'coarse_' if coarse else ''}rim_passes = 0)")
        passes = (cfg.coarse_rim_passes if coarse else cfg.rim_passes) if passes is None else passes
        if passes < 1:
            raise ValueError(f"rim stage passes must be >= 1, got {passes}")
        ellipse = start.detach().double()
        for remaining in range(passes - 1, -1, -1):
            points, normals = rim_frame(ellipse, cfg.rim_points)
            offsets = (scaled_offsets(cfg.rim_samples, ellipse, cfg.coarse_rim_reach)
                       if coarse else strip_offsets(cfg.rim_samples, cfg.rim_step,
                                                    device=start.device))
            rim = self._strip_landmarks(net, images, index, points, normals, offsets)
            if remaining:
                ellipse = usable_fit(rim.landmarks.detach(), rim.weights.detach(), ellipse)
        return rim

    def coarse_framed_rim_landmarks(self, images: list[Tensor] | Tensor, index: Tensor,
                                    start: Tensor) -> RimLandmarks:
        """The fine rim stage framed on the coarse rim stage's weighted fit from ``start``
        ``(K, 5)`` (``start`` kept where the fit fails). The coarse stage runs without
        gradient, as the fine stage's strips take none from the ellipses they are framed on.
        """
        with torch.no_grad():
            coarse = self.rim_landmarks(images, index, start, coarse=True)
            framed = usable_fit(coarse.landmarks, coarse.weights, start)
        return self.rim_landmarks(images, index, framed)

    def thin_rim_landmarks(self, images: list[Tensor] | Tensor, index: Tensor, start: Tensor
                           ) -> RimLandmarks:
        """The fine rim stage from thin-rim hypotheses around each ellipse ``start`` ``(K, 5)``
        (:func:`cupnet.rim.thin_rim_starts`): one pass from each, then ``rim_passes`` more
        from the weighted fit of the pass the network trusts most (lowest mean ``log sigma``).
        """
        return self.ranked_thin_rim_landmarks(images, index, start, 1)[0]

    def ranked_thin_rim_landmarks(self, images: list[Tensor] | Tensor, index: Tensor,
                                  start: Tensor, top: int) -> list[RimLandmarks]:
        """:meth:`thin_rim_landmarks` from each of the ``top`` hypotheses the network trusts
        most after one pass, most trusted first."""
        cfg = self.config
        starts = thin_rim_starts(start.detach().double(), cfg.thin_rim_angles, cfg.thin_rim_ratio)
        count, angles = starts.shape[:2]
        starts = starts.flatten(0, 1)
        first = self.rim_landmarks(images, index.repeat_interleave(angles), starts, passes=1)
        doubt = first.sigma.log().mean(-1).reshape(count, angles).nan_to_num(math.inf)
        ranked = doubt.argsort(-1)[:, :top]
        found = []
        for rank in range(ranked.shape[1]):
            pick = torch.arange(count, device=doubt.device) * angles + ranked[:, rank]
            framed = usable_fit(first.landmarks[pick], first.weights[pick], starts[pick])
            found.append(self.rim_landmarks(images, index, framed))
        return found

    def forward(self, images: Tensor | list, geometry: Geometry, cup_diameter: Tensor,
                crop_frames: Tensor | None = None, refine_pose: bool = False) -> CupNetOutput:
        """Images + geometry -> locator map, crop maps, landmarks, ellipses and poses.

        Args:
            images: ``(B, 1, H, W)`` float32 in [0, 1] (or a list of ``(1, H_i, W_i)``).
            geometry: fields ``(B,)`` or scalars.
            cup_diameter: ``(B,)`` or ``(B, C)`` mm.
            crop_frames: ``(B, C, 5)`` crops to segment (see
                :func:`cupnet.crops.ellipse_crop_affine`), NaN rows skipped (training frames
                them on the truth); None frames them on the locator's components.
            refine_pose: run the solver's maximum-likelihood refinement (slower); otherwise
                the closed form, differentiable through ``eigh``.
        Returns:
            :class:`CupNetOutput` with ``K`` = number of crops segmented.

        Gradients are those of the outputs with every crop and strip held where it was
        placed: each crop is framed on the locator's blob (or ``crop_frames``), the rim
        stage on the refiner's fit, and each rim pass after the first on the last pass's
        fit, all detached. So a pose loss reaches the rim network that gives the landmarks
        (the refiner where the model has no rim stage) and the image through it, not the
        locator or the refiner; and with ``rim_passes`` > 1 (the shipped model's 2) the rim
        network's gradient is not the whole derivative of the pose (against central
        differences, ratios of 0.5-0.9 and a sign or two): set ``config.rim_passes = 1``
        where that matters (ratios 1.000). Unlike :meth:`detect`, nothing is resized:
        images well under the training's sizes give far worse poses.
        """
        if isinstance(images, Tensor):
            if images.ndim != 4 or images.shape[1] != 1:
                raise ValueError(f"images must be (B, 1, H, W), got {tuple(images.shape)}")
            checked_pixels(images)
            # Kept a batch (one tensor for the networks), of the model's dtype: a float64
            # batch had failed deep in a convolution ("expected scalar type Double").
            image_list = images.to(self.dtype)
        else:
            image_list = _as_image_list(images, self.dtype)
        if len(image_list) == 0:
            raise ValueError("images is an empty batch: forward takes one image at least")
        check_geometry_batch(geometry, len(image_list))
        diameter = torch.as_tensor(cup_diameter)
        if diameter.ndim > 2 or (diameter.ndim > 0 and diameter.shape[0] != len(image_list)):
            # It had failed in an indexing error once every network had run.
            raise ValueError(f"cup_diameter must be a scalar, ({len(image_list)},) or "
                             f"({len(image_list)}, C), got {tuple(diameter.shape)}")
        locator_logits, letterbox = self.locate(list(image_list))
        if crop_frames is None:
            rough = self.ellipses_from_locator(locator_logits, letterbox)[0]
            crop_frames = self.frames(self.first_pass_ellipses(rough.flatten(0, 1))
                                      ).reshape(rough.shape)
        batch = locator_logits.shape[0]
        cup_index = torch.isfinite(crop_frames).all(-1).nonzero()  # (K, 2)
        frames = crop_frames[cup_index[:, 0], cup_index[:, 1]].to(locator_logits.device)
        crop_logits, crop_to_image = self.segment_crops(image_list, frames, cup_index[:, 0])
        crop_points, crop_weights = self.crop_landmarks(crop_logits, crop_to_image)
        points, weights, rim = crop_points, crop_weights, None
        if self.rim is not None:
            start = usable_fit(points.detach(), weights.detach(),
                                _frame_ellipse(frames, self.config))
            # From the refiner's fit, as for most cups at inference (the coarse stage, run
            # on the others, trains on its own: ``rim_stage: coarse``).
            rim = self.rim_landmarks(image_list, cup_index[:, 0], start)
            points, weights = rim.landmarks, rim.weights
        solution = self.solve(points, weights, geometry, cup_diameter, cup_index, batch,
                              refine_pose)
        return CupNetOutput(locator_logits, letterbox, crop_logits, crop_to_image, cup_index,
                            points, weights, solution, crop_points, crop_weights, rim)

    def solve(self, points: Tensor, weights: Tensor, geometry: Geometry, cup_diameter: Tensor,
              cup_index: Tensor, batch: int, refine: bool) -> PoseSolution:
        """Pose of each crop's landmarks with its image's geometry and cup diameter."""
        rows = geometry_rows(geometry, batch).to(points.device)[cup_index[:, 0]]
        diameter = torch.as_tensor(cup_diameter, dtype=torch.float64, device=points.device)
        diameter = diameter.expand(batch) if diameter.ndim == 0 else diameter
        diameter = (diameter[cup_index[:, 0], cup_index[:, 1]] if diameter.ndim == 2
                    else diameter[cup_index[:, 0]])
        if points.shape[0] == 0:
            empty = points.new_zeros(0, 5)
            none = torch.zeros(0, dtype=torch.bool, device=points.device)
            return PoseSolution(empty, empty, none, empty, points.new_zeros(0), none, [], none)
        return solve_pose(points, Geometry.from_rows(rows), diameter, weights, refine=refine,
                          on_error="flag")

    # -- inference -------------------------------------------------------------------------
    @torch.inference_mode()
    def detect(self, images: Tensor | list, geometry: Geometry, cup_diameter: Tensor | float,
               return_masks: bool = True) -> list[list[CupDetection]]:
        """Cups of each image: 0 (no cup), 1 or 2 :class:`CupDetection` per image.

        Args:
            images: ``(B, 1, H, W)`` float32 in [0, 1], or a list of ``(H, W)`` / ``(1, H, W)``
                arrays of any sizes (:data:`MIN_IMAGE_SIDE` to 4096 px; smaller ones run,
                with far worse poses). Values a little outside [0, 1] are taken (noise
                added, a filter's ring), up to :data:`PIXEL_RANGE`.
            geometry: fields ``(B,)`` or scalars, principal point in original-image pixels.
            cup_diameter: mm, scalar or ``(B,)``.
            return_masks: fill :attr:`CupDetection.mask` (an ``(H, W)`` array per cup).

        Raises:
            ValueError: naming the first image that cannot be used, before any network runs:
                pixels of an integer dtype, NaN, infinite or past :data:`PIXEL_RANGE`; a
                source-to-detector distance, pixel spacing or cup diameter that is not a
                positive number, or a principal point that is not finite; or a geometry
                field or diameter of other than one value or one per image.

        With ``round_field``, an image whose round field is much narrower than its frame (a
        screenshot or secondary capture with wide margins) is cut to the field's square
        first (:func:`cupnet.field.field_crop`), and its cups given back in its own pixels.
        """
        with evaluating(self):
            # Checked and converted once: every look takes these, or a subset of them.
            image_list = _as_image_list(images, self.dtype)
            if not image_list:  # an empty batch has no cups (it had failed in a torch.cat)
                return []
            diameter = cup_diameters(cup_diameter, len(image_list))
            check_usable_geometry(geometry, diameter)
            # An image over reduce_above is checked for noise as the networks see it (cut to
            # its round field and resized): the averaging lowers its noise, and non-local
            # means at full size tripled a noisy 2048 px DRR's time (docs/training.md,
            # item 71).
            large = [self.resize_factor(*image.shape[-2:]) < 1 for image in image_list]
            noises: list[tuple[float | None, bool | None]] = [(None, None)] * len(image_list)
            self._denoised_where_noisy(image_list, noises, [not big for big in large])
            shapes = [tuple(image.shape[-2:]) for image in image_list]
            # Found once: the crops come from them, and the later looks keep them (mirrored
            # where the look is; a turned look's locator finds its field afresh).
            fields = self.round_fields(image_list)
            # An image with no round field may still be a frame on a wider flat canvas.
            crops = [crop_of_field(field, *shape) if field is not None
                     else content_crop(image) if self.config.round_field else None
                     for field, shape, image in zip(fields, shapes, image_list, strict=True)]
            if any(crops):
                image_list, geometry = _cropped(image_list, geometry, crops)
                fields = [field if crop is None or field is None
                          else (field[0] - crop[0], field[1] - crop[1], field[2])
                          for field, crop in zip(fields, crops, strict=True)]
            # An image (or field) well under the networks' training sizes is enlarged to
            # their smallest first (docs/training.md, item 56), one far over them reduced
            # (item 71).
            sides = [tuple(image.shape[-2:]) for image in image_list]
            factors = [self.resize_factor(*side) for side in sides]
            if any(factor != 1 for factor in factors):
                image_list, geometry, fields = _resized(image_list, geometry, fields, factors)
            self._denoised_where_noisy(image_list, noises, large)
            with memoised_strips():
                found = self._detect(image_list, geometry, diameter, return_masks,
                                     fields=fields)
                for look in self.later_looks():
                    self._looked_again(found, image_list, geometry, diameter, return_masks,
                                       look, fields)
            # After every look: a later look may have posed the cup a failed piece is of.
            found = [without_failed_pieces(cups) for cups in found]
            found = self.with_image_displays(found, image_list)
            found = [[self._as_reported(cup, noise, cleaned, float(size) / 2) for cup in cups]
                     for cups, (noise, cleaned), size in zip(found, noises, diameter.tolist(),
                                                             strict=True)]
            found = with_second_poses(found, geometry, diameter)
            found = [cups if factor == 1 else [unresized(cup, factor, side) for cup in cups]
                     for cups, factor, side in zip(found, factors, sides, strict=True)]
            return [cups if crop is None else [moved(cup, crop[:2], shape) for cup in cups]
                    for cups, crop, shape in zip(found, crops, shapes, strict=True)]

    def resize_factor(self, height: int, width: int) -> float:
        """The factor :meth:`detect` resizes an ``height x width`` image (or its round
        field's square) by before the networks: up to ``enlarge_to`` where its shorter side
        is under ``enlarge_below``, down to ``reduce_to`` where over ``reduce_above``, else 1."""
        cfg = self.config
        return (enlargement(height, width, cfg.enlarge_below, cfg.enlarge_to)
                * reduction(height, width, cfg.reduce_above, cfg.reduce_to))

    def with_image_displays(self, found: list[list[CupDetection]], images: list[Tensor]
                            ) -> list[list[CupDetection]]:
        """``found`` (per image of ``images`` ``(1, H, W)``, in their pixels) with each
        image's cups reporting one display (``metal_bright``): with ``metal`` auto, the one
        the rims of the cups it reports show (:func:`cupnet.polarity.metal_shows_bright` on
        their ellipses, a near-tie going by its sign: no image is turned over by this
        judgement, so the looks' margin against turning one over needlessly does not apply;
        as found where those give none to judge by); with ``metal`` dark or bright every
        look reported the declared one already. No pose changes.

        Each look judges the display from its own locator blobs and turns the image over
        by it, and an image's cups may come from several looks: a stray blob beside a bright
        cup had tipped one look to dark, and a look that found a cup the first had missed
        had judged rightly the display the first look got wrong (docs/training.md, item
        65)."""
        if self.config.metal != "auto":
            return found
        out = []
        for cups, image in zip(found, images, strict=True):
            bright = metal_shows_bright(image, torch.from_numpy(
                np.stack([cup.ellipse for cup in cups])), REPORT_MARGIN) if cups else None
            out.append(cups if bright is None else
                       [replace(cup, metal_bright=bright) for cup in cups])
        return out

    def _denoised_where_noisy(self, images: list[Tensor],
                              noises: list[tuple[float | None, bool | None]],
                              which: list[bool]) -> None:
        """The ``images`` ``(1, H, W)`` that ``which`` marks checked for noise
        (:meth:`image_noises`, into ``noises``) and taken through non-local means where
        noisy, in place."""
        chosen = [i for i, take in enumerate(which) if take]
        for i, (noise, cleaned) in zip(chosen, self.image_noises([images[i] for i in chosen]),
                                       strict=True):
            noises[i] = (noise, cleaned)
            if cleaned:
                images[i] = denoised(images[i], noise)

    def image_noises(self, images: list[Tensor]) -> list[tuple[float | None, bool | None]]:
        """Whether each image's noise exceeds ``denoise_above``, so that :meth:`detect`
        takes it through non-local means first, and that noise (display units; None under
        the bar: the median that gives it costs more than the decision), as ``(noise,
        noisy)``; ``(None, None)`` each where ``denoise_above`` is None or infinite (never)."""
        above = self.config.denoise_above
        if above is None or math.isinf(above):
            return [(None, None)] * len(images)
        noises = [noise_above(image, above) for image in images]
        return [(noise, noise is not None) for noise in noises]

    @property
    def look_again_doubt(self) -> float | None:
        """The doubt from which a cup counts as flagged while :meth:`detect` looks
        (``look_again_doubt``, else ``check_doubt``)."""
        cfg = self.config
        return cfg.check_doubt if cfg.look_again_doubt is None else cfg.look_again_doubt

    def flagged(self, doubt: float | None, pose: Tensor, threshold: float | None
                ) -> bool | None:
        """Whether a cup of ``doubt`` and ``pose`` ``(5,)`` deg / mm is flagged at
        ``threshold`` (None: beyond ``max_theta_deg`` alone); None where no doubt was
        measured."""
        if doubt is None:
            return None
        return (threshold is not None and doubt >= threshold) or not bool(
            self.in_theta_range(pose))

    def _as_reported(self, cup: CupDetection, noise: float | None, cleaned: bool | None,
                     radius: float) -> CupDetection:
        """``cup`` as :meth:`detect` reports it: flagged at ``check_doubt`` (the looks went
        by ``look_again_doubt``), and wherever its rim's centre lies nearer the detector than
        the cup's ``radius`` (mm: its dome would pass through the detector; pure noise had
        given such cups, unflagged under ``--fastest``), with its image's ``noise`` and
        whether it was ``cleaned`` (:meth:`image_noises`)."""
        check = self.flagged(cup.doubt, torch.from_numpy(cup.pose), self.config.check_doubt)
        if float(cup.pose[4]) < radius:  # NaN (no pose): False
            check = True
        return replace(cup, check=check, noise=noise, denoised=cleaned)

    def later_looks(self) -> list[Look]:
        """:meth:`detect`'s later looks at images with a flagged or failed cup, in order,
        those the config asks for: mirrored (``second_look``; with ``partner_look`` at
        images with fewer cups than ``max_cups`` too, none included), at
        ``third_look_gamma``, at ``high_gamma_look`` (at images with no cup found too, and
        with ``partner_look`` at images with fewer cups than ``max_cups``),
        turned over (``fourth_look_turned``, at images with no cup found too, without the
        verification: in the shipped JSON the cups it doubts enough to verify would not
        pass its bar, and on an image without a cup it would verify blobs on anatomy, at
        13 times the first look's time).

        None searches the cups its verification leaves doubtful: on the selection seeds
        the later looks' search changed no cup's pose, and it took a sixth of the
        default's time on the speed set (docs/training.md, item 35)."""
        partners = {"partners": self.config.partner_look,
                    "partners_below": self.config.partner_doubt}
        looks = ([Look(mirrored=True, searched=False, **partners)]
                 if self.config.second_look else [])
        if self.config.third_look_gamma is not None:
            looks.append(Look(gamma=self.config.third_look_gamma, searched=False))
        if self.config.high_gamma_look is not None:
            # At images it sees only for a pair's other cup, verifying its blobs on anatomy
            # took most of its time and found no cup more (item 44).
            looks.append(Look(gamma=self.config.high_gamma_look, empty_images=True,
                              searched=False, partners_verified=False, **partners))
        if self.config.fourth_look_turned:
            looks.append(Look(turned=True, below=self.config.turned_look_doubt,
                              empty_images=True, verified=False, searched=False))
        if self.config.rod_look:
            looks.append(Look(rod_removed=True, searched=False))
        return looks

    def _looked_again(self, found: list[list[CupDetection]], images: list[Tensor],
                      geometry: Geometry, diameter: Tensor, return_masks: bool,
                      look: Look, fields: list[tuple[float, float, float] | None]) -> None:
        """The ``images`` ``(1, H, W)`` (with their ``geometry``, cup ``diameter`` ``(B,)``
        mm and round ``fields``) of ``found`` (:meth:`detect`'s) with a cup flagged
        ``check`` or an error (with ``look.empty_images`` those with no cup) detected again
        as ``look`` says, and with ``look.partners`` those with fewer than ``max_cups`` too
        (without verification where that alone brings them and ``look.partners_verified``
        is False). A flagged or failed cup takes a new detection that reaches it, is not
        flagged and is doubted less (and less than ``look.below`` where given); an image with
        no cup takes the new cups that pass those bars; with ``look.partners`` one with fewer
        cups adds such cups found elsewhere, doubted less than ``look.partners_below``
        (:func:`cupnet.detection.later_look_cups`). With ``look.rod_removed`` it sees only
        the images where :func:`cupnet.rod.without_rod` finds a rod, painted over.
        In place.

        The locator is neither mirror-symmetric nor blind to contrast, so its blob, and
        with it every crop, strip and landmark source after it, comes out a little
        different: another, nearly independent attempt. A flagged cup's first attempt
        mostly took a wrong contour (a femoral head, a thin rim at the wrong angle) from
        which no source or search recovered; from another framing they often do, and the
        rim network then believes the pose. Turned over, the image's display is judged
        afresh from the new blobs, where the first look may have judged it wrong.
        """
        partners = self.config.max_cups if look.partners else 0
        wanted = [i for i, cups in enumerate(found) if any(map(wants_another_look, cups))
                  or (look.empty_images and not cups)]
        if look.rod_removed:  # the images with a rod alone, seen with it painted over
            painted = {i: without_rod(images[i][0].cpu().numpy()) for i in wanted}
            wanted = [i for i in wanted if painted[i] is not None]
            images = [image if painted.get(i) is None
                      else torch.from_numpy(painted[i]).to(image)[None]
                      for i, image in enumerate(images)]
        paired = [i for i, cups in enumerate(found) if len(cups) < partners and i not in wanted]
        rows = geometry_rows(geometry, len(images))
        paired_look = look._replace(verified=look.verified and look.partners_verified)
        for again, this_look in ((wanted, look), (paired, paired_look)):
            if not again:
                continue
            # A believed cup is neither replaced nor added again: its blob gets no cup stages.
            known = [[cup.ellipse for cup in found[i] if not wants_another_look(cup)]
                     for i in again]
            second = self._detect([images[i] for i in again],
                                  Geometry.from_rows(rows[again]), diameter[again],
                                  return_masks, this_look, [fields[i] for i in again], known)
            for i, cups in zip(again, second, strict=True):
                found[i] = later_look_cups(found[i], cups, look.below, partners,
                                           look.partners_below)

    def _detect(self, image_list: list[Tensor], geometry: Geometry, diameter: Tensor,
                return_masks: bool, look: Look = FIRST_LOOK,
                fields: list[tuple[float, float, float] | None] | None = None,
                known: list[list[np.ndarray]] | None = None) -> list[list[CupDetection]]:
        """:meth:`detect` in eval mode on ``image_list`` ``(1, H, W)`` of the model's dtype
        and cup ``diameter`` ``(B,)`` mm (as :meth:`detect` checked them), the locator
        looking at the images as ``look`` says (the gamma through :meth:`rough_ellipses`),
        their round ``fields`` where known; blobs at the place of a ``known`` cup's ellipse
        ``(5,)`` px (per image) are passed over."""
        batch = len(image_list)
        turned = (self.config.metal == "bright") != look.turned
        if turned:
            image_list = [1 - image for image in image_list]
        if look.mirrored and fields is not None:
            # The mirror image's field is the field mirrored (to 1e-12 px; finding it again
            # took about as long as the look's locator).
            fields = [None if field is None else (image.shape[-1] - 1 - field[0], *field[1:])
                      for field, image in zip(fields, image_list, strict=True)]
        rough, scores = self.rough_ellipses(
            [image.flip(-1) for image in image_list] if look.mirrored else image_list,
            look.gamma, None if turned else fields)
        if look.mirrored:
            widths = torch.tensor([image.shape[-1] for image in image_list]).to(rough)
            rough = mirrored_ellipses(rough, widths[:, None])
        # Each image's display as given (a turned look's image was turned over above), as
        # declared or, with metal auto, as judged.
        bright = [self.config.metal == "bright"] * batch
        if self.config.metal == "auto":  # the cups found, not found again: none lost
            judged = [bool(metal_shows_bright(image, found))
                      for image, found in zip(image_list, rough, strict=True)]
            image_list = [1 - image if turn else image
                          for image, turn in zip(image_list, judged, strict=True)]
            bright = [turn != turned for turn in judged]
        # Weak blobs, and a later look's blobs at believed cups, are dropped before the cup
        # stages, not after: each cup is solved on its own, so the others' results are the
        # same (to the last digit with ONNX Runtime's networks, cupnet.batchwise), and a
        # dropped blob costs no strips.
        kept = self.kept_blobs(rough, scores)
        for i, ellipses in enumerate(known or []):
            for c in kept[i].nonzero()[:, 0].tolist():
                kept[i, c] = not any(same_place(rough[i, c].numpy(), e) for e in ellipses)
        cup_index = kept.nonzero()
        frames = self.frames(self.first_pass_ellipses(rough[cup_index[:, 0], cup_index[:, 1]]))
        results: list[list[CupDetection]] = [[] for _ in range(batch)]
        if len(cup_index) == 0:
            return results
        frames, crop_logits, crop_to_image = self.refiner_passes(image_list, frames,
                                                                 cup_index[:, 0])
        crop_points, crop_weights = self.crop_landmarks(crop_logits, crop_to_image)
        # Each cup's landmarks, weights and (solution, row) from the first source that gives
        # it a pose within max_theta_deg, each source run on the cups left: (1) the fine rim
        # stage framed on the refiner's fit (see trusted_rim_landmarks); (2) framed on the
        # coarse stage's fit (a rim the refiner missed); (3) the refiner's own landmarks (a
        # rim the strips lost); (4) the thin-rim hypotheses (a nearly edge-on rim the
        # refiner took for a disc); (5) the coarse stage from a start grown to a size the
        # rim can have (see _grown_rim_source). Sources 1, 2, 4 and 5 where the model has
        # them. Where none gives a pose within range: the first pose found, else the
        # refiner's failure (its ellipse is the one the mask shows); the verification
        # (reconsidered) looks at both again.
        index = cup_index[:, 0]

        def refiner(todo: Tensor) -> tuple[Tensor, Tensor]:
            return crop_points[todo], crop_weights[todo]

        sources: list[_Source] = [refiner]
        every_source = sources
        start: Tensor | None = None
        if self.rim is not None:
            start = self.refiner_fit(crop_points, crop_weights, frames)

            def run(method: Callable) -> _Source:
                return _source_from(method, image_list, index, start)

            sources = self.rim_sources(image_list, index, start, refiner)
            grown = []
            if self.coarse_rim is not None and self.config.grown_rim_scale is not None:
                grown = [self._grown_rim_source(image_list, geometry, diameter, cup_index,
                                                start)]
            sources += grown
            # What :meth:`verified` re-solves a doubtful cup from: each start on its own.
            every_source = [run(self.rim_landmarks),
                            *([run(self.coarse_framed_rim_landmarks)] if self.coarse_rim
                              is not None else []),
                            refiner, *grown]
        picks = self._first_picks(sources, refiner, geometry, diameter, cup_index, batch)
        poses = [solution.pose[row] for _, _, solution, row in picks]
        alt_poses = [solution.alt_pose[row] for _, _, solution, row in picks]
        ellipses = [solution.ellipse[row] for _, _, solution, row in picks]
        outlines: list[Tensor | None] = [None] * len(picks)
        doubts: dict[int, float] = {}
        residuals: dict[int, float] = {}
        solved = [k for k, (_, _, solution, row) in enumerate(picks) if solution.valid[row]]
        if self.config.outline_passes and self.rim is not None:
            rows = geometry_rows(geometry, batch)
            parts = torch.empty(0, 2, dtype=torch.float64)
            refused: dict[int, Tensor] = {}
            if solved:
                known, refused, seconds = self._outline_refine_picks(
                    image_list, index, picks, solved, poses, alt_poses, rows, diameter)
                # Ordered before the verification, which then doubts an ambiguous cup by its
                # better pose and keeps both where that one is believed.
                if self.config.ambiguous_by_doubt:
                    known.update(self._order_ambiguous(image_list, index, picks, solved, poses,
                                                       alt_poses, rows, diameter,
                                                       {k: torch.stack([known[k], second])
                                                        for k, second in seconds.items()}))
                parts = self._solved_doubts(image_list, index, solved, poses, rows, diameter,
                                            known)
            if self.config.verify_gate is not None and look.verified:
                solved, parts = self.reconsidered(image_list, index, picks, solved, poses,
                                                  alt_poses, parts, every_source, start,
                                                  geometry, diameter, cup_index, batch,
                                                  look.searched, refused)
            if solved:
                doubts = dict(zip(solved, parts.amax(-1).tolist(), strict=True))
                # The rim the refined pose projects to, not the landmarks' fit: the two differ
                # where the outline moved the pose (a thin rim's fit is short), and the overlay
                # should show the pose's rim.
                refined = torch.stack([poses[k] for k in solved])
                cup_geometry = Geometry.from_rows(rows[index[solved]])
                rims = ellipse_of_pose(refined, diameter[index[solved]], cup_geometry)
                domes = sphere_outline(pose_to_radians(refined), diameter[index[solved]] / 2,
                                       cup_geometry, 64, dome_only=True)[0]
                # The landmarks' residual to that rim too: their solution's had been reported
                # with the refined pose (1.8 px from one such rim, reported 0.9).
                residual = rim_residual(
                    pose_to_radians(refined),
                    pad_sequence([picks[k][0] for k in solved], batch_first=True),
                    pad_sequence([picks[k][1] for k in solved], batch_first=True),
                    diameter[index[solved]] / 2, cup_geometry)
                for k, rim, dome, distance in zip(solved, rims, domes, residual.tolist(),
                                                  strict=True):
                    ellipses[k], outlines[k], residuals[k] = rim, dome, distance
        for k, (i, c) in enumerate(cup_index.tolist()):
            points, weights, solution, row = picks[k]
            mask = None
            if return_masks:
                height, width = image_list[i].shape[-2:]
                mask = warp_affine(torch.sigmoid(crop_logits[k:k + 1]), crop_to_image[k:k + 1],
                                   (height, width), align_corners=True)[0, 0].numpy()
            ambiguous = bool(solution.ambiguous[row])
            doubt = doubts.get(k)
            results[i].append(CupDetection(
                pose=poses[k].numpy(),
                alt_pose=alt_poses[k].numpy() if ambiguous else None,
                ambiguous=ambiguous,
                ellipse=ellipses[k].numpy(),
                landmarks=points.numpy(),
                weights=weights.numpy(),
                residual_px=residuals.get(k, float(solution.residual_px[row])),
                mask=mask,
                status=found_cup_status(solution.status[row]),
                score=float(scores[i, c]),
                outline=None if outlines[k] is None else outlines[k].numpy(),
                doubt=doubt,
                check=self.flagged(doubt, poses[k], self.look_again_doubt),
                metal_bright=bright[i],
            ))
        return [distinct_cups(cups) for cups in results]

    def _first_picks(self, sources: list[_Source], refiner: _Source, geometry: Geometry,
                     diameter: Tensor, cup_index: Tensor, batch: int) -> list[_Pick]:
        """Each cup's pick (``cup_index (K, 2)``) from ``sources``, each run in turn on the
        cups still without a pose within ``max_theta_deg`` (:func:`takes_pick`): the first
        such pose; where none gives one, the first valid pose found, else the refiner's
        failure (its ellipse is the one its mask shows)."""
        chosen: list[_Pick | None] = [None] * len(cup_index)
        fallback: list[_Pick | None] = [None] * len(cup_index)
        for source in sources:
            todo = torch.tensor([k for k, pick in enumerate(chosen) if pick is None],
                                dtype=torch.long)
            if len(todo) == 0:
                break
            solved = self._solved_picks(source, todo, geometry, diameter, cup_index, batch)
            solution = solved[0][1][2]  # one solution for the source's rows
            in_range = solution.valid & self.in_theta_range(solution.pose)
            solved_before = torch.tensor([fallback[k] is not None and
                                          bool(fallback[k][2].valid[fallback[k][3]])
                                          for k in todo.tolist()], dtype=torch.bool,
                                         device=solution.valid.device)
            took = takes_pick(solution.valid, in_range, solved_before, source is refiner)
            for (k, pick), take, final in zip(solved, took.tolist(), in_range.tolist(),
                                              strict=True):
                if take and final:
                    chosen[k] = pick
                elif take:
                    fallback[k] = pick
        return [pick if pick is not None else other
                for pick, other in zip(chosen, fallback, strict=True)]

    def _solved_picks(self, source: _Source, todo: Tensor, geometry: Geometry,
                      diameter: Tensor, cup_index: Tensor, batch: int
                      ) -> list[tuple[int, _Pick]]:
        """``(cup, pick)`` of each cup in ``todo`` ``(K,)``: ``source``'s landmarks solved
        (with the ML refinement)."""
        points, weights = source(todo)
        solution = self.solve(points, weights, geometry, diameter, cup_index[todo], batch,
                              refine=True)
        return [(k, (points[row], weights[row], solution, row))
                for row, k in enumerate(todo.tolist())]

    def _outline_refine_picks(self, images: list[Tensor], index: Tensor, picks: list[_Pick],
                              solved: list[int], poses: list[Tensor], alt_poses: list[Tensor],
                              rows: Tensor, diameter: Tensor
                              ) -> tuple[dict[int, Tensor], dict[int, Tensor], dict[int, Tensor]]:
        """:meth:`outline_refined` on the ``solved`` cups' poses and their ambiguous pairs'
        second poses, in place in ``poses`` and ``alt_poses``; with ``outline_doubt_margin``,
        a pose the refinement leaves more doubted than it found it (:meth:`pose_doubt`, its
        parts summed) by more than that keeps its start.

        Args:
            index: ``(K,)`` image of each cup; picks: each cup's landmarks and solution.
            rows: ``(B, 4)`` each image's geometry; diameter: ``(B,)`` mm.
        Returns:
            ``cup -> (2,)`` the doubt (rim, outline) of each solved cup's pose as kept, where
            ``outline_doubt_margin`` had it measured (else empty); ``cup -> (5,)`` deg /
            mm the refined pose of each solved cup that kept its start instead; and
            ``cup -> (2,)`` the doubt of each ambiguous cup's second pose as kept, where
            measured (else empty).
        """
        paired = [k for k in solved if picks[k][2].ambiguous[picks[k][3]]]
        cups = solved + paired
        start = [poses[k] for k in solved] + [alt_poses[k] for k in paired]
        image = index[cups]
        refinements = self._refined_picks(images, image, [picks[k] for k in cups], start, rows,
                                          diameter)
        refined, doubt = self.unless_more_doubted(images, image, torch.stack(start),
                                                  refinements, rows[image], diameter[image])
        own = len(solved)  # the solved cups' poses, then their pairs' second poses
        kept = {} if doubt is None else dict(zip(solved, doubt[:own], strict=True))
        seconds = {} if doubt is None else dict(zip(paired, doubt[own:], strict=True))
        # Each pose kept is its start or its refinement: where it is not the refinement, the
        # start was kept against it.
        refused = {k: refinement for k, pose, refinement in zip(
            solved, refined[:own], refinements[:own], strict=True)
            if bool(torch.isfinite(refinement).all()) and not torch.equal(pose, refinement)}
        for k, pose in zip(solved, refined[:own], strict=True):
            poses[k] = pose
        for k, pose in zip(paired, refined[own:], strict=True):
            alt_poses[k] = pose
        return kept, refused, seconds

    def unless_more_doubted(self, images: list[Tensor] | Tensor, index: Tensor, start: Tensor,
                            refined: Tensor, geometry: Tensor, diameter: Tensor
                            ) -> tuple[Tensor, Tensor | None]:
        """``refined`` ``(K, 5)`` deg / mm, each row back at its ``start`` ``(K, 5)`` where
        :meth:`pose_doubt` (its parts summed) doubts it more than the start by more than
        ``outline_doubt_margin``; and the kept poses' doubts ``(K, 2)`` (rim, outline), or
        None where the config has no margin (``refined`` as it is, nothing measured).

        The rim network finds the dome's outline off it where the rim runs close inside (a
        strip across the outline shows both edges): the outline's landmarks then pull a
        right rim's pose off, which the network doubts more than before (docs/training.md,
        item 67).

        Args:
            images: the batch's images; index ``(K,)`` image of each pose.
            geometry: ``(K, 4)`` rows (sdd, spacing, u0, v0); diameter ``(K,)`` mm.
        """
        margin = self.config.outline_doubt_margin
        if margin is None or len(start) == 0:
            return refined, None
        doubt = self.pose_doubt(images, index.repeat(2), torch.cat([start, refined]),
                                geometry.repeat(2, 1), diameter.repeat(2)).reshape(2, -1, 2)
        worse = (doubt[1].sum(-1) > doubt[0].sum(-1) + margin)[:, None]
        return torch.where(worse, start, refined), torch.where(worse, doubt[0], doubt[1])

    def _refined_picks(self, images: list[Tensor], image: Tensor, picks: list[_Pick],
                       poses: list[Tensor], rows: Tensor, diameter: Tensor) -> Tensor:
        """:meth:`outline_refined` of ``poses`` (each ``(5,)``) solved from ``picks`` in the
        images ``image`` ``(P,)``; ``rows`` ``(B, 4)``, ``diameter`` ``(B,)`` per image.
        Returns ``(P, 5)``."""
        # Landmark sets differ in size (refiner 64, rim stages 128): zero weights pad them.
        return self.outline_refined(
            images, image, torch.stack(poses),
            pad_sequence([pick[0] for pick in picks], batch_first=True),
            pad_sequence([pick[1] for pick in picks], batch_first=True),
            torch.stack([pick[2].residual_px[pick[3]] for pick in picks]),
            rows[image], diameter[image])

    def reconsidered(self, images: list[Tensor], index: Tensor, picks: list[_Pick],
                     solved: list[int], poses: list[Tensor], alt_poses: list[Tensor],
                     parts: Tensor, sources: list[_Source], start: Tensor | None,
                     geometry: Geometry, diameter: Tensor, cup_index: Tensor,
                     batch: int, search: bool = True,
                     refused: dict[int, Tensor] | None = None) -> tuple[list[int], Tensor]:
        """Doubtful cups :meth:`verified`, then those still doubtful :meth:`searched` (where
        ``search`` and the config has a ``search_gate``), in place; the other arguments
        (``refused`` among them) as :meth:`verified`'s.

        A pose beyond ``max_theta_deg`` (no source gave one within it) is one the networks
        were never shown, however well the rim and the dome's outline they find agree with
        it (a nearly round rim along the sphere's outline explains both): it counts as
        doubted past every gate, so any candidate within range replaces it. Where none
        does, its ``parts`` are left as measured.

        A cup no landmark source solved (its rim lost, the landmarks on a femoral head too
        small for the cup) starts, where the model has ``start`` and a
        ``grown_rim_scale``, from the pose of ``start``'s ellipse grown as for
        :meth:`_grown_rim_source`, doubted past every gate as well; the candidate that
        replaces that start solves the cup where its doubt sums to under ``verify_gate``
        (a pose the verification would not doubt), else the cup stays unsolved.

        Returns:
            the solved cups (``solved`` and the cups solved here) and their ``parts``.
        """
        def take(k: int, pick: _Pick) -> None:
            picks[k], poses[k] = pick, pick[2].pose[pick[3]]
            alt_poses[k] = pick[2].alt_pose[pick[3]]

        starts = self._grown_start_picks(picks, solved, start, geometry, diameter,
                                         cup_index, batch)
        failed = {k: picks[k] for k in starts}
        for k, pick in starts.items():
            take(k, pick)
        solved = solved + list(starts)
        if not solved:
            return solved, parts
        parts = torch.cat([parts, parts.new_full((len(starts), 2), math.inf)])
        measured = parts.clone()
        parts[~self.in_theta_range(torch.stack([poses[k] for k in solved]))] = math.inf
        self.verified(images, index, picks, solved, poses, alt_poses, parts, sources, start,
                      geometry, diameter, cup_index, batch, refused)
        if search and self.config.search_gate is not None:
            self.searched(images, index, picks, solved, poses, alt_poses, parts, geometry,
                          diameter, cup_index, batch)
        parts = torch.where(parts.isinf(), measured, parts)
        kept = [j for j, k in enumerate(solved) if k not in starts or (
            picks[k] is not starts[k] and float(parts[j].sum()) < self.config.verify_gate)]
        for k in set(starts) - {solved[j] for j in kept}:
            take(k, failed[k])
        return [solved[j] for j in kept], parts[kept]

    def _grown_start_picks(self, picks: list[_Pick], solved: list[int], start: Tensor | None,
                           geometry: Geometry, diameter: Tensor, cup_index: Tensor,
                           batch: int) -> dict[int, _Pick]:
        """``cup -> pick`` of each cup not ``solved`` whose ``start`` ``(K, 5)`` ellipse,
        grown as for :meth:`_grown_rim_source`, gives a pose (its points solved); none
        without ``start`` or ``grown_rim_scale``."""
        unsolved = [k for k in range(len(picks)) if k not in solved]
        if start is None or self.config.grown_rim_scale is None or not unsolved:
            return {}
        todo = torch.tensor(unsolved, dtype=torch.long)
        ellipse = self._grown(start[todo], cup_index[todo, 0], geometry, diameter, batch)
        points = rim_frame(ellipse, self.config.rim_points)[0]
        weights = torch.ones(points.shape[:2], dtype=points.dtype)
        solution = self.solve(points, weights, geometry, diameter, cup_index[todo], batch,
                              refine=True)
        return {k: (points[row], weights[row], solution, row)
                for row, k in enumerate(unsolved) if solution.valid[row]}

    def verified(self, images: list[Tensor], index: Tensor, picks: list[_Pick],
                 solved: list[int], poses: list[Tensor], alt_poses: list[Tensor],
                 parts: Tensor, sources: list[_Source], start: Tensor | None,
                 geometry: Geometry, diameter: Tensor, cup_index: Tensor, batch: int,
                 refused: dict[int, Tensor] | None = None) -> None:
        """Doubtful cups solved again from every landmark source, in place.

        A solved cup whose outline-refined pose's doubt ``parts`` sums to ``verify_gate`` or
        more is solved from each of ``sources``, from the ``verify_thin_rims`` thin-rim
        hypotheses around ``start`` the fine rim stage trusts most and from the rims of its
        pose (and of the refinement it kept its start against, where ``refused`` holds one)
        turned to each of ``verify_anteversions``; the least doubted candidate replaces
        the cup's pose where it is doubted less by the margin (:meth:`_least_doubted`).
        The gross failures left after the outline are rims taken from the wrong contour (a
        femoral head's, a thin rim at the wrong angle); the source that finds the right one
        is not the same from cup to cup, and the right pose explains both the rim and the
        dome's outline where the others do not.

        Args:
            index: ``(K,)`` image of each cup; picks, poses (deg / mm), alt_poses: per cup.
            solved: the cups with a pose; parts: ``(len(solved), 2)`` their doubts (rim,
            outline; :meth:`pose_doubt`), in place.
            sources: as :meth:`detect`'s, cups -> landmarks.
            start: ``(K, 5)`` the refiner's ellipses (None: no thin-rim hypotheses).
            geometry, diameter: per image; cup_index: ``(K, 2)``; batch: images.
            refused: ``cup -> (5,)`` deg / mm, the outline refinement each cup's pose kept
                its start against (:meth:`unless_more_doubted`).
        """
        cfg = self.config
        rows = geometry_rows(geometry, batch)
        todo = _doubtful(solved, parts, cfg.verify_gate)
        if len(todo) == 0:
            return
        # More sources, each some landmarks per doubtful cup: the thin-rim hypotheses
        # (their first pass shared), then the rims of the first pose turned to each of
        # verify_anteversions (one network call for all).
        found: list[RimLandmarks] = []
        if start is not None and cfg.verify_thin_rims > 0:
            found += self.ranked_thin_rim_landmarks(images, index[todo], start[todo],
                                                    cfg.verify_thin_rims)
        found += self._turned_rims_found(images, index, todo, poses, rows, diameter)
        candidates = self._source_candidates(
            [*sources, *_found_sources(found, todo, len(index))], todo, picks, geometry,
            diameter, cup_index, batch)
        # A refinement unless_more_doubted turned down can hold the rim's inclination where
        # its start lost it (a start on the dome's outline and an inserter's edge, whose
        # turned rims keep its wrong inclination): its rims turned too (docs/training.md,
        # item 68).
        refused = refused or {}
        again = torch.tensor([k for k in todo.tolist() if k in refused], dtype=torch.long)
        if len(again):
            turned = self._turned_rims_found(images, index, again, refused, rows, diameter)
            candidates = self._source_candidates(
                _found_sources(turned, again, len(index)), again, picks, geometry, diameter,
                cup_index, batch, candidates)
        winners = self._least_doubted(images, index, solved, poses, parts, candidates,
                                      geometry, diameter, batch)
        for k, (pick, pose, doubt) in winners.items():
            picks[k], poses[k], alt_poses[k] = pick, pose, pick[2].alt_pose[pick[3]]
            parts[solved.index(k)] = doubt

    def _turned_rims_found(self, images: list[Tensor], index: Tensor, todo: Tensor,
                           poses: list[Tensor] | dict[int, Tensor], rows: Tensor,
                           diameter: Tensor) -> list[RimLandmarks]:
        """The fine rim network's landmarks across the rims of the cups ``todo`` ``(T,)``
        with ``poses`` (indexed by cup, each ``(5,)`` deg / mm) turned to each of
        ``verify_anteversions``, one set per anteversion (none without them); index
        ``(K,)`` image of each cup, rows ``(B, 4)`` and diameter ``(B,)`` per image."""
        anteversions = self.config.verify_anteversions
        if not anteversions:
            return []
        turned = torch.stack([poses[k] for k in todo.tolist()]).repeat(len(anteversions), 1, 1)
        turned[..., 0] = torch.tensor(anteversions).to(turned)[:, None]
        return self._pose_rim_found(images, index[todo], turned, rows, diameter)

    def _solved_doubts(self, images: list[Tensor], index: Tensor, solved: list[int],
                       poses: list[Tensor], rows: Tensor, diameter: Tensor,
                       known: dict[int, Tensor] | None = None) -> Tensor:
        """``(len(solved), 2)`` :meth:`pose_doubt` of the ``solved`` cups' poses, those of
        ``known`` (``cup -> (2,)``) taken as they are; rows ``(B, 4)``, diameter ``(B,)``
        per image."""
        known = known or {}
        current = torch.stack([poses[k] for k in solved])
        parts = current.new_empty(len(solved), 2)
        fresh = [j for j, k in enumerate(solved) if k not in known]
        if fresh:
            cups = index[solved][fresh]
            parts[fresh] = self.pose_doubt(images, cups, current[fresh], rows[cups],
                                           diameter[cups])
        for j, k in enumerate(solved):
            if k in known:
                parts[j] = known[k]
        return parts

    def searched(self, images: list[Tensor], index: Tensor, picks: list[_Pick],
                 solved: list[int], poses: list[Tensor], alt_poses: list[Tensor],
                 parts: Tensor, geometry: Geometry, diameter: Tensor, cup_index: Tensor,
                 batch: int) -> None:
        """Cups still doubtful after :meth:`verified` searched over the rim's orientation, in
        place.

        A solved cup whose doubt ``parts`` sums to ``search_gate`` or more, or has a part at
        ``search_part_gate`` or more, gets a grid of poses at its centre: anteversions
        ``search_anteversions`` by inclinations every ``search_inclination_step`` deg. The
        ``search_keep`` of them :meth:`pose_doubt` doubts least, and the
        ``search_keep_settled`` others it doubts least with the rim's offsets settled (from
        the same strips), give the fine rim network's landmarks across their rims; each
        set, solved (or, where it gives no pose within ``max_theta_deg``, its grid pose),
        is a start for :meth:`_least_doubted`, with its rules for turned rims on both angles
        and the rim ceiling ``search_rim_doubt``. A winner's landmarks, status and second
        pose are then solved from the network's landmarks across the rim it ends on. What
        this finds: a nearly edge-on cup whose dome and femoral head every source took for
        an open rim, an open cup taken for a thin rim across its head; the sources'
        landmarks all came from the same wrong contour, and the grid starts from none of
        them.

        Args:
            index: ``(K,)`` image of each cup; picks, poses (deg / mm), alt_poses: per cup.
            solved: the cups with a pose; parts: ``(len(solved), 2)`` their doubts (in place).
            geometry, diameter: per image; cup_index: ``(K, 2)``; batch: images.
        """
        cfg = self.config
        todo = _doubtful(solved, parts, cfg.search_gate, cfg.search_part_gate)
        if len(todo) == 0:
            return
        rows = geometry_rows(geometry, batch)
        orientations = torch.cartesian_prod(
            torch.tensor(cfg.search_anteversions, dtype=torch.float64),
            torch.arange(90.0, -90.0, -cfg.search_inclination_step, dtype=torch.float64))
        grid = torch.stack([poses[k] for k in todo.tolist()])[:, None].repeat(
            1, len(orientations), 1)  # (T, G, 5)
        grid[..., :2] = orientations
        cups = index[todo].repeat_interleave(len(orientations))
        flat = grid.flatten(0, 1)
        on_rim, rims = self._rim_edges(images, cups, flat, Geometry.from_rows(rows[cups]),
                                       diameter[cups])
        rim_doubts = [_rim_doubt(on_rim, rims, settled) for settled in (False, True)]
        dome = torch.full_like(rim_doubts[0], math.inf)
        screened = torch.ones_like(dome, dtype=torch.bool)
        if cfg.search_screen is not None and cfg.search_screen < len(orientations):
            # The dome's outline only for the poses whose rim, as it lies or settled, ranks
            # among each cup's search_screen best: the rest, far down on the rim, do not win.
            rank = torch.stack([doubt.reshape(len(todo), -1).argsort(-1).argsort(-1)
                                for doubt in rim_doubts]).amin(0)
            screened = (rank < cfg.search_screen).flatten()
        dome[screened] = self._outline_doubt(images, cups[screened], flat[screened],
                                             Geometry.from_rows(rows[cups[screened]]),
                                             diameter[cups[screened]])

        def ranked(settled: bool) -> Tensor:  # (T, G) the grid's doubts, as pose_doubt's sums
            return (rim_doubts[settled] + dome).reshape(len(todo), -1)

        best = ranked(False).topk(min(cfg.search_keep, len(orientations)), largest=False).indices
        extra = min(cfg.search_keep_settled, len(orientations) - best.shape[1])
        if extra > 0:  # the best once settled, beyond those
            best = torch.cat([best, ranked(True).scatter(1, best, math.inf).topk(
                extra, largest=False).indices], 1)
        kept = grid.gather(1, best[..., None].expand(-1, -1, 5)).transpose(0, 1)
        # Each kept grid pose's rim landmarks, solved; where they give no pose within
        # range, the refinement starts from the grid pose itself.
        candidates = []
        for starts, rim in zip(kept, self._pose_rim_found(images, index[todo], kept, rows,
                                                          diameter), strict=True):
            solution = self.solve(rim.landmarks, rim.weights, geometry, diameter,
                                  cup_index[todo], batch, refine=True)
            in_range = solution.valid & self.in_theta_range(solution.pose)
            candidates += [(k, (rim.landmarks[row], rim.weights[row], solution, row),
                            torch.where(in_range[row], solution.pose[row], starts[row]))
                           for row, k in enumerate(todo.tolist())]
        winners = self._least_doubted(images, index, solved, poses, parts, candidates,
                                      geometry, diameter, batch, turn_inclination=True,
                                      rim_ceiling=cfg.search_rim_doubt)
        if not winners:
            return
        # A winner's landmarks, status and second pose are those of the rim it ends on (its
        # start's landmarks may give no pose); where that rim gives none, it is not taken.
        won = list(winners)
        ends = torch.stack([winners[k][1] for k in won])
        rim = self._pose_rim_found(images, index[won], ends[None], rows, diameter)[0]
        solution = self.solve(rim.landmarks, rim.weights, geometry, diameter, cup_index[won],
                              batch, refine=True)
        for row, k in enumerate(won):
            if not solution.valid[row]:
                continue
            # the second pose is the rim's other one, whichever the solver put first
            first, second = solution.pose[row], solution.alt_pose[row]
            turn = [float((ends[row, :2] - pose[:2]).abs().sum()) for pose in (first, second)]
            picks[k] = (rim.landmarks[row], rim.weights[row], solution, row)
            poses[k], alt_poses[k] = ends[row], first if turn[1] < turn[0] else second
            parts[solved.index(k)] = winners[k][2]

    def _pose_rim_found(self, images: list[Tensor], image: Tensor, poses: Tensor,
                        rows: Tensor, diameter: Tensor) -> list[RimLandmarks]:
        """The fine rim network's landmarks across the rims of ``poses`` ``(S, T, 5)`` deg /
        mm, one set per ``S`` (one network call for all); ``image`` ``(T,)`` each column's
        image, ``rows`` ``(B, 4)`` and ``diameter`` ``(B,)`` per image."""
        sets = len(poses)
        cups = image.repeat(sets)
        found = self._pose_rim_landmarks(images, cups, poses.flatten(0, 1), diameter[cups],
                                         Geometry.from_rows(rows[cups]))
        return [RimLandmarks(*fields) for fields in zip(
            *(field.chunk(sets) for field in found), strict=True)]

    def _least_doubted(self, images: list[Tensor], index: Tensor, solved: list[int],
                       poses: list[Tensor], parts: Tensor,
                       candidates: list[tuple[int, _Pick, Tensor]], geometry: Geometry,
                       diameter: Tensor, batch: int, turn_inclination: bool = False,
                       rim_ceiling: float | None = None
                       ) -> dict[int, tuple[_Pick, Tensor, Tensor]]:
        """Each candidate's start pose refined with the outline (:meth:`outline_refined`);
        for each cup, the one with the least doubt where it beats the cup's doubt by more
        than ``verify_margin`` (and, where it turns the rim's anteversion, or with
        ``turn_inclination`` its inclination, by more than ``verify_turn_deg``, the rim's
        doubt too) and, with a ``rim_ceiling``, its rim's doubt is at most that.

        Args:
            index: ``(K,)`` image of each cup; poses: per cup (deg / mm).
            solved: the cups with a pose; parts: ``(len(solved), 2)`` their doubts.
            candidates: ``(cup, pick, start)``, the start ``(5,)`` deg / mm.
            geometry, diameter: per image; batch: images.
        Returns:
            ``cup -> (pick, refined pose (5,), doubt (2,))`` for each cup a candidate beats.
        """
        if not candidates:
            return {}
        cfg = self.config
        rows = geometry_rows(geometry, batch)
        slot = {k: j for j, k in enumerate(solved)}
        cups = torch.tensor([k for k, _, _ in candidates], dtype=torch.long)
        own = torch.tensor([slot[k] for k in cups.tolist()], dtype=torch.long)
        refined = self._refined_picks(images, index[cups], [pick for _, pick, _ in candidates],
                                      [start for _, _, start in candidates], rows, diameter)
        usable = torch.isfinite(refined).all(-1) & self.in_theta_range(refined)
        their = self.pose_doubt(images, index[cups], refined.nan_to_num(), rows[index[cups]],
                                diameter[index[cups]])
        if cfg.verify_turn_deg is not None:
            # The dome's outline tells the centre, not the rim's orientation: a candidate
            # that turns the rim must explain the rim alone better by the margin.
            first = torch.stack([poses[k][:2] for k in cups.tolist()])
            turn = (refined[:, :2] - first).abs()
            turn[:, 1] = torch.minimum(turn[:, 1], 180.0 - turn[:, 1])  # inclination wraps
            turned = (turn[:, :2 if turn_inclination else 1] > cfg.verify_turn_deg).any(-1)
            usable &= ~turned | (their[:, 0] < parts[own, 0] - cfg.verify_margin)
        if rim_ceiling is not None:
            usable &= their[:, 0] <= rim_ceiling
        doubts = their.sum(-1).masked_fill(~usable, math.inf)
        best = (parts.sum(-1) - cfg.verify_margin).tolist()
        winners = {}
        for (k, pick, _), pose, cost, doubt in zip(candidates, refined, doubts.tolist(), their,
                                                   strict=True):
            if cost < best[slot[k]]:
                best[slot[k]] = cost
                winners[k] = (pick, pose, doubt)
        return winners

    def _source_candidates(self, sources: list[_Source], todo: Tensor, picks: list[_Pick],
                           geometry: Geometry, diameter: Tensor, cup_index: Tensor,
                           batch: int, known: list[tuple[int, _Pick, Tensor]] | None = None
                           ) -> list[tuple[int, _Pick, Tensor]]:
        """``(cup, pick, pose)`` of each distinct pose within ``max_theta_deg`` that
        ``sources`` solve for the cups ``todo`` ``(T,)``, less the cups' own landmarks:
        after the ``known`` candidates, less those that repeat one of them."""
        candidates = [(k, pick) for source in sources
                      for k, pick in self._solved_picks(source, todo, geometry, diameter,
                                                        cup_index, batch)
                      if pick[2].valid[pick[3]] and bool(self.in_theta_range(
                          pick[2].pose[pick[3]]))
                      # the cup's own landmarks again (its source rerun) would give its pose
                      and not _same_landmarks(pick, picks[k])]
        earlier = [(k, pick) for k, pick, _ in known or []]
        return [(k, pick, pick[2].pose[pick[3]])
                for k, pick in _distinct(earlier + candidates)]

    def _order_ambiguous(self, images: list[Tensor], index: Tensor, picks: list[_Pick],
                         solved: list[int], poses: list[Tensor], alt_poses: list[Tensor],
                         rows: Tensor, diameter: Tensor,
                         measured: dict[int, Tensor] | None = None) -> dict[int, Tensor]:
        """Each ambiguous cup's two poses, the one :meth:`pose_doubt` doubts less first (in
        place in ``poses`` and ``alt_poses``). Both give the cup's rim; they differ in the
        sphere's centre, so in where the dome's outline lies and in the rim's fine shape.

        Args:
            index: ``(K,)`` image of each cup; rows: ``(B, 4)`` each image's geometry;
            diameter: ``(B,)`` mm.
            measured: ``cup -> (2, 2)`` the doubts of a cup's two poses as they stand
                (:meth:`_outline_refine_picks` measured them), taken as they are.
        Returns:
            ``cup -> (2,)`` the doubt (rim, outline) of each ordered cup's first pose.
        """
        measured = measured or {}
        pairs = [k for k in solved if picks[k][2].ambiguous[picks[k][3]]
                 and bool(torch.isfinite(alt_poses[k]).all())]
        fresh = [k for k in pairs if k not in measured]
        if fresh:
            cups = index[fresh].repeat_interleave(2)
            both = torch.stack([pose for k in fresh for pose in (poses[k], alt_poses[k])])
            doubt = self.pose_doubt(images, cups, both, rows[cups], diameter[cups])
            measured = {**measured, **dict(zip(fresh, doubt.reshape(-1, 2, 2), strict=True))}
        firsts = {}
        for k in pairs:
            first, second = measured[k]
            if second.sum() < first.sum():
                poses[k], alt_poses[k] = alt_poses[k], poses[k]
                first = second
            firsts[k] = first
        return firsts

    def pose_doubt(self, images: list[Tensor], index: Tensor, poses: Tensor, geometry: Tensor,
                   diameter: Tensor, settled: bool = False) -> Tensor:
        """How little the fine rim network believes each pose: the mean Laplace negative
        log-likelihood ``|s| / sigma + log sigma`` (``s`` the column's landmark offset, px)
        that the image's edge lies where the pose puts it, over strips across the pose's rim
        (``rim_points`` normals), and over strips across the dome's half of its sphere's
        outline (as :meth:`outline_refined` samples it); their sum is the pose's doubt.

        Args:
            images: the batch's images; index ``(K,)`` image of each pose.
            poses: ``(K, 5)`` deg / mm; geometry: ``(K, 4)`` rows; diameter: ``(K,)`` mm.
            settled: measure the rim's offsets less the ellipse step that best explains them
                (:func:`cupnet.rim.settled_offsets`): whether a rim lies near the pose's,
                not exactly where it puts it.
        Returns:
            ``(K, 2)``: the rim's and the outline's; lower: the network finds the edge where
            the pose puts it (near it, for the rim, where ``settled``).
        """
        frame = Geometry.from_rows(geometry)
        on_rim, rims = self._rim_edges(images, index, poses, frame, diameter)
        return torch.stack([_rim_doubt(on_rim, rims, settled),
                            self._outline_doubt(images, index, poses, frame, diameter)], -1)

    def _rim_edges(self, images: list[Tensor], index: Tensor, poses: Tensor, frame: Geometry,
                   diameter: Tensor) -> tuple[RimLandmarks, Tensor]:
        """What the rim part of :meth:`pose_doubt` measures, for ``poses`` ``(K, 5)`` deg / mm
        in the images ``index`` ``(K,)``; frame: fields ``(K,)``; diameter ``(K,)`` mm: the
        fine rim network's landmarks across each pose's rim (``(K, rim_points)`` columns)
        and the rim ellipses ``(K, 5)`` (cx, cy, a, b px, alpha deg)."""
        rims = ellipse_of_pose(poses, diameter, frame)
        return self.rim_landmarks(images, index, rims, passes=1), rims

    def _outline_doubt(self, images: list[Tensor], index: Tensor, poses: Tensor,
                       frame: Geometry, diameter: Tensor) -> Tensor:
        """The outline part ``(K,)`` of :meth:`pose_doubt` of ``poses`` ``(K, 5)`` deg / mm in
        the images ``index`` ``(K,)``; frame: fields ``(K,)``; diameter ``(K,)`` mm."""
        on_dome, keep = self._outline_landmarks(images, index, pose_to_radians(poses),
                                                diameter.to(poses) / 2, frame)
        return ((laplace_nll(on_dome.offset, on_dome.sigma) * keep).sum(-1)
                / keep.sum(-1).clamp_min(1))

    def outline_refined(self, images: list[Tensor], index: Tensor, poses: Tensor,
                        points: Tensor, weights: Tensor, residual: Tensor, geometry: Tensor,
                        diameter: Tensor) -> Tensor:
        """Solved poses refined with the dome's outline (at most ``outline_passes`` passes; a
        cup leaves once a pass moves it by less than ``outline_settled``).

        Each pass samples the fine rim stage's strips across the dome's half of the outline
        of the pose's sphere (:func:`cupnet.outline.sphere_outline`, ``rim_points``
        normals) and takes the network's landmarks there (beyond ``outline_min_side``, away
        from the arc's ends, inside the image, within three robust standard deviations of
        the others' distance to the outline), weighted ``outline_weight / sigma^2``; the
        solver fits them beside the rim landmarks, weighted by their residual's inverse
        variance (times ``outline_inner_rim_weight`` over the dome's shadow;
        :func:`cupnet.pose.refine_pose_with_outline`); with ``outline_rim_resample``, the rim
        landmarks too are the network's across the pose's own rim, taken anew each pass and
        weighted ``1 / sigma^2`` (those off the others' offset left out). A pose that leaves
        ``0 < h < sdd``, or crosses ``max_theta_deg``, keeps its rim-only value.

        Args:
            images: the batch's images; index ``(K,)`` image of each cup.
            poses: ``(K, 5)`` deg / mm; points ``(K, N, 2)`` px, weights ``(K, N)`` (mean 1)
            and residual ``(K,)`` px: the rim landmarks the poses were solved from.
            geometry: ``(K, 4)`` rows (sdd, spacing, u0, v0); diameter ``(K,)`` mm.
        Returns:
            ``(K, 5)`` deg / mm.
        """
        cfg = self.config
        radius = diameter.to(poses) / 2
        rim_weights = weights / residual.clamp_min(0.3)[:, None] ** 2
        pose = pose_to_radians(poses)
        active = torch.ones(len(pose), dtype=torch.bool, device=pose.device)
        twin = torch.arange(len(pose), device=pose.device)  # the row each row continues in
        for _ in range(cfg.outline_passes):
            rows = active.nonzero()[:, 0]
            if len(rows) == 0:
                break
            moved = self._outline_pass(images, index[rows], pose[rows], points[rows],
                                       rim_weights[rows], radius[rows], geometry[rows])
            step = pose_to_degrees(moved) - pose_to_degrees(pose[rows])
            pose[rows] = moved
            settled = cfg.outline_settled * step.new_tensor(TARGET_ACCURACY)
            active[rows] = ~(step.abs() < settled).all(-1)
            if cfg.outline_rim_resample:
                # A pass then depends on the pose alone: rows of one image that have come
                # together (the verification's candidates often do) are refined once.
                _merge_twins(pose_to_degrees(pose), index, active, twin)
        pose = pose[_representatives(twin)]
        refined = pose_to_degrees(canonical_pose(pose))
        usable = torch.isfinite(refined).all(-1) & (refined[:, 4] > 0) & (
            refined[:, 4] < geometry[:, 0])
        if cfg.max_theta_deg is not None:  # nor one the anteversion limit would have refused
            usable &= self.in_theta_range(refined) | (poses[:, 0] > cfg.max_theta_deg)
        return torch.where(usable[:, None], refined, poses)

    def _outline_landmarks(self, images: list[Tensor], index: Tensor, pose: Tensor,
                           radius: Tensor, frame: Geometry) -> tuple[RimLandmarks, Tensor]:
        """The fine rim network's landmarks across the dome's half of each pose's sphere
        outline (``rim_points`` normals), and which to keep ``(K, n)``: beyond
        ``outline_min_side``, inside the image, away from the arc's ends.

        Args:
            images: the batch's images; index ``(K,)`` image of each pose.
            pose: ``(K, 5)`` rad / mm; radius: ``(K,)`` mm; frame: fields ``(K,)``.
        """
        cfg = self.config
        outline, normals, side = sphere_outline(pose, radius, frame, cfg.rim_points,
                                                dome_only=True)
        net = self.fine_rim()
        found = self._strip_landmarks(net, images, index, outline, normals,
                                      strip_offsets(cfg.rim_samples, cfg.rim_step,
                                                    device=outline.device))
        keep = (side > cfg.outline_min_side) & _inside(found.landmarks, images, index)
        # The strip is an open arc: the rim network's columns near its ends see the other
        # end through its circular padding.
        ends = net.columns_seen
        keep[:, :ends] = False
        keep[:, -ends:] = False
        return found, keep

    def _outline_pass(self, images: list[Tensor], index: Tensor, pose: Tensor, points: Tensor,
                      rim_weights: Tensor, radius: Tensor, geometry: Tensor) -> Tensor:
        """One pass of :meth:`outline_refined` on ``K`` cups: poses ``(K, 5)`` rad / mm in
        and out."""
        cfg = self.config
        frame = Geometry.from_rows(geometry)
        found, keep = self._outline_landmarks(images, index, pose, radius, frame)
        landmarks = found.landmarks
        keep = _consistent(outline_distances(pose[:, 2:5], landmarks, radius, geometry)[0],
                           keep)
        outline_weights = torch.where(keep, cfg.outline_weight / found.sigma**2, 0.0)
        if cfg.outline_rim_resample:
            rim = self._pose_rim_landmarks(images, index, pose_to_degrees(pose), 2 * radius,
                                           frame)
            points = rim.landmarks
            usable = _consistent(rim.offset, _inside(points, images, index))
            rim_weights = torch.where(usable, 1 / rim.sigma**2, 0.0)
        inner = over_dome(points, pose, frame)
        return refine_pose_with_outline(
            pose, points, torch.where(inner, cfg.outline_inner_rim_weight * rim_weights,
                                      rim_weights), landmarks, outline_weights, frame, radius)

    def _strip_landmarks(self, net: RimNet, images: list[Tensor] | Tensor, index: Tensor,
                         points: Tensor, normals: Tensor, offsets: Tensor) -> RimLandmarks:
        """``net``'s landmarks on strips across ``points`` ``(K, n, 2)`` px along ``normals``
        ``(K, n, 2)`` at ``offsets`` ``(S,)`` or ``(K, S)`` px, in the images ``index``
        ``(K,)``."""
        strips = sample_strips(images, index, points, normals, offsets)
        if strips.shape[0] == 0:  # no cup: no network call (BatchNorm needs a batch)
            points, normals = points.double(), normals.double()  # as strip_landmarks's
            empty = points.new_zeros(0, points.shape[1])
            return RimLandmarks(points, empty, empty, empty, points, normals,
                                points.new_zeros(0, 1))
        return strip_landmarks(*net(strips.to(self.dtype)), points, normals, offsets)

    def _pose_rim_landmarks(self, images: list[Tensor], index: Tensor, poses: Tensor,
                            diameter: Tensor, frame: Geometry) -> RimLandmarks:
        """The fine rim network's landmarks across each pose's own rim (``rim_points``
        normals). poses: ``(K, 5)`` deg / mm; diameter: ``(K,)`` mm; frame: fields ``(K,)``."""
        return self.rim_landmarks(images, index, ellipse_of_pose(poses, diameter, frame),
                                  passes=1)

    def refiner_fit(self, points: Tensor, weights: Tensor, frames: Tensor) -> Tensor:
        """The ellipses ``(K, 5)`` a refiner pass's landmarks ``(K, n, 2)`` and weights
        ``(K, n)`` give the next stage (:func:`usable_fit`, the frame's ellipse where the fit
        fails), grown to at least ``reframe_min_scale`` of the semi-major axis of the ellipse
        each crop frame ``(K, 5)`` was made for."""
        framed = _frame_ellipse(frames, self.config)
        ellipse = usable_fit(points, weights, framed)
        if self.config.reframe_min_scale is None:
            return ellipse
        return grown_to(ellipse, self.config.reframe_min_scale * framed[:, 2])

    def _grown_rim_source(self, images: list[Tensor], geometry: Geometry, diameter: Tensor,
                          cup_index: Tensor, start: Tensor
                          ) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
        """:meth:`detect`'s last landmark source: the fine rim stage framed on the coarse
        stage's fit from each start ``(K, 5)`` enlarged (never shrunk) to ``grown_rim_scale``
        times the smallest rim the cup can make, its radius over the pixel spacing (the
        magnification is at least 1). Landmarks that give no pose often follow a femoral head's
        outline, too small for the cup (the solver then puts it below the detector), and the
        rim lies outside the coarse stage's reach from there."""
        def grown(todo: Tensor) -> tuple[Tensor, Tensor]:
            image = cup_index[todo, 0]
            ellipse = self._grown(start[todo], image, geometry, diameter, len(images))
            return self.coarse_framed_rim_landmarks(images, image, ellipse)[:2]

        return grown

    def _grown(self, ellipses: Tensor, image: Tensor, geometry: Geometry, diameter: Tensor,
               batch: int) -> Tensor:
        """``ellipses`` ``(K, 5)`` in the images ``image`` ``(K,)`` enlarged (never shrunk) to
        ``grown_rim_scale`` times the smallest rim each cup can make, its radius over the
        pixel spacing (the magnification is at least 1); geometry, diameter ``(B,)`` per
        image of ``batch``."""
        spacing = geometry_rows(geometry, batch)[image, 1]
        smallest = (diameter[image] / 2 / spacing).to(ellipses)  # px
        return grown_to(ellipses, self.config.grown_rim_scale * smallest)

    def rim_alternatives(self) -> list[RimAlternative]:
        """The fine rim stage's other starts this model has: framed on the coarse stage's
        fit (with a coarse rim stage), from the thin-rim hypotheses (with a
        ``thin_rim_gate``; after the refiner's own landmarks in :meth:`detect`)."""
        cfg = self.config
        alternatives = []
        if self.coarse_rim is not None:
            alternatives.append(RimAlternative(self.coarse_framed_rim_landmarks,
                                               cfg.coarse_rim_gate, 0.0, after_refiner=False))
        if cfg.thin_rim_gate is not None and cfg.thin_rim_angles > 0:
            alternatives.append(RimAlternative(self.thin_rim_landmarks, cfg.thin_rim_gate,
                                               cfg.thin_rim_margin, after_refiner=True))
        return alternatives

    def rim_sources(self, images: list[Tensor] | Tensor, index: Tensor, start: Tensor,
                    refiner: _Source) -> list[_Source]:
        """:meth:`detect`'s landmark sources of a model with a rim stage, in the order it
        tries them on the cups still without a pose in range: the fine rim stage from the
        refiner's ellipses ``start`` ``(K, 5)`` (:meth:`trusted_rim_landmarks`), the
        :meth:`rim_alternatives` tried before the refiner's own landmarks (``refiner``),
        those, and the alternatives tried after them (not the grown-rim source).

        Args:
            images: the batch's images; index: ``(K,)`` image of each cup.
        Returns:
            each a function: cups ``(k,)`` -> their landmarks ``(k, n, 2)`` px and weights
            ``(k, n)``.
        """
        alternatives = self.rim_alternatives()
        return [_source_from(self.trusted_rim_landmarks, images, index, start),
                *[_source_from(alt.landmarks, images, index, start)
                  for alt in alternatives if not alt.after_refiner],
                refiner,
                *[_source_from(alt.landmarks, images, index, start)
                  for alt in alternatives if alt.after_refiner]]

    def trusted_rim_landmarks(self, images: list[Tensor] | Tensor, index: Tensor, start: Tensor
                              ) -> tuple[Tensor, Tensor]:
        """The fine rim stage's landmarks ``(K, n, 2)`` and weights ``(K, n)`` from the
        refiner's ellipses ``start`` ``(K, 5)``; where their mean ``log sigma`` exceeds
        ``coarse_rim_gate`` (``thin_rim_gate``), those framed on the coarse stage's fit (the
        thin-rim hypotheses' best) instead if the fine network trusts them more (by
        ``thin_rim_margin`` for the thin-rim hypotheses). Either
        rescues a rim the refiner missed, costs more rim passes, and would only blur a right
        start."""
        plain = self.rim_landmarks(images, index, start)
        doubt = plain.sigma.log().mean(-1)
        landmarks, weights = plain.landmarks, plain.weights
        for alt in self.rim_alternatives():
            if alt.gate is None:
                continue
            redo = (doubt > alt.gate).nonzero()[:, 0]
            if len(redo) == 0:
                continue
            rim = alt.landmarks(images, index[redo], start[redo])
            rim_doubt = rim.sigma.log().mean(-1)
            better = rim_doubt < doubt[redo] - alt.margin
            rows = redo[better]
            landmarks, weights, doubt = landmarks.clone(), weights.clone(), doubt.clone()
            landmarks[rows], weights[rows] = rim.landmarks[better], rim.weights[better]
            doubt[rows] = rim_doubt[better]
        return landmarks, weights


def _on_cpu(images: list[Tensor]) -> list[Tensor]:
    """``images`` (any shapes) on the CPU, copied in this thread (so after the work queued
    before on its stream), in one copy where they share a shape."""
    if not images or images[0].device.type == "cpu":
        return list(images)
    if all(image.shape == images[0].shape for image in images):
        return list(torch.stack(images).cpu())
    return [image.cpu() for image in images]


def takes_pick(valid: Tensor, in_range: Tensor, solved_before: Tensor, refiner: bool
               ) -> Tensor:
    """Which cups take a landmark source's solution ``(K,)`` bool, as :meth:`CupNet.detect`
    and :func:`cupnet.batched.batched_cups` pick: a pose within ``max_theta_deg``
    (``in_range``, the search for the cup then ends); else, while the cup has no pose
    (``solved_before`` false), any pose (``valid``), or the refiner's failure (its ellipse is
    the one its mask shows)."""
    return in_range | (~solved_before & (valid | refiner))


def _cropped(images: list[Tensor], geometry: Geometry,
             crops: list[tuple[int, int, int] | None]) -> tuple[list[Tensor], Geometry]:
    """``images`` ``(1, H, W)`` cut to their ``crops`` (``(u0, v0, side)`` or None: whole),
    and ``geometry`` with each principal point where its crop puts it."""
    rows = geometry_rows(geometry, len(images))  # a new tensor: the caller's is kept
    out = []
    for i, (image, crop) in enumerate(zip(images, crops, strict=True)):
        if crop is None:
            out.append(image)
            continue
        u0, v0, side = crop
        out.append(image[:, v0:v0 + side, u0:u0 + side].contiguous())
        rows[i, 2:] -= rows.new_tensor([u0, v0])
    return out, Geometry.from_rows(rows)


def _resized(images: list[Tensor], geometry: Geometry,
             fields: list[tuple[float, float, float] | None], factors: list[float]
             ) -> tuple[list[Tensor], Geometry, list[tuple[float, float, float] | None]]:
    """``images`` ``(1, H, W)`` resized by their ``factors`` (1: kept;
    :func:`cupnet.crops.resized`), with ``geometry`` and the round ``fields`` ``(cx, cy, r)``
    where the resizing puts them: the pixel spacing divided by the factor, a point ``u``
    at ``(u + 0.5) f - 0.5`` (:func:`cupnet.crops.rescaled_pixels`)."""
    rows = geometry_rows(geometry, len(images))  # a new tensor: the caller's is kept
    scale = rows.new_tensor(factors)
    rows[:, 1] /= scale
    rows[:, 2:] = rescaled_pixels(rows[:, 2:], scale[:, None])
    fields = [field if field is None else (rescaled_pixels(field[0], f),
                                           rescaled_pixels(field[1], f), field[2] * f)
              for field, f in zip(fields, factors, strict=True)]
    return ([image if f == 1 else resized(image, f)
             for image, f in zip(images, factors, strict=True)],
            Geometry.from_rows(rows), fields)


def _source_from(method: Callable, images: list[Tensor] | Tensor, index: Tensor, start: Tensor
                 ) -> _Source:
    """A landmark source: cups ``todo`` ``(k,)`` -> the landmarks and weights ``method``
    (images, their indices, start ellipses) gives from their ``start`` ``(K, 5)``."""
    return lambda todo: method(images, index[todo], start[todo])[:2]


def _frame_ellipse(frames: Tensor, config: CupNetConfig) -> Tensor:
    """An ellipse a crop frame ``(K, 5)`` fits: the fallback where a fit fails.

    Its centre, angle and major axis are those the frame was made for; its minor axis is too
    where the crop was stretched (within ``crop_max_stretch``), else ``crop_min_ratio a``:
    whatever it is, :meth:`CupNet.frames` of it gives the same frame back.
    """
    major = frames[:, 2:3] * config.crop_fill / 2
    minor = frames[:, 3:4] * config.crop_fill * config.crop_min_ratio / 2
    return torch.cat([frames[:, :2], major, minor.clamp_max(major), frames[:, 4:]], -1).double()


def _merge_twins(poses: Tensor, index: Tensor, active: Tensor, twin: Tensor) -> None:
    """Each active row of ``poses`` ``(K, 5)`` deg / mm within ``_OUTLINE_TWINS`` of another
    row of its image ``index`` ``(K,)`` (an earlier one, or one already settled) that
    continues in itself: made inactive, its ``twin`` that row (in place)."""
    near = ((poses[:, None] - poses[None]).abs() < poses.new_tensor(_OUTLINE_TWINS)).all(-1)
    near &= index[:, None] == index[None]
    # Row by row, each depending on the last: on the CPU (the same tensors there), not with
    # a device sync a row.
    near, on_cpu_active, on_cpu_twin = near.cpu(), active.cpu(), twin.cpu()
    rows = torch.arange(len(poses))
    for row in on_cpu_active.nonzero()[:, 0].tolist():
        kept = (near[row] & (on_cpu_twin == rows) & (rows != row)
                & ((rows < row) | ~on_cpu_active))
        if kept.any():
            on_cpu_twin[row] = int(kept.nonzero()[0, 0])
            on_cpu_active[row] = False
    active.copy_(on_cpu_active)
    twin.copy_(on_cpu_twin)


def _representatives(twin: Tensor) -> Tensor:
    """``(K,)`` the row each row's chain of ``twin`` ``(K,)`` ends in."""
    while not torch.equal(twin[twin], twin):
        twin = twin[twin]
    return twin


def _inside(points: Tensor, images: list[Tensor] | Tensor, index: Tensor) -> Tensor:
    """``(K, n)``: which of ``points`` ``(K, n, 2)`` px lie inside their images ``index``
    (a ``(B, 1, H, W)`` batch's all share one size)."""
    size = (points.new_tensor(images.shape[-1:-3:-1]).expand(len(index), 2)
            if isinstance(images, Tensor) else
            torch.tensor([images[int(i)].shape[-1:-3:-1] for i in index], dtype=points.dtype))
    return (points >= 0).all(-1) & (points <= size[:, None] - 1).all(-1)


def _consistent(values: Tensor, keep: Tensor) -> Tensor:
    """``keep`` ``(K, n)`` less the ``values`` ``(K, n)`` px more than three robust standard
    deviations (at least 1 px) from the median of each row's kept ones: a landmark on
    another edge than the rest."""
    values = values.masked_fill(~keep, math.nan)
    middle = values.nanmedian(-1, keepdim=True).values
    spread = 1.4826 * (values - middle).abs().nanmedian(-1, keepdim=True).values
    return keep & ((values - middle).abs() <= (3 * spread).clamp_min(1.0))


def _rim_doubt(on_rim: RimLandmarks, rims: Tensor, settled: bool) -> Tensor:
    """``(K,)`` the rim's part of :meth:`CupNet.pose_doubt` from the landmarks across the
    rims ``(K, 5)`` (cx, cy, a, b px, alpha deg), their offsets ``settled`` or as they lie."""
    offset = on_rim.offset
    if settled:
        offset = settled_offsets(offset, on_rim.sigma, rims, on_rim.normals)
    return laplace_nll(offset, on_rim.sigma).mean(-1)


def _doubtful(solved: list[int], parts: Tensor, gate: float,
              part_gate: float | None = None) -> Tensor:
    """``(T,)`` the cups of ``solved`` whose doubt ``parts`` ``(len(solved), 2)`` sums to
    ``gate`` or more, or with a part at ``part_gate`` or more."""
    part_gate = math.inf if part_gate is None else part_gate
    return torch.tensor([k for k, total, part in zip(solved, parts.sum(-1).tolist(),
                                                     parts.amax(-1).tolist(), strict=True)
                         if total >= gate or part >= part_gate], dtype=torch.long)


def _found_sources(found: list[RimLandmarks], todo: Tensor, cups: int) -> list[_Source]:
    """One landmark source per set of ``found`` (each ``(T, n)`` rows, one per cup of
    ``todo`` ``(T,)`` among ``cups``)."""
    row = torch.full((cups,), -1, dtype=torch.long)
    row[todo] = torch.arange(len(todo))
    return [lambda asked, rim=rim: (rim.landmarks[row[asked]], rim.weights[row[asked]])
            for rim in found]


def _same_landmarks(pick: _Pick, other: _Pick) -> bool:
    """Both picks hold the same landmarks and weights."""
    return (pick[0].shape == other[0].shape and torch.equal(pick[0], other[0])
            and torch.equal(pick[1], other[1]))


def _distinct(candidates: list[tuple[int, _Pick]]) -> list[tuple[int, _Pick]]:
    """``(cup, pick)`` pairs without the picks whose pose repeats an earlier one of the same
    cup (within 0.2 deg, 0.2 mm and 1 mm in h): sources often find the same rim."""
    tolerance = torch.tensor([0.2, 0.2, 0.2, 0.2, 1.0], dtype=torch.float64)
    kept: list[tuple[int, _Pick]] = []
    for k, pick in candidates:
        pose = pick[2].pose[pick[3]]
        if not any(j == k and ((other[2].pose[other[3]] - pose).abs() <= tolerance).all()
                   for j, other in kept):
            kept.append((k, pick))
    return kept


def mirrored_ellipses(ellipses: Tensor, width: Tensor) -> Tensor:
    """Ellipses ``(..., 5)`` (cx, cy, a, b, alpha_deg) px of an image mirrored left to right,
    in the image itself, ``width`` px (broadcast over ``(...)``): pixel centres at integers,
    so ``cx -> width - 1 - cx``, and the axis angle turns to ``180 - alpha`` (mod 180)."""
    out = ellipses.clone()
    out[..., 0] = width - 1 - ellipses[..., 0]
    out[..., 4] = (180.0 - ellipses[..., 4]) % 180.0
    return out


def grown_to(ellipses: Tensor, major: Tensor) -> Tensor:
    """Ellipses ``(K, 5)`` scaled about their centres (axis ratio and angle kept) so their
    semi-major axis is at least ``major`` ``(K,)`` px; never shrunk."""
    scale = (major / ellipses[:, 2]).clamp_min(1.0)
    return torch.cat([ellipses[:, :2], ellipses[:, 2:4] * scale[:, None], ellipses[:, 4:]], -1)


def usable_fit(points: Tensor, weights: Tensor, fallback: Tensor) -> Tensor:
    """Weighted ellipse fit ``(K, 5)`` of landmarks ``(K, N, 2)``, ``fallback`` ``(K, 5)``
    where the fit fails or collapses (semi-major axis under half a pixel)."""
    ellipse = fit_ellipse(points, weights, on_error="flag").params
    usable = torch.isfinite(ellipse).all(-1) & (ellipse[:, 2] > 0.5)
    return torch.where(usable[:, None], ellipse, fallback.to(ellipse))


def _read_checkpoint(path: Path) -> tuple[dict[str, Tensor], dict | None]:
    """State dict and model config (when the file holds one) of a checkpoint.

    safetensors, or a ``torch.load(weights_only=True)`` file: a plain state dict, or a
    Lightning checkpoint whose ``hyper_parameters["model"]`` is the config.
    """
    if not path.exists():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        if _is_safetensors(path):  # by content: save_model writes it under any name
            from safetensors.torch import load_file

            return load_file(str(path)), None
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - each reader fails in its own ways on a bad file
        raise ValueError(f"{path}: not a readable checkpoint (safetensors, or a weights-only "
                         "torch file; corrupt, cut short or another format: "
                         f"{whole_reason(exc, 300)})") from exc
    config = None
    if isinstance(state, dict) and "state_dict" in state:
        config = (state.get("hyper_parameters") or {}).get("model")
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(f"{path}: holds no state dict of tensors (a {type(state).__name__})")
    return state, config


def _is_safetensors(path: Path) -> bool:
    """Whether ``path`` starts as safetensors does: an 8-byte little-endian header length,
    then the header's JSON (a torch file starts with a zip's or a pickle's magic)."""
    with path.open("rb") as f:
        start = f.read(9)
    return len(start) == 9 and start[8:] == b"{"


def config_path(checkpoint: Path) -> Path:
    """The JSON model config stored beside a checkpoint (same stem)."""
    return checkpoint.with_suffix(".json")


def save_model(model: CupNet, checkpoint: str | Path) -> Path:
    """Write ``model`` as safetensors plus its JSON config beside it; returns the weights path."""
    from safetensors.torch import save_file

    checkpoint = Path(checkpoint)
    if checkpoint.is_dir():  # safetensors had failed on it in a traceback
        raise ValueError(f"{checkpoint} is a folder; give the weights file's name, such as "
                         f"{checkpoint / 'cupnet.safetensors'}")
    checkpoint.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    save_file(state, str(checkpoint))
    config = asdict(model.config)
    config_path(checkpoint).write_text(json.dumps(config, indent=2) + "\n")
    # safetensors writes its file readable by its owner alone (0600); the JSON beside it has
    # the umask's mode, which a model shared with other users needs too.
    shutil.copymode(config_path(checkpoint), checkpoint)
    return checkpoint


def load_model(checkpoint: str | Path | None = None) -> CupNet:
    """A CupNet in eval mode from a checkpoint; None loads the shipped default.

    Accepts safetensors (with the JSON config beside it) or a file readable with
    ``torch.load(weights_only=True)``: a plain state dict (JSON config beside it) or a
    Lightning checkpoint of :class:`train.module.CupNetModule` (its ``model.`` keys and
    hyper-parameters); loading never runs code from the file. Without a config the default
    :class:`CupNetConfig` is used.
    """
    path = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
    state, stored = _read_checkpoint(path)
    if any(k.startswith("model.") for k in state):
        state = {k[len("model."):]: v for k, v in state.items() if k.startswith("model.")}
    cfg_file = config_path(path)
    if cfg_file.exists():
        try:
            stored = json.loads(cfg_file.read_text())
        except (ValueError, UnicodeDecodeError) as exc:
            raise ValueError(f"{cfg_file}: the model config beside {path.name} is no JSON "
                             f"({exc})") from exc
    config = CupNetConfig.from_dict(stored or {})
    config.encoder_weights = None  # the checkpoint holds the trained encoders
    model = CupNet(config)
    misfit = _state_misfit(model.state_dict(), state)
    if misfit:
        source = (f"its config {cfg_file.name}" if cfg_file.exists() else "its own config"
                  if stored else f"the default config (no {cfg_file.name} beside it)")
        raise ValueError(f"{path}: the weights do not fit {source}: {misfit}")
    model.load_state_dict(state)
    return model.eval()


def _state_misfit(expected: dict[str, Tensor], given: dict[str, Tensor]) -> str | None:
    """How the tensors ``given`` fail to fit a model whose state dict is ``expected`` (None
    where they fit): the counts of tensors missing, unexpected and of another shape, with
    the first of each (load_state_dict's own message lists every one, a hundred lines)."""
    missing = [k for k in expected if k not in given]
    unexpected = [k for k in given if k not in expected]
    reshaped = [f"{k} {tuple(given[k].shape)} for {tuple(expected[k].shape)}" for k in expected
                if k in given and given[k].shape != expected[k].shape]
    parts = [f"{len(keys)} {what} (first: {keys[0]})" for keys, what in (
        (missing, "missing"), (unexpected, "unexpected"), (reshaped, "of another shape"))
        if keys]
    return "; ".join(parts) or None
