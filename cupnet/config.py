"""CupNet's settings: the networks' shapes and every inference stage's, and the speed presets.

:class:`CupNetConfig` travels with the weights (the JSON beside a checkpoint,
:func:`cupnet.model.save_model`); :data:`SPEED_PRESETS` are faster operating points of the
same weights, inference settings only.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import yaml

from cupnet.checked import CheckedFields
from cupnet.polarity import METAL_DISPLAYS

# The target MAEs (theta, phi in degrees; k, l, h in mm): the unit of
# ``outline_settled`` and of the training's normalised pose loss.
TARGET_ACCURACY = (1.0, 1.0, 1.0, 1.0, 8.0)

# A model told its images are blurred that has no blur-trained rim network: refused by the
# config and, where the config's blur_rim was set after the model was made without the
# network, where a rim stage would run (CupNet.fine_rim).
BLURRED_WITHOUT_BLUR_RIM = ("blurred needs blur_rim: this model has no rim network trained "
                            "on blurrier images")


# The fields that size a network or count what it makes (>= 1), and the stages' passes (>= 0);
# but the refiner always runs once (0 passes had run one), and a cup's landmarks are
# fitted with an ellipse, which takes 5 (4 had trained without an ellipse or pose loss,
# and every cup of the model exported was an error).
COUNTS = ("locator_size", "crop_size", "n_rays", "ray_samples", "rim_points", "rim_samples",
          "rim_channels", "max_cups", "thin_rim_angles", "enlarge_to", "reduce_to")
PASSES = ("refine_passes", "rim_passes", "coarse_rim_passes", "outline_passes")
LEAST = {**dict.fromkeys(COUNTS, 1), **dict.fromkeys(PASSES, 0), "refine_passes": 1,
         "n_rays": 5, "rim_points": 5}


@dataclass
class CupNetConfig(CheckedFields):
    """Architecture and inference settings (stored as JSON beside a checkpoint).

    Attributes:
        encoder: smp encoder name of both U-Nets (never downloaded: ``encoder_weights=None``).
        decoder_channels: U-Net decoder widths, deepest first.
        encoder_weights: optional path of an encoder state dict (safetensors or torch) loaded
            into both encoders, e.g. an ImageNet checkpoint the user has locally.
        locator_size: letterbox side (px) of stage 1.
        crop_size: crop side (px) of stage 2.
        crop_fill: rim major diameter / crop side.
        crop_min_ratio: the minor direction of a crop is stretched so the rim's axis ratio
            in the crop is at least this ...
        crop_max_stretch: ... stretching by this factor at most.
        n_rays: soft landmarks per cup (at least 5, an ellipse's).
        ray_samples: samples per ray.
        max_cups: cups per image at most.
        detect_threshold: probability threshold of the locator's components.
        min_cup_area: smallest component (locator px) that counts as a cup.
        min_score: a detected cup whose locator component's mean probability
            (:attr:`CupDetection.score`) is below this is dropped before the cup stages (None:
            none is): weak blobs make most false cups, many of them with confident poses
            (item 24 of docs/training.md).
        refine_passes: stage-2 passes at inference, at least 1 (each re-frames on the last
            ellipse).
        locator_scale: the first pass frames the locator's blob enlarged by this factor and
            made round (axis ratio >= 0.8, no stretch), as in training's coarse frames.
        rim_passes: rim-stage passes (0: no rim stage; the landmarks are the refiner's); each
            pass after the first is framed on the weighted fit of the pass before.
        rim_points: rim landmarks (strip columns) per cup (at least 5).
        rim_samples: samples along each normal (strip rows) ...
        rim_step: ... this many image pixels apart.
        rim_channels: width of :class:`cupnet.rim.RimNet` (the rim networks: fine, coarse,
            blur-trained).
        coarse_rim_channels: the coarse stage's width where it differs (None: the same).
        coarse_rim_passes: coarse rim-stage passes before the fine ones (0: none) ...
        coarse_rim_reach: ... their strips reaching this many semi-major axes either side of
            the ellipse, in ``rim_samples`` rows.
        coarse_rim_gate: at inference the coarse stage runs on the cups whose fine landmarks
            (from the refiner's fit) get no pose (within ``max_theta_deg``), and on those
            whose mean ``log sigma`` (px) exceeds this (None: on no others).
        thin_rim_angles: orientations of the thin-rim hypotheses (see
            :func:`cupnet.rim.thin_rim_starts`) ...
        thin_rim_ratio: ... their axis ratio ...
        thin_rim_gate: ... tried on the cups whose fine landmarks (from the refiner's fit)
            have a mean ``log sigma`` (px) above this (None: on no cup), and on the cups the
            other sources give no pose ...
        thin_rim_margin: ... and their landmarks replace the first ones where their mean
            ``log sigma`` is lower by more than this: a thin ellipse across a femoral head's
            disc can win by chance over an open rim the head partly hides.
        locator_retry_gamma: where the locator finds no cup in an image (no component of
            score ``min_score`` or more), it looks again at the image raised to this power
            (None: it does not): a cup under thick anatomy, in the dark part of an image
            with bright regions, has too little contrast left after standardisation; a power
            below 1 stretches the dark range.
        round_field: drop the locator's cups centred outside the image intensifier's round
            field where the image shows one (:func:`cupnet.field.round_field`: a flat
            surround holding its corners, edged by a circle): the locator, trained on
            square images, takes that surround at an oblong frame's ends for cups.
        metal: how the images show metal: ``"dark"`` (the usual fluoroscopy display, and
            most of the networks' training images: used as given), ``"bright"`` (a
            radiograph-style display, metal white: every image is turned over, as the
            networks find and place rims best with metal dark), or ``"auto"`` (turned over
            after the locator where :func:`cupnet.polarity.metal_shows_bright` finds the
            cups it found brighter than their surroundings; wrong on about 1 % of images).
        denoise_above: an image whose noise (:func:`cupnet.denoise.noise_sigma`, display
            units) exceeds this is taken through non-local means (:func:`cupnet.denoise.denoised`)
            before anything else (None: no image is): noisier than nearly every training
            image, its cups fail grossly more often.
        enlarge_below: an image (or, with ``round_field``, its field's square) whose shorter
            side is under this many pixels is enlarged so that it is ``enlarge_to`` px
            (Lanczos, :func:`cupnet.crops.enlarged`) after the noise check and before the
            networks, its cups reported in its own pixels (None: none is): the networks
            learnt images of 512 px and more, and place a smaller image's rims worse.
        enlarge_to: the shorter side (px) ``enlarge_below`` enlarges an image to.
        reduce_above: an image (or its field's square) whose shorter side is over this many
            pixels is reduced so that it is ``reduce_to`` px (area averaging,
            :func:`cupnet.crops.resized`) at the step where ``enlarge_below`` enlarges a
            small one, its cups reported in its own pixels (None: none is): the networks
            learnt images of 512 and 768 px, and on 2048 px DRRs reduced to 1024 they
            failed grossly less often than on the DRRs as rendered (docs/training.md,
            item 71).
        reduce_to: the shorter side (px) ``reduce_above`` reduces an image to.
        max_theta_deg: a pose with a larger anteversion (deg) counts as a failure of its
            landmarks: the cup goes on to :meth:`CupNet.detect`'s next landmark source and
            keeps that pose only where none gives one within range (None: any anteversion).
            Set it a little above the largest anteversion of the training data: a pose
            beyond it is one the network was never shown, in practice the outline of a
            nearly edge-on cup and its femoral head taken for an open rim, or a nearly
            round rim along the sphere's outline. One reported all the same is verified
            whatever its doubt, replaced by any candidate within range, and else flagged
            ``check``.
        grown_rim_scale: where no other landmark source gives a cup a pose (within
            ``max_theta_deg``), :meth:`CupNet.detect` starts the coarse rim stage again from
            the refiner's ellipse enlarged to this many times the smallest rim the cup can
            make (magnification 1; never shrunk), then the fine stage from the coarse fit;
            None: it does not (needs both rim stages). Where that fails too, the grown
            ellipse's own pose is a start for the verification and search (see
            :meth:`CupNet.reconsidered`).
        reframe_min_scale: each refiner pass's fit is grown (never shrunk) to at least this
            fraction of the semi-major axis of the ellipse its crop was framed on before it
            frames the next pass or starts the rim stages (None: as it is): a fit much
            smaller than its frame is mostly a femoral head inside the cup, and a crop or
            strips framed on it miss the rim.
        outline_passes: passes at most of the dome-outline refinement of each solved pose
            (:meth:`CupNet.outline_refined`; 0: none): the fine rim network locates the
            sphere's outline on the dome's side of the pose's rim plane, and the solver fits
            those landmarks beside the rim's. Needs the fine rim stage.
        outline_min_side: outline points nearer the rim plane than this many radii are left
            out: there the dome's outline meets the rim's tips, and a wrong pose's side of
            the plane may not be the dome's.
        outline_doubt_margin: a solved pose the dome-outline refinement leaves more doubted
            (:meth:`CupNet.pose_doubt`, its two parts summed) than its start by more than
            this keeps its start; None: the refined pose stands whatever its doubt. Where the
            rim runs close inside the dome's outline (a small or wide-open cup), the rim
            network finds the outline between the two edges, and the refinement pulls a
            right rim off (docs/training.md, item 67).
        outline_weight: the outline landmarks' weights are this over their ``sigma^2`` (the
            rim landmarks' are their residual's inverse variance).
        outline_settled: a cup's dome-outline refinement stops once a pass moves its pose by
            less than this fraction of the issue's target accuracy (1 deg, 1 deg, 1 mm, 1 mm,
            8 mm) in every parameter. The passes are a fixed-point iteration whose last
            steps often swing back and forth rather than settle: stopping at the first small
            step is as accurate as going on, and sooner.
        outline_inner_rim_weight: in the dome-outline refinement, the rim landmarks over the
            dome's own shadow (:func:`cupnet.outline.over_dome`) count this much: the edge the
            network finds there is the shell's inner surface, inside the rim.
        outline_rim_resample: each dome-outline pass also takes the fine rim network's
            landmarks across the current pose's own rim, weighted by their inverse variance
            ``1 / sigma^2`` (on the outline landmarks' scale), in place of the landmarks the
            pose was solved from: those came from strips framed on an ellipse fit, often a
            few pixels off where a femoral head's edge crosses the rim, and the pose's rim
            is nearer the true one each pass.
        verify_gate: after the dome-outline refinement, a cup whose refined pose the fine rim
            network doubts (:meth:`CupNet.pose_doubt` at least this) is solved again from
            every landmark source (:meth:`CupNet.verified`), each pose refined with the
            outline, and keeps the one the network doubts least ... (None: no cup; needs
            ``outline_passes``)
        verify_margin: ... where it beats the first pose's doubt by more than this.
        verify_thin_rims: the thin-rim hypotheses among those sources: the fine rim stage from
            each of the hypotheses it trusts most after one pass (at most
            ``thin_rim_angles``).
        verify_turn_deg: a candidate whose anteversion differs from the first pose's by more
            than this (deg) must also beat its doubt on the rim alone by ``verify_margin``
            (None: no such rule): the dome's outline tells the centre, not the rim's
            orientation, and a thin rim at the wrong angle through the right centre fits the
            outline as well as the right rim.
        verify_anteversions: anteversions (deg) to which the first pose's rim is turned (its
            inclination and centre kept) for more of those sources: the fine rim network's
            landmarks across each turned rim. A gross failure left after the outline has the
            centre and mostly the inclination right and the anteversion far off; a turned rim
            within the network's reach of the true one is then drawn to it
            (``outline_rim_resample``).
        ambiguous_by_doubt: of an ambiguous cup's two poses, report first the one
            :meth:`CupNet.pose_doubt` doubts less (otherwise the larger anteversion); needs
            ``outline_passes``.
        search_gate: a cup still doubted this much or more after the verification (the sum
            of the doubt's parts) is searched over its rim's orientation
            (:meth:`CupNet.searched`, in the first look only; None: no cup; needs
            ``verify_gate`` and ``outline_rim_resample``) ...
        search_part_gate: ... and so is a cup either of whose doubt's two parts (rim,
            outline) reaches this (None: the sum alone counts; a rim the network finds
            nowhere near the pose, with a dome outline that fits, sums to little). The
            search: a grid of ``search_anteversions`` (deg) by inclinations every
            ``search_inclination_step`` (deg) at its pose's centre, whose ``search_keep``
            least doubted rims give the candidates ...
        search_keep_settled: ... and so do this many other grid poses (0: none), those
            doubted least once their rim's offsets are settled (the ellipse step their own
            landmarks would fit taken out, :func:`cupnet.rim.settled_offsets`): a thin rim's
            doubt is sharp, about 1 deg wide in inclination, so a grid pose a few pixels off
            the true rim is doubted as if no rim lay there ...
        search_rim_doubt: ... each taken only where the network doubts its rim no more than
            this (None: any); a search candidate must also beat the cup's rim doubt by
            ``verify_margin`` where it turns the rim's anteversion or inclination by more
            than ``verify_turn_deg``. No landmark source proposed it, so the rim must
            support it: a grid pose refined onto a femoral head's outline or the shell's
            inner edge can explain the dome better than a right pose whose rim the image
            hides (true poses' rim doubt: 99th percentile 1.7-2.1 on the evaluation sets).
        search_screen: the search measures the dome's outline (the costlier half of a grid
            pose's doubt) only for the grid poses whose rim, as it lies or settled, ranks
            among each cup's this many best (None: for all; at least ``search_keep +
            search_keep_settled``): the rest, far down on the rim, do not win (at 24, the
            same poses on the benchmark, a fresh seed and the oblong images).
        check_doubt: a detected cup whose reported pose the network doubts this much or
            more (the larger of :meth:`CupNet.pose_doubt`'s rim and outline parts) is
            flagged ``check`` (None: none is): the edges the network finds across its rim or
            dome outline lie off them, as they do for most gross failures (needs
            ``outline_passes``). A cup reported beyond ``max_theta_deg`` is flagged too.
            The flag alone: which cups the later looks look at again goes by
            ``look_again_doubt``.
        look_again_doubt: while :meth:`CupNet.detect` looks, a cup counts as flagged (one
            the later looks look at again, and a later look's detection one they do not
            believe) where doubted this much or more, or beyond ``max_theta_deg`` (None:
            ``check_doubt``); ``check_doubt`` flags the cups reported once every look is
            done. Above ``check_doubt``, more cups are flagged for a look by eye than are
            looked at again: the flag catches most gross failures, and the later looks'
            work and poses stay those of the threshold they were chosen with
            (docs/training.md, item 51).
        second_look: an image with a cup flagged (``look_again_doubt``) or failed is
            detected again with the locator on its mirror image, and such a cup takes the
            second look's unflagged detection of the same place where that one is doubted
            less (:meth:`CupNet._looked_again`; needs ``look_again_doubt`` or
            ``check_doubt``). This look verifies its doubtful cups but searches none
            (:meth:`CupNet.later_looks`).
        third_look_gamma: ... and an image with a cup still flagged or failed after that is
            detected again with the locator on the image raised to this power, the same rule
            taking its detections, verified but not searched (None: no third look).
        high_gamma_look: ... and an image with a cup still flagged or failed, or with no
            cup found, is detected again with the locator on the image raised to this power
            (above 1), verified but not searched, the same rule taking its detections and
            an image without a cup taking those it believes (None: no such look): a high
            power darkens a bright surround, where bright metal on bright, nearly saturated
            anatomy gave the first looks no blob or a wrong frame (docs/training.md, item
            43).
        fourth_look_turned: ... and once more with the locator on the image turned over
            (``1 - image``), so the polarity check judges its display afresh: a cup
            whose metal the first looks took to show dark where it shows bright (or the
            other way) is framed and segmented in the display the networks learnt. This
            look also looks at the images where no cup was found, and keeps the cups it
            finds there that it would let replace one; it verifies no cup.
        turned_look_doubt: ... where the network doubts it less than this, too (None:
            wherever it is not flagged, as the other looks'): turned over, a blob on no cup
            can be judged a cup in the other display and believed only just.
        partner_look: the mirrored look (``second_look``) also looks at the images with
            fewer cups than ``max_cups`` (none included) for cups elsewhere, and adds those
            it believes (not flagged): the locator passes over a bilateral pair's second
            cup more often than over a lone one, and a pair's cups are mirror images of each
            other, so the mirrored locator sees the missed one much as it saw the found one;
            where it found no cup, the mirrored look is a second, nearly independent
            framing. Only blobs away from the believed cups get the cup stages
            (docs/training.md, items 42 and 43). The high gamma look
            (``high_gamma_look``) does the same, without verifying the images it sees for
            that alone (item 44): a power of 3 frames a pair's second cup that neither the
            first look nor its mirror image framed.
        partner_doubt: a cup a partner look adds beside the cups found must be doubted
            less than this, too (None: any cup not flagged): a blob elsewhere on the
            anatomy, believed only just, is a made-up cup (item 44).
        rod_look: ... and, last, an image with a cup still flagged or failed where
            :func:`cupnet.rod.find_rod` finds a straight rod (the cup's inserter, during
            impaction) is detected again with the rod painted over, every stage seeing it
            so, verified but not searched, the same rule taking its detections: the rod
            cuts the opening in two, and such a cup's rim was mostly fitted to one half
            (docs/training.md, item 70).
        blur_rim: the model holds a second fine rim network (``rim_channels`` wide, the same
            strips), trained on blurrier images than the first (docs/training.md, item 76).
        blurred: every rim stage runs that network in place of the first (needs
            ``blur_rim``; ``cupnet predict --blurred``): for images blurrier than a sharp
            DRR, where the first network's rim lies off by a bias that grows with the blur.
    """

    encoder: str = "timm-mobilenetv3_small_100"
    decoder_channels: tuple[int, ...] = (64, 32, 16, 16, 8)
    encoder_weights: str | None = None
    locator_size: int = 128
    crop_size: int = 128
    crop_fill: float = 0.78
    crop_min_ratio: float = 0.5
    crop_max_stretch: float = 6.0
    n_rays: int = 64
    ray_samples: int = 128
    max_cups: int = 2
    detect_threshold: float = 0.5
    min_cup_area: float = 4.0
    min_score: float | None = None
    refine_passes: int = 2
    locator_scale: float = 1.15
    rim_passes: int = 0
    rim_points: int = 128
    rim_samples: int = 64
    rim_step: float = 0.5
    rim_channels: int = 16
    coarse_rim_channels: int | None = None
    coarse_rim_passes: int = 0
    coarse_rim_reach: float = 0.6
    coarse_rim_gate: float | None = None
    thin_rim_angles: int = 12
    thin_rim_ratio: float = 0.15
    thin_rim_gate: float | None = None
    thin_rim_margin: float = 0.0
    locator_retry_gamma: float | None = None
    round_field: bool = False
    metal: str = "dark"
    denoise_above: float | None = None
    enlarge_below: int | None = None
    enlarge_to: int = 512
    reduce_above: int | None = None
    reduce_to: int = 1024
    max_theta_deg: float | None = None
    grown_rim_scale: float | None = None
    reframe_min_scale: float | None = None
    outline_passes: int = 0
    outline_min_side: float = 0.3
    outline_doubt_margin: float | None = None
    outline_weight: float = 0.5
    outline_settled: float = 0.05
    outline_inner_rim_weight: float = 1.0
    outline_rim_resample: bool = False
    verify_gate: float | None = None
    verify_margin: float = 0.8
    verify_thin_rims: int = 3
    verify_turn_deg: float | None = None
    verify_anteversions: tuple[float, ...] = ()
    ambiguous_by_doubt: bool = False
    search_gate: float | None = None
    search_anteversions: tuple[float, ...] = (3.0, 10.0, 20.0, 30.0, 40.0, 48.0)
    search_inclination_step: float = 15.0
    search_keep: int = 4
    search_part_gate: float | None = None
    search_keep_settled: int = 0
    search_rim_doubt: float | None = None
    search_screen: int | None = None
    check_doubt: float | None = None
    look_again_doubt: float | None = None
    second_look: bool = False
    third_look_gamma: float | None = None
    high_gamma_look: float | None = None
    fourth_look_turned: bool = False
    turned_look_doubt: float | None = None
    partner_look: bool = False
    partner_doubt: float | None = None
    rod_look: bool = False
    blur_rim: bool = False
    blurred: bool = False

    def __post_init__(self) -> None:
        # Sizes and counts: 0 or less had failed only at the first forward (a negative crop
        # in kornia's warp, a division by zero rays).
        for name, least in LEAST.items():
            if getattr(self, name) < least:
                raise ValueError(f"{name} must be >= {least}, got {getattr(self, name)}")
        if not self.decoder_channels or min(self.decoder_channels) < 1:
            # A zero width had failed in a convolution at the first forward, unnamed.
            raise ValueError(f"decoder_channels must be one or more widths >= 1, got "
                             f"{list(self.decoder_channels)}")
        if self.metal not in METAL_DISPLAYS:
            raise ValueError(f"unknown metal display {self.metal!r}; choose from "
                             f"{', '.join(METAL_DISPLAYS)}")
        if (self.reduce_above is not None and self.enlarge_below is not None
                and self.reduce_above < self.enlarge_below):
            raise ValueError(f"reduce_above ({self.reduce_above}) must be at least "
                             f"enlarge_below ({self.enlarge_below}): a side between them "
                             "would be both enlarged and reduced")
        kept = self.search_keep + self.search_keep_settled
        if self.search_screen is not None and self.search_screen < kept:
            # The grid poses past the screen have no outline doubt to rank them by.
            raise ValueError(f"search_screen ({self.search_screen}) must be at least "
                             f"search_keep + search_keep_settled ({kept}), the grid poses "
                             "the search keeps")
        if self.blurred and not self.blur_rim:
            raise ValueError(BLURRED_WITHOUT_BLUR_RIM)

    @classmethod
    def from_dict(cls, values: dict) -> CupNetConfig:
        unknown = cls.unknown_fields(values)
        if unknown:
            raise ValueError(f"unknown CupNet config keys: {unknown}")
        hints = {f.name: str(f.type) for f in fields(cls)}
        return cls(**{key: _field_value(key, value, hints[key]) for key, value in values.items()})


def _field_value(name: str, value: Any, hint: str) -> Any:
    """``value`` of the config field ``name`` as its annotation ``hint`` (``"int"``,
    ``"float | None"``, ``"tuple[float, ...]"``...) says, or a ValueError naming the field.

    JSON and YAML give lists where the config holds tuples, and a training command line
    (``--model.model.rim_channels 8``: the LightningModule takes the config as a dict, so
    jsonargparse cannot type its keys) gives strings, read here as YAML values.
    """
    kinds = {part.strip() for part in hint.split("|")}
    if isinstance(value, str) and ("str" not in kinds or "None" in kinds):
        try:
            read = yaml.safe_load(value)
        except yaml.YAMLError:
            read = value  # left a string: the check below names the field
        # Text is kept for a text field, but YAML's null (the 'null' of a command line's
        # --model.model.encoder_weights null) is None for one that takes None.
        value = read if "str" not in kinds or read is None else value
    if value is None and "None" in kinds:
        return None
    for kind in kinds:
        if kind.startswith("tuple[") and isinstance(value, list | tuple):
            element = kind[len("tuple["):].split(",")[0].strip()
            return tuple(_field_value(name, item, element) for item in value)
    if isinstance(value, bool):
        if "bool" in kinds:
            return value
    elif "int" in kinds and isinstance(value, int | float) and float(value).is_integer():
        return int(value)
    elif "float" in kinds and isinstance(value, int | float):
        return float(value)
    elif "str" in kinds and isinstance(value, str):
        return value
    raise ValueError(f"CupNet config {name}: expected {hint}, got {value!r}")


# Faster operating points of a trained model: inference settings only, the weights unchanged
# (figures in docs/benchmarks.md, "CupNet accuracy" and "CupNet speed").
SPEED_PRESETS: dict[str, dict[str, object]] = {
    # no verification, so no search either, of doubtful cups (items 12 and 16 of
    # docs/training.md); the later looks at flagged ones stay (items 32-34: on the
    # selection seeds theta 0.94 -> 0.69 deg, 548 -> 553 of 561 cups found, for an eighth
    # more time)
    "fast": {"verify_gate": None},
    # ... nor the dome's outline (so no doubt, no check flag and no ordering of ambiguous
    # pairs, which all measure the pose against the outline) nor the thin-rim hypotheses,
    # nor the later looks: segmentation, the rim stages and the solver alone
    "fastest": {"verify_gate": None, "outline_passes": 0, "thin_rim_gate": None,
                "second_look": False, "third_look_gamma": None, "high_gamma_look": None,
                "fourth_look_turned": False, "rod_look": False},
}


def apply_speed_preset(config: CupNetConfig, preset: str | None) -> CupNetConfig:
    """``config`` with the inference settings of the :data:`SPEED_PRESETS` entry ``preset``
    (None: unchanged), in place; an unknown name is a ValueError naming the presets."""
    if preset is None:
        return config
    if preset not in SPEED_PRESETS:
        raise ValueError(f"unknown speed preset {preset!r}; choose from "
                         f"{', '.join(SPEED_PRESETS)}")
    return config.update(**SPEED_PRESETS[preset])
