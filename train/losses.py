"""Training losses of CupNet: segmentation, geometric ellipse, rim landmark and normalised
pose terms."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from cupnet.config import TARGET_ACCURACY
from cupnet.ellipse import sampson_distance
from cupnet.rim import RimLandmarks, laplace_nll, normal_crossings

# The pose's components, in the order of every (..., 5) pose tensor.
POSE_NAMES = ("theta", "phi", "k", "l", "h")
# Pose error that counts as 1 in the normalised pose loss: the target MAEs.
POSE_SCALE = TARGET_ACCURACY


def segmentation_loss(logits: Tensor, target: Tensor, eps: float = 1.0) -> Tensor:
    """BCE + soft Dice of ``(K, 1, H, W)`` logits against coverage targets in [0, 1]."""
    if logits.shape[0] == 0:
        return logits.sum() * 0.0
    bce = F.binary_cross_entropy_with_logits(logits, target)
    prob = torch.sigmoid(logits)
    inter = (prob * target).sum((-2, -1))
    dice = 1 - (2 * inter + eps) / (prob.sum((-2, -1)) + target.sum((-2, -1)) + eps)
    return bce + dice.mean()


def ellipse_loss(conic: Tensor, rim: Tensor, pixel_scale: Tensor, valid: Tensor) -> Tensor:
    """Huber loss (smooth L1, quadratic within 1 crop pixel) of the Sampson distances of true
    rim points to predicted conics, averaged over points.

    Args:
        conic: ``(K, 3, 3)`` predicted conics, image pixels.
        rim: ``(K, M, 2)`` true rim points, image pixels; an item with a NaN point (a cup
            without truth) is left out, as an invalid one.
        pixel_scale: ``(K,)`` image pixels per crop pixel (distances are reported in crop
            pixels so large and small cups weigh alike).
        valid: ``(K,)`` bool, items with a usable fit.
    """
    valid = valid & torch.isfinite(rim).all(-1).all(-1)
    if not bool(valid.any()):
        return conic.sum() * 0.0
    dist = sampson_distance(conic[valid], rim[valid]).abs() / pixel_scale[valid, None]
    return F.smooth_l1_loss(dist, torch.zeros_like(dist), beta=1.0)


def distill_loss(student: tuple[Tensor, Tensor], teacher: tuple[Tensor, Tensor]) -> Tensor:
    """How far a rim network's outputs on strips lie from a teacher's on the same strips.

    Args:
        student, teacher: :class:`cupnet.rim.RimNet` outputs, offset logits ``(K, S, n)``
            and ``log sigma`` ``(K, n)`` (the teacher's taken as constants).
    Returns:
        the mean over columns of the KL divergence from the teacher's offset distribution to
        the student's, plus the mean absolute difference of their ``log sigma``.
    """
    logits, log_sigma = student
    teacher_logits, teacher_log_sigma = (t.detach().float() for t in teacher)
    divergence = F.kl_div(F.log_softmax(logits.float(), 1), F.log_softmax(teacher_logits, 1),
                          log_target=True, reduction="none").sum(1)
    return divergence.mean() + (log_sigma.float() - teacher_log_sigma).abs().mean()


def rim_loss(rim: RimLandmarks, truth: Tensor) -> Tensor:
    """Laplace negative log-likelihood of the rim stage's offsets.

    ``|s - s*| / sigma + log sigma`` per column, ``s*`` where the column's normal line leaves
    the true ellipse (:func:`cupnet.rim.normal_crossings`) clipped to its strip's reach:
    the network is rewarded for landmarks on the rim, at the column's own place along it (a
    distance to the ellipse would accept a thin ellipse's tip column anywhere on its long
    sides), and for a ``sigma`` (its fit weight ``1 / sigma^2``) equal to the error it expects,
    so a column where the rim cannot be seen learns a large ``sigma`` rather than a guess at
    full weight.

    Args:
        rim: the rim stage's output for ``K`` cups; truth: ``(K, 5)`` true ellipses.
    """
    if rim.offset.shape[0] == 0:
        return rim.offset.sum() * 0.0
    target = normal_crossings(rim.points, rim.normals, truth).clamp(-rim.reach, rim.reach)
    return laplace_nll(rim.offset - target, rim.sigma).mean()


def wrap_angle(delta: Tensor, period: float = 180.0) -> Tensor:
    """Angle differences wrapped into ``[-period / 2, period / 2)``."""
    return torch.remainder(delta + period / 2, period) - period / 2


def pose_errors(pred: Tensor, truth: Tensor) -> Tensor:
    """``(K, 5)`` signed errors (deg, deg, mm, mm, mm); phi wrapped with period 180 deg."""
    err = pred - truth
    return torch.cat([err[:, :1], wrap_angle(err[:, 1:2]), err[:, 2:]], -1)


def pose_loss(pred: Tensor, truth: Tensor, valid: Tensor) -> Tensor:
    """Huber loss of pose errors, each component divided by :data:`POSE_SCALE`.

    Args:
        pred, truth: ``(K, 5)`` public units; ``valid``: ``(K,)`` bool (solved poses). A
            truth row with a NaN (a cup without truth) is left out, as an invalid one: it
            had made the loss NaN, and every gradient of the step with it.
    """
    valid = valid & torch.isfinite(truth).all(-1)
    if not bool(valid.any()):
        return pred.nan_to_num().sum() * 0.0
    scale = torch.tensor(POSE_SCALE, dtype=pred.dtype, device=pred.device)
    err = pose_errors(pred[valid], truth[valid]) / scale
    return F.smooth_l1_loss(err, torch.zeros_like(err), beta=1.0)


def ramp(step: int, start: int, length: int) -> float:
    """Weight schedule: 0 before ``start``, then linear to 1 over ``length`` steps."""
    if step < start:
        return 0.0
    return 1.0 if length <= 0 else min(1.0, (step - start + 1) / length)
