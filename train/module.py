"""LightningModule of CupNet: segmentation first, then ellipse and pose losses end to end."""

from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Timer
from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor, nn

from cupnet.config import CupNetConfig
from cupnet.crops import ellipse_to_view, resample_batch, square_windows
from cupnet.detection import CupDetection
from cupnet.ellipse import fit_ellipse
from cupnet.geometry import Geometry
from cupnet.landmarks import ellipse_coverage
from cupnet.model import CupNet, load_model, save_model, usable_fit
from cupnet.offload import networks_on
from cupnet.pose import PoseSolution
from train.losses import (
    POSE_NAMES,
    POSE_SCALE,
    distill_loss,
    ellipse_loss,
    pose_errors,
    pose_loss,
    ramp,
    rim_loss,
    segmentation_loss,
)


class CosineToFloor(torch.optim.lr_scheduler.CosineAnnealingLR):
    """Cosine decay from the optimizer's rate to ``eta_min`` over ``T_max`` steps, then
    ``eta_min`` held. torch's own goes on round the cosine, so a run resumed with a larger
    ``max_steps`` than its checkpoint's saw the rate rise again; within ``T_max`` the rates
    are torch's to the bit (its recursion gives ``eta_min`` exactly at ``T_max``)."""

    def get_lr(self) -> list[float | Tensor]:
        if self.last_epoch >= self.T_max:
            return [self.eta_min for _ in self.optimizer.param_groups]
        return super().get_lr()


# The state-dict prefixes of the rim networks a stage trains: one of another width, or one a
# model gains, starts afresh under init_weights.
TRAINED_RIMS = ("rim.", "coarse_rim.")


def _networks(keys: list[str]) -> list[str]:
    """The networks (``rim``, ``locator``, ...) that state-dict ``keys`` belong to."""
    return sorted({key.split(".")[0] for key in keys})


def batch_geometry(geometry: Tensor) -> Geometry:
    """``(B, 4)`` rows (sdd, spacing, u0, v0) of a collated batch -> :class:`Geometry`."""
    return Geometry.from_rows(geometry.double())


def jittered_ellipses(ellipse: Tensor, valid: Tensor, coarse: float, coarse_shift: float,
                      coarse_scale: float, fine_shift: float, fine_scale: float,
                      fine_angle: float, fine_ratio: float) -> Tensor:
    """True ellipses perturbed like the ellipses crops are framed on at inference.

    A fraction ``coarse`` of the cups get a first-pass frame, as from the locator's blob: the
    centre moved by up to ``coarse_shift * a`` per axis, the size scaled by up to
    ``exp(+-coarse_scale)``, any orientation and a roundish axis ratio in [0.6, 1] (so the
    crop is not stretched). The others get a second-pass frame, as from the first pass's
    fit: with a magnitude ``m ~ U(0, 1)^2``, the centre moved by up to ``m fine_shift a``,
    both axes scaled by up to ``exp(+-m fine_scale)``, ``b`` alone by ``exp(+-m fine_ratio)``,
    the angle turned by up to ``m fine_angle`` degrees.

    Args:
        ellipse: ``(B, C, 5)`` true ellipses, image pixels; valid: ``(B, C)`` bool.
    Returns:
        ``(B, C, 5)``, NaN where not valid.
    """
    u = 2 * torch.rand_like(ellipse) - 1  # (B, C, 5) in [-1, 1]
    a, b = ellipse[..., 2:3], ellipse[..., 3:4]
    is_coarse = torch.rand_like(a) < coarse
    m = torch.rand_like(a) ** 2
    shift = torch.where(is_coarse, coarse_shift, m * fine_shift) * a
    centre = ellipse[..., :2] + u[..., :2] * shift
    major = a * torch.exp(u[..., 2:3] * torch.where(is_coarse, coarse_scale, m * fine_scale))
    minor_fine = b * torch.exp(u[..., 2:3] * m * fine_scale + u[..., 3:4] * m * fine_ratio)
    minor = torch.where(is_coarse, major * (0.8 + 0.2 * u[..., 3:4]), minor_fine)
    alpha = torch.where(is_coarse, 90 * (u[..., 4:] + 1), ellipse[..., 4:] + m * u[..., 4:]
                        * fine_angle)
    out = torch.cat([centre, *_ordered_axes(major, minor, alpha)], -1)
    return torch.where(valid[..., None], out, torch.full_like(out, math.nan))


