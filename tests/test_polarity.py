"""Which way an image shows metal: the cue on hand-made images, and detect's turned images."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cupnet.config import TARGET_ACCURACY, CupNetConfig
from cupnet.geometry import Geometry
from cupnet.model import load_model
from cupnet.polarity import REPORT_MARGIN, metal_shows_bright, metals_show_bright
from data_synth import SynthConfig, synthesize

ELLIPSE = torch.tensor([[60.0, 50.0, 20.0, 12.0, 30.0]], dtype=torch.float64)


def disc_image(inside: float, around: float) -> torch.Tensor:
    """``(1, 100, 120)``: ``inside`` within the shell's outline (the ellipse's major axis as
    its radius), ``around`` elsewhere, and black and white stripes far from the cup, so that
    the image's 5-95 % range is 0-1."""
    v, u = torch.meshgrid(torch.arange(100.0), torch.arange(120.0), indexing="ij")
    image = torch.full((100, 120), around)
    image[(u - 60) ** 2 + (v - 50) ** 2 <= 20**2] = inside
    image[:50, 100:], image[50:, 100:] = 0.0, 1.0
    return image[None]


def test_a_dark_cup_is_metal_dark_and_a_bright_one_metal_bright():
    assert metal_shows_bright(disc_image(0.1, 0.7), ELLIPSE) is False
    assert metal_shows_bright(disc_image(0.9, 0.3), ELLIPSE) is True
    # Brighter, but within the margin (0.15 of the 5-95 % range): kept as given.
    assert metal_shows_bright(disc_image(0.6, 0.5), ELLIPSE) is False
    assert metal_shows_bright(disc_image(0.7, 0.5), ELLIPSE) is True
    # The margin detect reports the display by, once no image is turned over by it: the sign.
    assert metal_shows_bright(disc_image(0.6, 0.5), ELLIPSE, REPORT_MARGIN) is True
    assert metal_shows_bright(disc_image(0.45, 0.5), ELLIPSE, REPORT_MARGIN) is False


@pytest.mark.parametrize("transposed", [False, True])
def test_a_cup_near_the_long_side_of_an_oblong_image_is_judged(transposed):
    """A dark cup 260 px along a 100 x 300 image (and the image transposed): its pixels lie
    inside the image only when u is bounded by the width and v by the height."""
    v, u = torch.meshgrid(torch.arange(100.0), torch.arange(300.0), indexing="ij")
    image = torch.full((100, 300), 0.7)
    image[(u - 260) ** 2 + (v - 50) ** 2 <= 20**2] = 0.1
    image[:, :20] = torch.arange(100.0)[:, None] / 99  # a full 0-1 range, away from the cup
    ellipse = [260.0, 50.0, 20.0, 12.0, 30.0]
    if transposed:  # u and v swapped, the axis angle mirrored about the diagonal
        image, ellipse = image.T, [50.0, 260.0, 20.0, 12.0, 60.0]
    assert metal_shows_bright(image[None], torch.tensor([ellipse], dtype=torch.float64)) is False


def test_no_cup_to_judge_by_gives_none():
    image = disc_image(0.9, 0.3)
    assert metal_shows_bright(image, torch.full((2, 5), math.nan)) is None
    far = torch.tensor([[1000.0, 1000.0, 20.0, 12.0, 0.0]], dtype=torch.float64)
    assert metal_shows_bright(image, far) is None
    # A NaN row beside a cup: the cup decides.
    both = torch.cat([ELLIPSE, torch.full((1, 5), math.nan, dtype=torch.float64)])
    assert metal_shows_bright(image, both) is True
    assert metal_shows_bright(image, torch.zeros(0, 5, dtype=torch.float64)) is None


def test_a_batch_is_judged_image_by_image():
    """:func:`metals_show_bright` of a batch: each image's own verdict, an image without a
    cup unjudged (and not bright), a batch of none empty."""
    images = torch.stack([disc_image(0.1, 0.7), disc_image(0.9, 0.3), disc_image(0.9, 0.3)])
    ellipses = torch.stack([ELLIPSE, ELLIPSE, torch.full((1, 5), math.nan,
                                                         dtype=torch.float64)])
    bright, judged = metals_show_bright(images, ellipses)
    assert bright.tolist() == [False, True, False] and judged.tolist() == [True, True, False]
    bright, judged = metals_show_bright(images[:0], ellipses[:0])
    assert bright.shape == judged.shape == (0,)


def test_an_unknown_metal_display_is_named_with_the_choices():
    with pytest.raises(ValueError, match="unknown metal display 'grey'.*dark, bright, auto"):
        CupNetConfig(metal="grey")


@pytest.fixture(scope="module")
def drr_detections():
    """The shipped model on a DRR (metal dark) and on the same DRR turned over (metal
    bright), with each metal setting; poses ``(cups, 5)`` and the cups' ``metal_bright`` by
    (setting, image), the true pose, and how far two refinements of one cup from nearby
    starts may end apart ``(5,)``: the step under which the dome-outline passes stop."""
    model = load_model()
    sample = synthesize(SynthConfig(image_size=(512, 512), p_anatomy=0.0, p_invert=0.0), 0, 0)
    geometry = Geometry.from_row(sample["geometry"])
    images = {"dark": sample["image"], "bright": 1 - sample["image"]}
    poses, judged = {}, {}
    for metal in ("dark", "bright", "auto"):
        model.config.metal = metal
        for shown, image in images.items():
            found = model.detect(image[None], geometry, float(sample["cup_diameter"][0]),
                                 return_masks=False)[0]
            poses[metal, shown] = np.array([cup.pose for cup in found])
            judged[metal, shown] = [cup.metal_bright for cup in found]
    settled = model.config.outline_settled * np.array(TARGET_ACCURACY)
    return poses, judged, sample["pose"][:1].double().numpy(), settled


def test_bright_and_auto_turn_a_metal_bright_image_into_the_dark_ones_poses(drr_detections):
    """Turned over (1 - image, exact to a float32 rounding), the bright DRR gives the dark
    DRR's poses (to the outline passes' stopping step: the locator, which ``auto`` runs on
    the image as given, starts them a hair apart); ``auto`` turns the bright one and leaves
    the dark one, so it gives them on both; and the dark DRR's poses are the truth's."""
    poses, _, truth, settled = drr_detections
    reference = poses["dark", "dark"]
    assert reference.shape == (1, 5)
    assert np.allclose(reference[:, :2], truth[:, :2], atol=1.0)
    assert (np.abs(poses["bright", "bright"] - reference) < settled).all()
    assert (np.abs(poses["auto", "bright"] - reference) < settled).all()
    assert np.array_equal(poses["auto", "dark"], reference)  # not turned: the same run


def test_each_cup_says_which_display_its_image_was_taken_to_show(drr_detections):
    """``metal_bright``: the setting's display for ``dark`` and ``bright`` whatever the
    image, the cue's judgement for ``auto``."""
    _, judged, _, _ = drr_detections
    assert judged["dark", "dark"] == judged["dark", "bright"] == [False]
    assert judged["bright", "dark"] == judged["bright", "bright"] == [True]
    assert judged["auto", "dark"] == [False] and judged["auto", "bright"] == [True]
