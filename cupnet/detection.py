"""One detected cup: the record ``CupNet.detect``, ``cupnet predict`` and ``cupnet solve`` share.

Kept apart from :mod:`cupnet.model` so that landmark-only tools load without the network's
libraries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np


@dataclass
class CupDetection:
    """One detected cup (public units).

    Attributes:
        pose: ``(5,)`` (theta_deg, phi_deg, k_mm, l_mm, h_mm); NaN where ``status`` is an error.
        alt_pose: ``(5,)`` the second in-range pose where ``ambiguous``, else None.
        ambiguous: both circle poses of the ellipse lie in range: of the landmarks' fit, or
            (from the network) of ``pose``'s rim (:func:`cupnet.model.with_second_poses`).
        ellipse: ``(5,)`` (cx, cy, a, b, alpha_deg) original-image pixels: the rim ellipse
            of ``pose`` where the model refined it with the dome's outline or the pose was
            solved from given landmarks (:func:`cupnet.solve_cli.solve_cup`), else the
            landmarks' weighted fit.
        landmarks: ``(N, 2)`` original-image pixels (u, v).
        weights: ``(N,)`` relative landmark weights (only their ratios count in the fit
            and pose): from the rim network each landmark's precision (inverse variance)
            scaled to a mean of 1, from the refiner's mask in [0, 1], given landmarks 1.
        residual_px: weighted RMS distance of the landmarks to the rim of ``pose`` (px).
        mask: ``(H, W)`` opening probability in original-image pixels, or None.
        status: ``"ok"``, ``"ambiguous"`` or ``"error: <reason>"``.
        score: mean locator probability of the cup's component.
        outline: ``(M, 2)`` original-image pixels along the dome's half of the outline of
            ``pose``'s sphere where the model refined the pose with it (for checking by eye
            that it follows the dome), else None.
        doubt: how little the model's rim network believes ``pose``: the larger of the mean
            negative log-likelihoods of the edges it finds across the pose's rim and dome
            outline (:meth:`cupnet.model.CupNet.pose_doubt`; lower is better, true poses
            mostly below 1), or None where not measured (no rim stage, landmarks given).
        check: ``doubt`` is at or above the model's ``check_doubt``, or the pose lies beyond
            its ``max_theta_deg`` or within the cup's radius of the detector (given
            landmarks: they lie off the solved rim, or its pose lies near the source or the
            detector, see :func:`cupnet.solve_cli.solve_cup`): look at this
            cup's overlay before trusting it (most gross failures are flagged; see README).
            None where not measured (a model without a rim stage or its dome-outline
            refinement).
        metal_bright: the image shows metal bright, as ``CupNetConfig.metal`` declares it
            (``"bright"``) or, with ``"auto"``, as judged from the rims of the image's
            cups (:meth:`CupNet.with_image_displays`: one display for all of them, a
            near-tie by its sign); False: metal dark; None where not judged (landmarks
            given). Each look of :meth:`CupNet.detect` judged the display from its own
            locator blobs and turned the image over by that before placing the rims.
        pose_sd: ``(5,)`` standard errors of ``pose`` (deg, deg, mm, mm, mm) from the
            scatter of given landmarks about the solved rim
            (:func:`cupnet.pose.pose_standard_errors`), or None: not given for the network's
            landmarks, whose errors are correlated along the rim, so that such errors would
            cover 42-78 % of the real ones where they claim 95 % (docs/training.md, item 50).
        noise: the image's noise (:func:`cupnet.denoise.noise_sigma`, display units [0, 1])
            where it exceeds the model's ``denoise_above``, else None.
        denoised: the image was taken through non-local means first, its noise exceeding
            the model's ``denoise_above``; None where not measured.
        enlarged: the factor the image (or its round field's square) was enlarged by before
            the networks, its shorter side under the model's ``enlarge_below``; None where
            it was not.
        reduced: the factor (< 1) the image (or its round field's square) was reduced by
            before the networks, its shorter side over the model's ``reduce_above``; None
            where it was not.
    """

    pose: np.ndarray
    alt_pose: np.ndarray | None
    ambiguous: bool
    ellipse: np.ndarray
    landmarks: np.ndarray
    weights: np.ndarray
    residual_px: float
    mask: np.ndarray | None = None
    status: str = "ok"
    score: float = 1.0
    outline: np.ndarray | None = None
    doubt: float | None = None
    check: bool | None = None
    metal_bright: bool | None = None
    pose_sd: np.ndarray | None = None
    noise: float | None = None
    denoised: bool | None = None
    enlarged: float | None = None
    reduced: float | None = None


def moved(cup: CupDetection, offset: tuple[int, int], shape: tuple[int, int]
          ) -> CupDetection:
    """``cup`` found in a crop whose top-left pixel is ``offset`` ``(u, v)`` of an image of
    ``shape`` ``(H, W)``, in that image's pixels (the pose, in mm about the principal point,
    is the same in both)."""
    du, dv = offset
    ellipse = cup.ellipse.copy()
    ellipse[:2] += (du, dv)
    mask = None
    if cup.mask is not None:
        mask = np.zeros(shape, cup.mask.dtype)
        mask[dv:dv + cup.mask.shape[0], du:du + cup.mask.shape[1]] = cup.mask
    return replace(cup, ellipse=ellipse, landmarks=cup.landmarks + (du, dv), mask=mask,
                   outline=None if cup.outline is None else cup.outline + (du, dv))


def unresized(cup: CupDetection, factor: float, shape: tuple[int, int]) -> CupDetection:
    """``cup`` found in an image resized ``factor`` times (:func:`cupnet.crops.resized`), in
    the pixels of that image before, of ``shape`` ``(H, W)``: a pixel ``u`` there lies at
    ``(u + 0.5) / factor - 0.5`` here, lengths divide by ``factor`` (the pose, in mm, is the
    same in both), the mask is resampled to ``shape`` (area-averaged where it shrinks);
    ``enlarged`` (``factor > 1``) or ``reduced`` (``< 1``) says ``factor``."""
    def back(points: np.ndarray) -> np.ndarray:
        return (points + 0.5) / factor - 0.5

    ellipse = cup.ellipse.copy()
    ellipse[:2], ellipse[2:4] = back(ellipse[:2]), ellipse[2:4] / factor
    mask = (None if cup.mask is None
            else cv2.resize(cup.mask, shape[::-1], interpolation=cv2.INTER_AREA))
    return replace(cup, ellipse=ellipse, landmarks=back(cup.landmarks),
                   residual_px=cup.residual_px / factor, mask=mask,
                   outline=None if cup.outline is None else back(cup.outline),
                   **({"enlarged": factor} if factor > 1 else {"reduced": factor}))


def found_cup_status(status: str) -> str:
    """The status of a cup the model found, from its pose's ``status`` (the solver's): an
    error then says that the cup was found and its rim gave no pose, before the solver's
    reason. That reason's own hint (check the cup diameter, SDD and pixel spacing) fits a
    run whose every cup fails so; for one odd cup the rim found is the likelier fault (a
    femoral head's contour, a thin rim at the wrong angle)."""
    if not status.startswith("error: "):
        return status
    return f"error: no pose from the rim found: {status.removeprefix('error: ')}"


def failed(cup: CupDetection) -> bool:
    """Whether ``cup`` gave no pose: an ``error`` status, its pose NaN (the solver sets
    both together)."""
    return cup.status.startswith("error")


def distinct_cups(detections: list[CupDetection], tolerance: float = 0.1
                  ) -> list[CupDetection]:
    """One image's ``detections`` less the repeats, in their order.

    Two detections whose ellipses' centres and semi-axes agree within ``tolerance`` of the
    larger major semi-axis are one cup found twice (a thin rim's locator blob can break in
    two; where the locator's windows overlap an oblong image, both may see it): the one kept
    has a pose rather than an error, then the lower doubt (None counting as the highest).
    """
    def rank(det: CupDetection) -> tuple[bool, float]:
        return failed(det), math.inf if det.doubt is None else det.doubt

    kept: list[CupDetection] = []
    for det in sorted(detections, key=rank):
        if not any(repeats(det, other, tolerance) for other in kept):
            kept.append(det)
    return [det for det in detections if any(det is k for k in kept)]


def repeats(one: CupDetection, other: CupDetection, tolerance: float = 0.1) -> bool:
    """Whether detections ``one`` and ``other`` are one cup found twice: their ellipses'
    centres and semi-axes (cx, cy, a, b px) agree within ``tolerance`` of the larger major
    semi-axis (False where either ellipse is NaN)."""
    first = np.asarray(one.ellipse, np.float64)[:4]
    second = np.asarray(other.ellipse, np.float64)[:4]
    scale = tolerance * max(first[2], second[2])
    return bool(np.hypot(*(first[:2] - second[:2])) <= scale
                and (np.abs(first[2:] - second[2:]) <= scale).all())


def without_failed_pieces(detections: list[CupDetection]) -> list[CupDetection]:
    """One image's ``detections`` less each failed one (an ``error`` status) that a cup
    with a pose :func:`reaches`, in their order.

    A failed detection within a posed cup's major semi-axis of its centre is a piece of
    that cup's rim, or of the anatomy beside it, that gave no pose; reported, it counts as
    a second cup where there is one (docs/training.md, item 73). A failed detection at a
    place of its own (a bilateral pair's other cup) is kept: it tells the user a cup is
    there."""
    posed = [det for det in detections if not failed(det)]
    return [det for det in detections
            if not failed(det) or not any(reaches(cup.ellipse, det.ellipse) for cup in posed)]


def wants_another_look(cup: CupDetection) -> bool:
    """Whether ``cup`` is flagged ``check`` or failed (an ``error`` status): the cups the
    model's later looks may replace."""
    return cup.check or failed(cup)


def later_look_cups(first: list[CupDetection], second: list[CupDetection],
                    below: float | None = None, up_to: int = 0,
                    added_below: float | None = None) -> list[CupDetection]:
    """One image's cups ``first`` with each one that :func:`wants_another_look` replaced by
    the least doubted cup of ``second`` that :func:`reaches` it, is believed (not flagged,
    doubted less than ``below``, None: any doubt) and is doubted less, each cup of
    ``second`` replacing one at most; the others as they are; then, while there are fewer
    than ``up_to``, the least doubted believed cups of ``second`` at other places (a
    bilateral pair's other cup) doubted less than ``added_below`` (None: any) added, each
    in place of a failed cup it reaches where there is one. Where ``first`` is empty (no cup
    found), the believed cups of ``second``.

    Reaching, not :func:`same_place`: a flagged or failed cup's ellipse is often a piece of
    its rim or of the anatomy beside it, short and off centre, so its major semi-axis may
    not reach the cup's centre though the cup's reaches its own (docs/training.md, item
    44). Where the replacement repeats a cup of ``first`` that wants no other look (the
    later look found that believed cup again, as :func:`distinct_cups` tells repeats), the
    flagged cup was a piece of it and is dropped: replaced, it had reported one cup twice
    (item 72)."""
    believed = [other for other in second if other.doubt is not None and not other.check
                and (below is None or other.doubt < below)]
    if not first:
        return believed
    first_believed = [cup for cup in first if not wants_another_look(cup)]
    out: list[CupDetection] = []
    for cup in first:
        if wants_another_look(cup):
            better = [other for other in believed
                      if (cup.doubt is None or other.doubt < cup.doubt)
                      and reaches(other.ellipse, cup.ellipse)
                      and not any(other is taken for taken in out)]
            cup = min(better, key=lambda other: other.doubt, default=cup)
            if any(repeats(cup, kept) for kept in first_believed):
                continue
        out.append(cup)
    for other in sorted(believed, key=lambda other: other.doubt) if up_to else []:
        if added_below is not None and other.doubt >= added_below:
            break  # sorted: the rest are doubted more
        if any(same_place(other.ellipse, cup.ellipse) for cup in out):
            continue
        reached = [k for k, cup in enumerate(out)
                   if failed(cup) and reaches(other.ellipse, cup.ellipse)]
        if reached:
            out[reached[0]] = other
        elif len(out) < up_to:
            out.append(other)
    return out


def reaches(one: np.ndarray, other: np.ndarray) -> bool:
    """Whether ellipse ``(5,)`` px ``one`` reaches ``other``: ``other``'s centre lies no
    further from ``one``'s than ``one``'s major semi-axis (False where either is NaN). Not
    symmetric: a rim's ellipse reaches a short piece of it off its centre, not the other
    way."""
    one, other = np.asarray(one, np.float64), np.asarray(other, np.float64)
    return bool(np.hypot(*(one[:2] - other[:2])) <= one[2])


def same_place(one: np.ndarray, other: np.ndarray) -> bool:
    """Whether ellipses ``(5,)`` px ``one`` and ``other`` mark one place: each
    :func:`reaches` the other (False where either is NaN)."""
    return reaches(one, other) and reaches(other, one)