def _ordered_axes(first: Tensor, second: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
    """Semi-axes ``(..., 2)`` as (major, minor) and the major axis's angle ``(..., 1)`` (deg)
    of an ellipse given by the axis along ``alpha`` and the one across it."""
    swapped = second > first
    axes = torch.cat([torch.maximum(first, second), torch.minimum(first, second)], -1)
    return axes, alpha + 90 * swapped


def jittered_rim_starts(ellipse: Tensor, scale: float) -> Tensor:
    """True ellipses ``(K, 5)`` perturbed like the refiner's fits the rim stage starts from.

    With a magnitude ``m ~ U(0.1, 1.2) scale`` per cup: the centre moved by
    ``N(0, m max(2 px, 0.04 a))`` per axis, ``a`` scaled by ``exp(N(0, 0.08 m))``, ``b`` moved
    by ``N(0, 0.04 m a)`` (additive: a nearly edge-on cup's minor axis is off by pixels, not
    by a fraction of itself), the angle turned by ``N(0, 3 m)`` degrees.
    """
    count = ellipse.shape[0]
    noise = torch.randn(count, 5, dtype=ellipse.dtype, device=ellipse.device)
    m = scale * (0.1 + 1.1 * torch.rand(count, 1, dtype=ellipse.dtype, device=ellipse.device))
    a, b = ellipse[:, 2:3], ellipse[:, 3:4]
    centre = ellipse[:, :2] + noise[:, :2] * m * (0.04 * a).clamp_min(2.0)
    axes = _ordered_axes(a * torch.exp(0.08 * m * noise[:, 2:3]),
                         (b + 0.04 * m * a * noise[:, 3:4]).clamp_min(0.5),
                         ellipse[:, 4:] + 3 * m * noise[:, 4:])
    return torch.cat([centre, *axes], -1)


def coarse_rim_starts(ellipse: Tensor, scale: float, head: float = 0.5) -> Tensor:
    """True ellipses ``(K, 5)`` perturbed like the refiner's gross errors, which the coarse rim
    stage corrects.

    A fraction ``head`` of the cups start from a femoral head's outline, the refiner's worst
    mistake on a nearly edge-on cup: a roundish ellipse (axis ratio in [0.8, 1], any angle)
    of semi-major axis ``U(0.5, 1) a`` centred within ``N(0, 0.05 a)`` of the rim's centre (a
    head sits in the cup). The others, with a magnitude ``m ~ U(0, 1) scale``: the centre
    moved by ``N(0, 0.06 m a)`` per axis, ``a`` scaled by ``exp(N(0, 0.15 m))``, ``b`` moved
    towards ``a`` by ``m u (a - b)``, ``u ~ U(-0.3, 1)``, the angle turned by ``N(0, 20 m)``
    degrees.
    """
    count = ellipse.shape[0]
    noise = torch.randn(count, 4, dtype=ellipse.dtype, device=ellipse.device)
    m, u, is_head, size, ratio, turn = torch.rand(count, 6, dtype=ellipse.dtype,
                                                  device=ellipse.device).split(1, -1)
    m, u = scale * m, 1.3 * u - 0.3
    a, b = ellipse[:, 2:3], ellipse[:, 3:4]
    centre = ellipse[:, :2] + 0.06 * m * a * noise[:, :2]
    major = a * torch.exp(0.15 * m * noise[:, 2:3])
    minor = torch.minimum((b + m * u * (a - b)).clamp_min(0.5), major)
    jittered = torch.cat([centre, major, minor, ellipse[:, 4:] + 20 * m * noise[:, 3:]], -1)
    radius = a * (0.5 + 0.5 * size)
    outline = torch.cat([ellipse[:, :2] + 0.05 * a * noise[:, :2], radius,
                         radius * (0.8 + 0.2 * ratio), 180 * turn], -1)
    return torch.where(is_head < head, outline, jittered)


def far_rim_starts(ellipse: Tensor, ratio: float) -> Tensor:
    """True ellipses ``(K, 5)`` replaced by the starts the thin-rim hypotheses and a disc give
    the fine rim stage at inference, mostly out of its reach: half a disc's round outline
    (:func:`coarse_rim_starts`' femoral heads), half a thin ellipse (axis ratio ``ratio``, as
    :attr:`cupnet.config.CupNetConfig.thin_rim_ratio`; the semi-major axis
    ``a exp(N(0, 0.1))``, the centre within ``N(0, 0.05 a)``) at any angle.
    The rim stage learns to say where it cannot see the rim (a large ``sigma``), which is how
    :meth:`cupnet.model.CupNet.trusted_rim_landmarks` chooses among its starts."""
    count = ellipse.shape[0]
    noise = torch.randn(count, 3, dtype=ellipse.dtype, device=ellipse.device)
    turn, is_disc = torch.rand(count, 2, dtype=ellipse.dtype, device=ellipse.device).split(1, -1)
    a = ellipse[:, 2:3]
    major = a * torch.exp(0.1 * noise[:, 2:3])
    thin = torch.cat([ellipse[:, :2] + 0.05 * a * noise[:, :2], major, ratio * major,
                      180 * turn], -1)
    return torch.where(is_disc < 0.5, coarse_rim_starts(ellipse, 0.0, head=1.0), thin)


def crop_targets(ellipse: Tensor, valid: Tensor, crop_to_image: Tensor, cup_index: Tensor,
                 size: int) -> Tensor:
    """Coverage maps ``(K, 1, size, size)`` of all true ellipses of each crop's image."""
    image_ellipses = torch.where(valid[..., None], ellipse, torch.full_like(ellipse, math.nan))
    mine = image_ellipses[cup_index[:, 0]].double()  # (K, C, 5)
    in_crop = ellipse_to_view(mine, crop_to_image.double()[:, None])
    return ellipse_coverage(in_crop, size, size).float()


def match_detections(detections: list[CupDetection], ellipse: np.ndarray, valid: np.ndarray
                     ) -> list[CupDetection | None]:
    """Each true cup's detection: the nearest ellipse centre within half the true major axis.

    Args:
        detections: one image's detections.
        ellipse: ``(C, 5)`` true ellipses; valid: ``(C,)`` bool.
    Returns:
        ``C`` detections or None (missed or not a true cup).
    """
    out: list[CupDetection | None] = []
    for c in range(len(valid)):
        best, best_d = None, 0.5 * float(ellipse[c, 2])
        for det in detections if valid[c] else []:
            d = float(np.hypot(*(det.ellipse[:2] - ellipse[c, :2])))
            if np.isfinite(d) and d < best_d:
                best, best_d = det, d
        out.append(best)
    return out


def cup_errors(detections: list[CupDetection], truth_pose: np.ndarray, truth_ellipse: np.ndarray,
               valid: np.ndarray
               ) -> tuple[list[tuple[int, CupDetection | None, np.ndarray | None]], int]:
    """Each true cup's detection and absolute pose errors.

    Args:
        detections: the image's detections; truth_pose: ``(C, 5)`` public units;
        truth_ellipse: ``(C, 5)`` px; valid: ``(C,)`` bool.
    Returns:
        per true cup ``(index, detection or None, errors (5,) or None where it has no pose)``
        (phi wrapped as in :func:`train.losses.pose_errors`), and the number of detections
        matching no true cup.
    """
    matched = match_detections(detections, truth_ellipse, valid)
    cups: list[tuple[int, CupDetection | None, np.ndarray | None]] = []
    for c, det in enumerate(matched):
        if not valid[c]:
            continue
        err = None
        if det is not None and np.isfinite(det.pose).all():
            err = pose_errors(torch.from_numpy(np.asarray(det.pose, np.float64))[None],
                              torch.from_numpy(np.asarray(truth_pose[c], np.float64))[None]
                              )[0].abs().numpy()
        cups.append((c, det, err))
    return cups, len(detections) - sum(m is not None for m in matched)


def score_detections(detections: list[CupDetection], truth_pose: np.ndarray,
                     truth_ellipse: np.ndarray, valid: np.ndarray
                     ) -> tuple[list[np.ndarray], int, int, int]:
    """Score one image's detections against its true cups.

    Args: as :func:`cup_errors`.
    Returns:
        absolute pose errors ``(5,)`` of each true cup detected with a pose, the number of such
        cups, the number of true cups, and the detections matching no true cup.
    """
    cups, false_positives = cup_errors(detections, truth_pose, truth_ellipse, valid)
    errors = [err for _, _, err in cups if err is not None]
    return errors, len(errors), len(cups), false_positives


def _pose_maes(solution: PoseSolution, truth: Tensor) -> dict[str, Tensor]:
    """Training-log MAEs ``mae_theta`` ... ``mae_h`` of the solved poses against ``truth``
    (NaN where none is solved), and ``posed``, the share of cups solved: the pose loss reads
    0 where none is, as it would for a perfect fit."""
    with torch.no_grad():
        err = pose_errors(solution.pose, truth)
        ok = solution.valid
        maes = {f"mae_{name}": (err[ok, j].abs().mean() if bool(ok.any())
                                else torch.tensor(math.nan))
                for j, name in enumerate(POSE_NAMES)}
        return {**maes, "posed": ok.double().mean() if len(ok) else torch.tensor(math.nan)}


# Settings out of range had run on: a negative loss weight trained its error up, no crops
# trained no refiner, a negative weight decay ended in AdamW's traceback.
_NON_NEGATIVE = ("weight_decay", "ellipse_weight", "pose_weight", "locator_weight",
                 "rim_weight", "distill_weight", "ellipse_start", "pose_start", "ramp_steps",
                 "coarse_shift", "coarse_scale", "fine_shift", "fine_scale", "fine_angle",
                 "fine_ratio", "rim_jitter")
_FRACTIONS = ("coarse_fraction", "rim_refiner_starts", "rim_far_starts", "locator_dark_views",
              "locator_min_ratio")
_AT_LEAST_ONE = ("crops_per_cup", "rim_copies")


def _check_ranges(hparams: dict) -> None:
    """A ValueError naming the first of the module's numeric settings out of its range
    (NaN is out of every range)."""
    for name in _NON_NEGATIVE:
        if not hparams[name] >= 0:
            raise ValueError(f"{name} must be >= 0, got {hparams[name]}")
    for name in _FRACTIONS:
        if not 0 <= hparams[name] <= 1:
            raise ValueError(f"{name} must be a fraction in [0, 1], got {hparams[name]}")
    for name in _AT_LEAST_ONE:
        if not hparams[name] >= 1:
            raise ValueError(f"{name} must be >= 1, got {hparams[name]}")


class CupNetModule(L.LightningModule):
    """CupNet training: locator + refiner segmentation, then ellipse and pose losses.

    Args:
        model: :class:`cupnet.config.CupNetConfig` fields.
        lr: AdamW learning rate (cosine decay to ``lr / 20`` over ``max_steps``).
        weight_decay: AdamW weight decay.
        ellipse_start, pose_start: steps at which the ellipse and pose losses come in, each
            ramped linearly over ``ramp_steps`` (segmentation always on).
        ellipse_weight, pose_weight: their full weights (``pose_weight: 0`` trains on
            segmentation (and ellipse) alone: the ablation). The pose loss reaches the
            networks whose landmarks give the pose: the rim network where the model has one
            (``rim_passes > 0``; the refiner only frames its strips), else the refiner.
        locator_weight: weight of the locator's segmentation loss.
        coarse_fraction, coarse_shift, coarse_scale, fine_shift, fine_scale, fine_angle,
            fine_ratio: crop framing errors (see :func:`jittered_ellipses`).
        crops_per_cup: differently jittered crops per cup and image (synthesis costs more
            than a crop's training step, so each image is used several times).
        refine_pose: train through the solver's ML refinement (else its closed form).
        rim_weight: weight of the rim stage's landmark loss (:func:`train.losses.rim_loss`),
            when the model has a rim stage.
        rim_only: train a rim stage alone, the U-Nets (and the other rim stage) frozen and
            not run: strips framed on jittered true ellipses, one pass, rim and pose losses.
        rim_stage: which: ``"fine"`` (starts from :func:`jittered_rim_starts`) or
            ``"coarse"`` (:func:`coarse_rim_starts`).
        rim_jitter: scale of those jitters; rim_copies: differently jittered starts per cup.
        rim_refiner_starts: the fraction of ``rim_only`` starts that are instead the frozen
            refiner's fits on crops framed like its second inference pass (its real errors).
        rim_far_starts: the fraction of the fine stage's ``rim_only`` starts that are instead
            :func:`far_rim_starts` (a disc's outline or a thin-rim hypothesis).
        locator_only: train the locator alone (its segmentation loss), every other network
            frozen and not run; it sees each image through one of the square windows
            :meth:`cupnet.model.CupNet.locate_windows` shows it (drawn at random; a square
            image's one window is its letterbox), so oblong training images teach it what
            it meets in an oblong image's windows.
        locator_min_ratio: the locator's target is the true openings, each widened to this
            axis ratio at least (0: the synthesised mask as it is); a nearly edge-on cup's
            opening is sub-pixel thin in the letterboxed view, and the locator then misses it
            (its blob only frames the refiner's first, round crop).
        locator_dark_views: the fraction of the locator's views raised to a power in
            ``[0.25, 0.6]``, as :attr:`cupnet.config.CupNetConfig.locator_retry_gamma` shows
            them to it where it found no cup.
        freeze: networks not to train (``locator``, ``refiner``, ``rim``, ``coarse_rim``),
            kept in eval mode: e.g. a refiner-only stage.
        torch_threads: intra-op threads (None: torch's default); 1 suits a shared CPU,
            where the data worker takes the other core.
        init_weights: a checkpoint whose network weights start this run (fine-tuning; a
            resume with ``--ckpt_path`` restores the old run's hyper-parameters instead);
            a rim network of another width than this model's starts afresh (warned of,
            with the ones this run does not train, whose export holds them untrained).
        rim_teacher: a checkpoint whose fine rim network teaches this one (``rim_only``,
            ``rim_stage: fine``): on every training strip, the KL divergence from the
            teacher's offset distribution to this network's, per column, and the absolute
            difference of their ``log sigma``, weighted ``distill_weight``, beside the
            truth's loss (a narrower, faster rim network learns the wider one's doubts too,
            which the verification's gates were tuned on).
        export_path: where :meth:`on_fit_end` writes the model as safetensors + JSON.
    """

    def __init__(
        self,
        model: dict | None = None,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
        ellipse_start: int = 200,
        pose_start: int = 400,
        ramp_steps: int = 200,
        ellipse_weight: float = 0.5,
        pose_weight: float = 0.2,
        locator_weight: float = 0.5,
        coarse_fraction: float = 0.4,
        coarse_shift: float = 0.15,
        coarse_scale: float = 0.3,
        fine_shift: float = 0.05,
        fine_scale: float = 0.08,
        fine_angle: float = 8.0,
        fine_ratio: float = 0.25,
        crops_per_cup: int = 2,
        refine_pose: bool = False,
        rim_weight: float = 1.0,
        rim_only: bool = False,
        rim_stage: str = "fine",
        rim_jitter: float = 1.0,
        rim_copies: int = 3,
        rim_refiner_starts: float = 0.0,
        rim_far_starts: float = 0.0,
        locator_only: bool = False,
        locator_min_ratio: float = 0.0,
        locator_dark_views: float = 0.0,
        freeze: tuple[str, ...] = (),
        torch_threads: int | None = None,
        init_weights: str | None = None,
        rim_teacher: str | None = None,
        distill_weight: float = 1.0,
        export_path: str | None = None,
    ) -> None:
        super().__init__()
        if not lr > 0:  # NaN fails too; AdamW had refused it at the first step
            raise ValueError(f"lr must be a learning rate > 0, got {lr}")
        self.save_hyperparameters()
        _check_ranges(self.hparams)
        self.model = CupNet(CupNetConfig.from_dict(model or {}))
        # A resumed run's random state (CPU, CUDA), set at its first step (on_load_checkpoint).
        self._resumed_rng: tuple[Tensor | None, list[Tensor] | None] = (None, None)
        fresh: list[str] = []  # rim networks init_weights could not start
        if init_weights:
            # A model gaining a rim stage starts from weights without one; a rim network of
            # another width starts afresh.
            own = self.model.state_dict()
            start = load_model(init_weights)
            state = start.state_dict()
            if start.blur_rim is not None and self.model.blur_rim is None:
                # An inference option (--blurred) no stage trains: left out, and said so.
                state = {k: v for k, v in state.items() if not k.startswith("blur_rim.")}
                rank_zero_warn(f"{init_weights}'s blur-trained rim network (blur_rim) is not "
                               "in this model: this run's export holds none (train.merge "
                               "--take blur_rim= puts one back)")
            reshaped = {k for k, v in state.items() if k in own and own[k].shape != v.shape}
            refused = [k for k in state if k in reshaped and not k.startswith(TRAINED_RIMS)]
            if refused:  # load_state_dict's own message lists each, 64 lines for a decoder
                first = refused[0]
                raise ValueError(
                    f"{init_weights} does not fit this model: {len(refused)} tensors of "
                    f"another shape, in {_networks(refused)} (first: {first} "
                    f"{tuple(state[first].shape)} for {tuple(own[first].shape)}): another "
                    "encoder or decoder width")
            state = {k: v for k, v in state.items() if k not in reshaped}
            missing, unexpected = self.model.load_state_dict(state, strict=False)
            if unexpected or any(not k.startswith(TRAINED_RIMS) for k in missing):
                raise ValueError(
                    f"{init_weights} does not fit this model: it holds networks this model "
                    f"has not built {_networks(unexpected)} (a rim stage with 0 passes builds "
                    f"none) and lacks ones it has {_networks(missing)}; first keys: "
                    f"unexpected {unexpected[:3]}, missing {missing[:3]}")
            fresh = _networks(missing)
        if rim_only:
            if rim_stage not in ("fine", "coarse"):
                raise ValueError(f"rim_stage must be 'fine' or 'coarse', got {rim_stage!r}")
            if self._trained_rim() is None:
                raise ValueError(f"rim_only with rim_stage {rim_stage!r} needs a model with that "
                                 "rim stage (rim_passes or coarse_rim_passes > 0)")
        if rim_teacher:
            if not (rim_only and rim_stage == "fine"):
                raise ValueError("rim_teacher teaches the fine rim stage: set rim_only and "
                                 "rim_stage: fine")
            teacher = load_model(rim_teacher).rim
            if teacher is None:
                raise ValueError(f"{rim_teacher} has no fine rim network to teach with")
            # Not a child module: no optimiser state, not in this run's checkpoints.
            self.__dict__["_rim_teacher"] = teacher.requires_grad_(False).eval()
        unknown = set(freeze) - {"locator", "refiner", "rim", "coarse_rim"}
        if unknown:
            raise ValueError(f"freeze names unknown networks: {sorted(unknown)}")
        for net in self._frozen_nets():
            net.requires_grad_(False)
        self._freeze_modes()
        if fresh:
            # Not an error: the hour recipe's coarse chain trains the coarse network beside a
            # fine one it never trains, and train.merge takes the coarse one alone.
            untrained = [name for name in fresh
                         if getattr(self.model, name) in self._frozen_nets()]
            rank_zero_warn(
                f"{init_weights} holds no {fresh} this model can take (none, or of another "
                "width: rim_channels, coarse_rim_channels): they start afresh"
                + (f", and {untrained} are not trained this run, so its export holds them "
                   "untrained (train.merge can take another run's)" if untrained else ""))

    def _trained_rim(self) -> nn.Module | None:
        """The rim network a ``rim_only`` run trains."""
        return self.model.coarse_rim if self.hparams.rim_stage == "coarse" else self.model.rim

    def _frozen_nets(self) -> list[nn.Module]:
        """The networks ``freeze`` names, and with ``rim_only`` or ``locator_only`` every
        network but the one trained."""
        names = ("locator", "refiner", "rim", "coarse_rim")
        hp = self.hparams
        trained = (self._trained_rim() if hp.rim_only
                   else self.model.locator if hp.locator_only else None)
        return [net for name in names if (net := getattr(self.model, name)) is not None
                and (name in hp.freeze or (trained is not None and net is not trained))]

    def _freeze_modes(self) -> None:
        """The frozen networks stay in eval mode, so running them (the refiner for
        :meth:`rim_starts`, the locator in every forward) never updates their BatchNorm
        statistics."""
        for net in self._frozen_nets():
            net.eval()

    def train(self, mode: bool = True) -> CupNetModule:
        super().train(mode)
        self._freeze_modes()
        return self

    def on_train_start(self) -> None:
        self._freeze_modes()
        self._warn_of_a_resumed_schedule()

    def losses(self, batch: dict, step: int) -> dict[str, Tensor]:
        """All loss terms of one batch and their weighted total (``"loss"``)."""
        if self.hparams.rim_only:
            return self.rim_losses(batch)
        if self.hparams.locator_only:
            return self.locator_losses(batch)
        hp, cfg = self.hparams, self.model.config
        images = batch["image"]
        cups = batch["cup_valid"].shape[1]
        # Slot c * cups + j is the c-th jittered crop of cup j.
        valid = batch["cup_valid"].bool().repeat(1, hp.crops_per_cup)
        geometry = batch_geometry(batch["geometry"])
        rough = jittered_ellipses(batch["ellipse"].double().repeat(1, hp.crops_per_cup, 1), valid,
                                  hp.coarse_fraction, hp.coarse_shift, hp.coarse_scale,
                                  hp.fine_shift, hp.fine_scale, hp.fine_angle, hp.fine_ratio)
        out = self.model(images, geometry, batch["cup_diameter"].repeat(1, hp.crops_per_cup),
                         crop_frames=self.model.frames(rough), refine_pose=hp.refine_pose)
        terms = {"seg_locator": segmentation_loss(out.locator_logits,
                                                  self.locator_targets(batch, out.letterbox))}
        target = crop_targets(batch["ellipse"], batch["cup_valid"].bool(), out.crop_to_image,
                              out.cup_index, cfg.crop_size)
        terms["seg_crop"] = segmentation_loss(out.crop_logits, target)
        i, c = out.cup_index[:, 0], out.cup_index[:, 1] % cups
        w_ellipse = ramp(step, hp.ellipse_start, hp.ramp_steps) * hp.ellipse_weight
        w_pose = ramp(step, hp.pose_start, hp.ramp_steps) * hp.pose_weight
        if w_ellipse > 0:
            fit = fit_ellipse(out.refiner_landmarks, out.refiner_weights, on_error="flag")
            crop_step = torch.linalg.svdvals(out.crop_to_image[:, :, :2].double())[:, -1]
            terms["ellipse"] = ellipse_loss(fit.conic, batch["rim"][i, c].double(), crop_step,
                                            fit.valid)
        solution = out.solution
        terms["pose"] = pose_loss(solution.pose, batch["pose"][i, c].double(), solution.valid)
        if w_pose > 0 and torch.is_grad_enabled() and not terms["pose"].requires_grad:
            # (Python's warnings say it once.)
            rank_zero_warn("pose_weight > 0, but the pose loss reaches no network this run "
                           "trains: it reaches those whose landmarks give the pose, the rim "
                           "network where the model has one (rim_passes > 0), else the "
                           "refiner; pose_weight has no effect here")
        total = (hp.locator_weight * terms["seg_locator"] + terms["seg_crop"]
                 + w_ellipse * terms.get("ellipse", 0.0) + w_pose * terms["pose"])
        if out.rim is not None:
            terms["rim"] = rim_loss(out.rim, batch["ellipse"][i, c])
            total = total + hp.rim_weight * terms["rim"]
        terms["loss"] = total.float()
        terms.update(_pose_maes(solution, batch["pose"][i, c].double()))
        return terms

    def locator_targets(self, batch: dict, letterbox: Tensor) -> Tensor:
        """The locator's target ``(B, 1, S, S)`` in its views (view-to-image affines
        ``letterbox`` ``(B, 2, 3)``): the openings' coverage, widened by
        ``locator_min_ratio``."""
        size, ratio = self.model.config.locator_size, self.hparams.locator_min_ratio
        if ratio <= 0:
            return resample_batch(batch["mask"], letterbox, size)
        ellipse = batch["ellipse"].double()
        widened = torch.cat([ellipse[..., :3],
                             torch.maximum(ellipse[..., 3:4], ratio * ellipse[..., 2:3]),
                             ellipse[..., 4:]], -1)
        rows = torch.arange(len(letterbox), device=letterbox.device)[:, None]
        return crop_targets(widened, batch["cup_valid"].bool(), letterbox, rows, size)

    def locator_losses(self, batch: dict) -> dict[str, Tensor]:
        """Segmentation loss of the locator alone (``locator_only``), see :meth:`losses`."""
        images = batch["image"]
        dark = torch.rand(len(images), device=images.device) < self.hparams.locator_dark_views
        gamma = torch.where(dark, 0.25 + 0.35 * torch.rand(len(images), device=images.device),
                            torch.ones(len(images), device=images.device))
        size = self.model.config.locator_size
        windows, _ = square_windows(*images.shape[-2:], size, dtype=images.dtype)
        drawn = (torch.randint(len(windows), (len(images),)) if len(windows) > 1
                 else torch.zeros(len(images), dtype=torch.long))  # a square image's letterbox
        affines = windows[drawn].to(images.device)
        logits = self.model.locator_logits(resample_batch(images, affines, size), gamma)
        loss = segmentation_loss(logits, self.locator_targets(batch, affines))
        return {"seg_locator": loss, "loss": loss.float()}

    def rim_losses(self, batch: dict) -> dict[str, Tensor]:
        """Loss terms of the rim stage alone (``rim_only``), see :meth:`losses`."""
        hp = self.hparams
        cup_index = batch["cup_valid"].bool().nonzero().repeat(hp.rim_copies, 1)  # (K, 2)
        i, c = cup_index[:, 0], cup_index[:, 1]
        truth = batch["ellipse"][i, c].double()
        teacher = self.__dict__.get("_rim_teacher")
        seen: list[tuple[Tensor, tuple[Tensor, Tensor]]] = []  # (strips, outputs) per call
        hook = (self._trained_rim().register_forward_hook(
            lambda _, inputs, outputs: seen.append((inputs[0], outputs)))
            if teacher is not None else None)
        try:
            rim = self.model.rim_landmarks(batch["image"], i,
                                           self.rim_starts(batch["image"], i, truth), passes=1,
                                           coarse=hp.rim_stage == "coarse")
        finally:
            if hook is not None:
                hook.remove()
        solution = self.model.solve(rim.landmarks, rim.weights, batch_geometry(batch["geometry"]),
                                    batch["cup_diameter"], cup_index, batch["image"].shape[0],
                                    refine=hp.refine_pose)
        terms = {"rim": rim_loss(rim, truth),
                 "pose": pose_loss(solution.pose, batch["pose"][i, c].double(), solution.valid)}
        total = hp.rim_weight * terms["rim"] + hp.pose_weight * terms["pose"]
        if teacher is not None and seen:
            # The teacher's weights and the strips need no gradient: no graph is built.
            terms["distill"] = sum(
                distill_loss(outputs, teacher.to(strips.device).forward_batch(strips))
                for strips, outputs in seen) / len(seen)
            total = total + hp.distill_weight * terms["distill"]
        if len(cup_index) == 0:  # no cup in the batch: a zero loss that still has a graph
            total = total + sum(p.sum() for p in self._trained_rim().parameters()) * 0.0
        terms["loss"] = total.float()
        terms.update(_pose_maes(solution, batch["pose"][i, c].double()))
        return terms

    def rim_starts(self, images: Tensor, index: Tensor, truth: Tensor) -> Tensor:
        """Ellipses ``(K, 5)`` the rim stage starts from in ``rim_only`` training.

        A fraction ``rim_refiner_starts`` are the frozen refiner's fits on crops framed like
        its second inference pass (:func:`jittered_ellipses`, fine frames), so the rim stage
        meets the refiner's real mistakes (a femoral head's outline, a thin rim's short major
        axis); the others are :func:`jittered_rim_starts` (:func:`coarse_rim_starts` for the
        coarse stage).

        Args:
            images: ``(B, 1, H, W)``; index: ``(K,)`` image of each cup; truth: ``(K, 5)``.
        """
        hp = self.hparams
        jitter = coarse_rim_starts if hp.rim_stage == "coarse" else jittered_rim_starts
        start = jitter(truth, hp.rim_jitter)
        if hp.rim_far_starts > 0 and hp.rim_stage == "fine":
            far = torch.rand(len(truth), 1, device=truth.device) < hp.rim_far_starts
            start = torch.where(far, far_rim_starts(truth, self.model.config.thin_rim_ratio),
                                start)
        if hp.rim_refiner_starts <= 0:
            return start
        valid = torch.ones_like(truth[None, :, 0], dtype=torch.bool)
        frames = self.model.frames(jittered_ellipses(
            truth[None], valid, 0.0, hp.coarse_shift, hp.coarse_scale, hp.fine_shift,
            hp.fine_scale, hp.fine_angle, hp.fine_ratio)[0])
        use = (torch.rand(len(truth), 1, device=truth.device)
               < hp.rim_refiner_starts)[:, 0].nonzero()[:, 0]
        if len(use) == 0:
            return start
        start = start.clone()
        with torch.no_grad():  # the refiner runs only on the cups that take its fit
            crop_logits, crop_to_image = self.model.segment_crops(images, frames[use], index[use])
            start[use] = usable_fit(*self.model.crop_landmarks(crop_logits, crop_to_image),
                                    start[use])
        return start

    def setup(self, stage: str) -> None:
        if self.hparams.torch_threads:
            torch.set_num_threads(self.hparams.torch_threads)

    def training_step(self, batch: dict, batch_idx: int) -> Tensor:
        terms = self.losses(batch, self.global_step)
        self.log_dict({f"train/{k}": v.detach() for k, v in terms.items() if k != "loss"},
                      batch_size=batch["image"].shape[0])
        self.log("train/loss", terms["loss"].detach(), prog_bar=True,
                 batch_size=batch["image"].shape[0])
        return terms["loss"]

    def on_validation_epoch_start(self) -> None:
        # detect keeps its geometry on the CPU: on an accelerator only the networks run
        # there (cupnet.offload). Kept out of the module's children, so out of checkpoints.
        self.__dict__["_detector"] = (self.model if self.device.type == "cpu"
                                      else networks_on(self.model, self.device))

    def on_validation_epoch_end(self) -> None:
        self.__dict__.pop("_detector", None)

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        """Full inference path (locator -> crops -> pose) against the truth."""
        batch = {k: v.cpu() for k, v in batch.items()}
        detector = self.__dict__.get("_detector", self.model)
        detections = detector.detect(batch["image"], batch_geometry(batch["geometry"]),
                                     batch["cup_diameter"][:, 0].double(), return_masks=False)
        errors, found, total = [], 0, 0
        truth_pose = batch["pose"].double().numpy()
        for b, dets in enumerate(detections):
            e, f, t, _ = score_detections(dets, truth_pose[b], batch["ellipse"][b].numpy(),
                                          batch["cup_valid"][b].numpy().astype(bool))
            errors += e
            found += f
            total += t
        size = batch["image"].shape[0]
        detected = found / max(total, 1)
        # sync_dist: under DDP each process validates its share of the images.
        self.log("val/detected", detected, batch_size=size, sync_dist=True)
        mae = np.mean(errors, 0) if errors else np.full(5, np.nan)
        for j, name in enumerate(POSE_NAMES):
            self.log(f"val/mae_{name}", float(mae[j]), batch_size=size, sync_dist=True)
        # One figure for checkpoint selection: each MAE relative to its target, plus missed
        # cups; logged on every batch (a large value when nothing was found).
        relative = float(np.mean(mae / np.array(POSE_SCALE))) if errors else 100.0
        self.log("val/score", relative + 10 * (1 - detected), batch_size=size, prog_bar=True,
                 sync_dist=True)

    def configure_optimizers(self) -> dict[str, object]:
        optimizer = torch.optim.AdamW((p for p in self.parameters() if p.requires_grad),
                                      lr=self.hparams.lr,
                                      weight_decay=self.hparams.weight_decay)
        steps = max(1, int(self.trainer.max_steps)) if self.trainer.max_steps > 0 else 10_000
        scheduler = CosineToFloor(optimizer, steps, self.hparams.lr / 20)
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def on_fit_start(self) -> None:
        # A resume restores the time the stopped run had used of max_time (Lightning's
        # Timer stops a depleted one here, before any step, and the run ends quietly).
        timer = next((c for c in self.trainer.callbacks if isinstance(c, Timer)), None)
        left = timer.time_remaining() if timer is not None else None
        if self.trainer.ckpt_path and left is not None and left <= 0:
            rank_zero_warn(f"the checkpoint's run had used its max_time "
                           f"({timer.time_elapsed():.0f} s), so no step will run: give a "
                           "larger --trainer.max_time to train on")

    def _warn_of_a_resumed_schedule(self) -> None:
        # A resume restores the stopped run's schedule, over its max_steps.
        if not self.trainer.ckpt_path:
            return
        schedule = self.lr_schedulers()
        if self.trainer.max_steps > 0 and isinstance(
                schedule, CosineToFloor) and schedule.T_max != self.trainer.max_steps:
            rank_zero_warn(
                f"resumed with max_steps {self.trainer.max_steps}, but the checkpoint's "
                f"learning-rate cosine runs over {schedule.T_max} steps: "
                + ("it holds its floor (lr / 20) for the steps past them; to train longer at a "
                   "higher rate, start a new stage from the run's export (--model.init_weights)"
                   if schedule.T_max < self.trainer.max_steps else
                   "the run stops before the rate reaches its floor"))

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # The random draws of the training steps (jittered rim starts, dark views, windows),
        # so that a resumed run goes on drawing as the stopped one would have.
        checkpoint["torch_rng_state"] = torch.get_rng_state()
        if torch.cuda.is_available():
            checkpoint["cuda_rng_states"] = torch.cuda.get_rng_state_all()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        # Set at the first step, not now: the data loader's start draws from the generator
        # in between, which the stopped run had done once, long before.
        self._resumed_rng = (checkpoint.get("torch_rng_state"),
                             checkpoint.get("cuda_rng_states"))

    def on_train_batch_start(self, batch: dict, batch_idx: int) -> None:
        state, cuda_states = self._resumed_rng
        if state is not None:
            torch.set_rng_state(state)
        if cuda_states is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(cuda_states)
        self._resumed_rng = (None, None)

    def on_fit_end(self) -> None:
        if self.hparams.export_path and self.trainer.is_global_zero:
            save_model(self.model, Path(self.hparams.export_path))
