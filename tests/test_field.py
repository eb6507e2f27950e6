"""The intensifier's round field: found from its flat surround, and the cups outside it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from cupnet.field import CROP_BELOW, content_crop, field_crop, outside_field, round_field
from data_synth import SynthConfig
from data_synth.formation import form_image


def framed(height: int, width: int, centre: tuple[float, float], radius: float,
           surround: float = 0.03, seed: int = 0) -> np.ndarray:
    """``(H, W)`` textured noise inside a disc, a flat ``surround`` outside it (float32)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[:height, :width]
    image = 0.3 + 0.4 * rng.random((height, width))
    image[np.hypot(u - centre[0], v - centre[1]) > radius] = surround
    return image.astype(np.float32)


@pytest.mark.parametrize(("height", "width", "centre", "radius"), [
    (480, 640, (330.0, 235.0), 236.0),   # 4:3 video frame, the disc a little off centre
    (512, 768, (383.5, 255.5), 300.0),   # the disc wider than the frame is high
    (768, 512, (255.5, 383.5), 240.0),   # portrait
    (2400, 3200, (1610.0, 1190.0), 1160.0),  # large: looked at every other pixel
])
def test_round_field_recovers_a_drawn_disc(height, width, centre, radius):
    found = round_field(torch.from_numpy(framed(height, width, centre, radius))[None])
    assert found is not None
    cx, cy, r = found
    step = max(1, min(height, width) // 1024)  # the pixels round_field looks at
    assert math.hypot(cx - centre[0], cy - centre[1]) < step
    # The flat test looks 2 px around: the surround's edge lies up to 3 px outside the disc.
    assert radius - step <= r <= radius + 3.5 * step


def test_round_field_of_data_synths_intensifier_frame():
    # An independent generator: data_synth's image formation with its round field, centred.
    height, width, radius = 400, 600, 210.0
    line_integral = torch.from_numpy(np.random.default_rng(1).uniform(0.5, 2.5, (height, width)))
    for seed in range(4):  # the formation's random settings: bits, inversion, surround
        image = form_image(line_integral, radius, SynthConfig(), np.random.default_rng(seed))
        cx, cy, r = round_field(image)
        assert math.hypot(cx - (width - 1) / 2, cy - (height - 1) / 2) < 1.0
        # Its edge is soft (2 px): the surround's flat part begins up to 5 px out.
        assert radius - 1 <= r <= radius + 5


def test_a_saturated_stem_joining_the_surround_does_not_bend_the_circle():
    image = framed(480, 640, (319.5, 239.5), 230.0)
    image[300:, 300:340] = 0.03  # metal as flat as the surround, from inside out to it
    cx, cy, r = round_field(image)
    assert math.hypot(cx - 319.5, cy - 239.5) < 1.0 and 230.0 <= r <= 233.5


@pytest.mark.parametrize(("levels", "flat"), [(50, True), (100, False)])
def test_a_surround_is_flat_up_to_a_thousandth(levels, flat):
    # A 16-bit capture's surround some levels off black: 50 of 65535 (7.6e-4) is flat,
    # 100 (1.5e-3) is not, and without a flat corner there is no field.
    image = framed(480, 640, (319.5, 239.5), 236.0)
    dark = image == 0.03
    image[dark] += np.random.default_rng(3).integers(0, levels + 1, dark.sum()) / 65535
    found = round_field(image)
    assert (found is not None) == flat
    if flat:
        cx, cy, r = found
        assert math.hypot(cx - 319.5, cy - 239.5) < 1.0 and 236.0 <= r <= 239.5


def test_a_jpeg_frame_keeps_its_field_a_little_wider():
    # JPEG's ringing roughens the surround's edge and its flat part starts farther out: the
    # circle may only grow (a wider field drops fewer blobs, never a cup inside the disc).
    image = framed(480, 640, (319.5, 239.5), 236.0)
    _, jpeg = cv2.imencode(".jpg", np.round(image * 255).astype(np.uint8),
                           [cv2.IMWRITE_JPEG_QUALITY, 75])
    cx, cy, r = round_field(cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255)
    assert math.hypot(cx - 319.5, cy - 239.5) < 2.0 and 236.0 <= r <= 248.0


def test_text_burnt_into_the_surrounds_corners_does_not_hide_the_field():
    image = framed(480, 640, (319.5, 239.5), 236.0)
    text = np.zeros(image.shape, np.uint8)
    for u, v in ((4, 20), (470, 20), (4, 470), (470, 470)):  # every corner
        cv2.putText(text, "PATIENT 12", (u, v), cv2.FONT_HERSHEY_SIMPLEX, 0.6, 255, 2)
    image[text > 0] = 1.0
    cx, cy, r = round_field(image)
    assert math.hypot(cx - 319.5, cy - 239.5) < 1.0 and 236.0 <= r <= 239.5


@pytest.mark.parametrize("case", ["noise", "one corner", "short arc", "off centre",
                                  "shutters", "octagon", "small disc", "flat disc",
                                  "air in a corner", "all flat", "tiny"])
def test_no_round_field_where_the_image_shows_none(case):
    # A flat patch with a curved edge (bright air, a saturated stem) or a short arc's
    # circle must not pass for the field and drop true cups. The drawn fields are turned
    # down each by one check alone; the rest have no flat corner or too few edge points.
    rng = np.random.default_rng(2)
    image = (0.3 + 0.4 * rng.random((480, 640))).astype(np.float32)
    if case == "one corner":  # an arc too short to fit: the circle falls off centre
        image = framed(480, 640, (365.0, 275.0), 422.0)
    elif case == "short arc":  # one corner's arc: its circle would cut the field
        image = framed(480, 640, (362.4, 192.9), 415.1)
    elif case == "off centre":  # no intensifier's disc is framed this far off
        image = framed(480, 640, (150.0, 240.0), 300.0)
    elif case == "shutters":  # a rectangular collimator: a flat frame with straight edges
        image[:60], image[-60:], image[:, :80], image[:, -80:] = 0.02, 0.02, 0.02, 0.02
    elif case == "octagon":  # an iris collimator's field: not round
        angles = np.radians(22.5 + 45 * np.arange(8))
        corners = np.stack([319.5 + 250 * np.cos(angles), 239.5 + 250 * np.sin(angles)], 1)
        mask = np.zeros(image.shape, np.uint8)
        cv2.fillPoly(mask, [np.round(corners).astype(np.int32)], 1)
        image[mask == 0] = 0.02
    elif case == "small disc":  # a round patch, not a field: narrower than a quarter side
        image = framed(480, 640, (319.5, 239.5), 100.0)
    elif case == "flat disc":  # bright air or metal, flat inside its circle, at the border
        v, u = np.mgrid[:480, :640]
        image[np.hypot(u - 319.5, v - 239.5) < 150] = 1.0
        image[235:245, 319:] = 1.0
    elif case == "air in a corner":  # flat bright air beyond the body, round-edged
        v, u = np.mgrid[:480, :640]
        image[np.hypot(u, v) < 200] = 1.0
    elif case == "all flat":
        image[:] = 0.03
    elif case == "tiny":
        image = framed(8, 8, (3.5, 3.5), 3.0)
    assert round_field(image) is None


def test_outside_field_by_hand():
    centres = torch.tensor([[100.0, 100.0], [100.0, 151.0], [math.nan, math.nan]])
    assert outside_field(centres, (100.0, 100.0, 50.0)).tolist() == [False, True, False]
    assert outside_field(centres, None).tolist() == [False, False, False]


@pytest.mark.parametrize(("height", "width", "centre", "radius", "crop"), [
    # A screenshot: the disc half the frame's height, with text beside it. The square is
    # the disc's bounding square (the surround's flat part starts up to 3 px out).
    (600, 900, (449.5, 299.5), 150.0, True),
    (600, 900, (430.0, 310.0), 0.44 * 600, True),  # just narrower than CROP_BELOW
    (600, 900, (449.5, 299.5), 0.46 * 600, False),  # as narrow as training's narrowest
    (480, 640, (319.5, 239.5), 236.0, False),  # a video frame's disc: taken whole
])
def test_field_crop_cuts_out_a_field_narrower_than_training_showed(height, width, centre,
                                                                   radius, crop):
    image = framed(height, width, centre, radius)
    text = np.zeros(image.shape, np.uint8)
    cv2.putText(text, "L HIP 72 kV", (5, height - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.8, 255, 2)
    image[text > 0] = 1.0
    found = field_crop(image)
    assert (found is not None) == crop
    if crop:
        u0, v0, side = found
        cx, cy, r = round_field(image)
        assert 2 * r < CROP_BELOW * height
        # The disc's bounding square, whole, in the image: every exposed pixel kept.
        assert abs(u0 - (cx - r)) <= 0.5 and abs(v0 - (cy - r)) <= 0.5
        assert side == math.ceil(2 * r) + 1
        v, u = np.nonzero(image > 0.03)
        inside = np.hypot(u - centre[0], v - centre[1]) <= radius
        assert u[inside].min() >= u0 and u[inside].max() < u0 + side
        assert v[inside].min() >= v0 and v[inside].max() < v0 + side
    assert field_crop(np.full((600, 900), 0.5, np.float32)) is None  # no field at all


def test_detect_cuts_a_narrow_field_out_of_its_frame_and_answers_in_the_frames_pixels():
    # A 512 px intensifier frame pasted into a 900 x 600 capture with wide flat margins and
    # burnt-in text: its disc spans 0.8 of the capture's height, narrower than any training
    # frame's, so detect looks at the disc's square and maps the cups back.
    from cupnet.geometry import Geometry
    from cupnet.model import load_model
    from data_synth import synthesize

    config = SynthConfig(image_size=(512, 512), p_anatomy=0.0, p_circular_field=1.0,
                         field_radius_frac=(0.47, 0.47), p_bilateral=0.0, p_no_cup=0.0)
    sample = synthesize(config, 3, 0)
    frame = sample["image"][0]
    capture = torch.full((600, 900), float(frame[0, 0]))  # the surround, flat to the edge
    capture[44:556, 194:706] = frame
    text = np.zeros((600, 900), np.uint8)
    cv2.putText(text, "L HIP 2026-11-03", (5, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, 255, 2)
    capture[torch.from_numpy(text > 0)] = 1.0
    model = load_model()
    cup = _pasted_cup(model, sample, capture, (194, 44))
    sdd, spacing, u0, v0 = (float(v) for v in sample["geometry"])
    diameter = float(sample["cup_diameter"][0])
    # Exactly the detection of the square cut by hand, moved to the capture's pixels.
    left, top, side = field_crop(capture)
    square = capture[top:top + side, left:left + side]
    (alone,) = model.detect(square[None, None], Geometry(sdd, spacing, u0 + 194 - left,
                                                         v0 + 44 - top), diameter)[0]
    np.testing.assert_array_equal(cup.pose, alone.pose)
    # The square (491 px) is under the shipped enlarge_below: both were enlarged to 512 px
    # first, and mapped back through the enlargement, then the cut.
    assert side < model.config.enlarge_below
    assert cup.enlarged == alone.enlarged == pytest.approx(model.config.enlarge_to / side)
    np.testing.assert_array_equal(cup.ellipse[:2], alone.ellipse[:2] + (left, top))
    np.testing.assert_array_equal(cup.landmarks, alone.landmarks + (left, top))
    np.testing.assert_array_equal(cup.outline, alone.outline + (left, top))
    assert cup.mask.shape == (600, 900) and cup.mask.sum() == pytest.approx(alone.mask.sum())
    np.testing.assert_array_equal(cup.mask[top:top + side, left:left + side], alone.mask)


def test_content_crop_cuts_a_frame_off_a_wide_flat_canvas():
    """A square frame (no round field) pasted on a black canvas: the bounding square of the
    frame, 4 px wider a side (2 of the 5 x 5 flatness window, 2 of margin); text burnt
    into the canvas's far corners, a frame filling the canvas, or an image without a flat
    corner: none."""
    rng = np.random.default_rng(0)
    canvas = np.zeros((2000, 1800), np.float32)
    canvas[700:1212, 600:1112] = rng.uniform(0.2, 0.8, (512, 512))
    assert content_crop(canvas) == (596, 696, 520)
    assert content_crop(torch.from_numpy(canvas)[None]) == (596, 696, 520)
    text = np.zeros(canvas.shape, np.uint8)
    cv2.putText(text, "L", (1300, 1900), cv2.FONT_HERSHEY_SIMPLEX, 2.0, 255, 3)
    # Text widens the square, here to hold it (the frame still inside) ...
    u0, v0, side = content_crop(np.where(text > 0, 1.0, canvas))
    assert u0 <= 600 and v0 <= 700 and u0 + side >= 1340 and v0 + side >= 1900
    # ... and in the canvas's far corners past CROP_BELOW: the image is taken whole.
    cv2.putText(text, "PATIENT 0421", (20, 60), cv2.FONT_HERSHEY_SIMPLEX, 2.0, 255, 3)
    assert content_crop(np.where(text > 0, 1.0, canvas)) is None
    full = np.zeros((600, 600), np.float32)
    full[20:580, 20:580] = rng.uniform(0.2, 0.8, (560, 560))
    assert content_crop(full) is None
    assert content_crop(rng.uniform(0, 1, (300, 300)).astype(np.float32)) is None


def test_detect_finds_the_cup_of_a_frame_pasted_on_a_wide_black_canvas():
    """A 512 px frame without a round field on a 1600 px black canvas: the locator, seeing
    the canvas whole, had found no cup ('no_cup'); it now looks at the frame's square and
    answers in the canvas's pixels, as for the frame alone."""
    from cupnet.model import load_model
    from data_synth import synthesize

    config = SynthConfig(image_size=(512, 512), p_circular_field=0.0, p_bilateral=0.0,
                         p_no_cup=0.0)
    sample = synthesize(config, 5, 0)
    canvas = torch.zeros(1600, 1600)
    canvas[600:1112, 500:1012] = sample["image"][0]
    _pasted_cup(load_model(), sample, canvas, (500, 600))


def _pasted_cup(model: object, sample: dict, picture: torch.Tensor, offset: tuple[int, int]
                ) -> object:
    """The one cup ``model`` detects in ``picture`` ``(H, W)``, which holds ``sample``'s
    frame pasted at ``offset`` ``(u, v)``, asserted where the frame shows it (centre within
    2 px) with the frame's pose (angles within 1 deg)."""
    from cupnet.geometry import Geometry

    sdd, spacing, u0, v0 = (float(v) for v in sample["geometry"])
    (cup,) = model.detect(picture[None, None],
                          Geometry(sdd, spacing, u0 + offset[0], v0 + offset[1]),
                          float(sample["cup_diameter"][0]))[0]
    truth = sample["ellipse"][0].numpy()
    assert np.hypot(*(cup.ellipse[:2] - truth[:2] - offset)) < 2.0
    assert np.abs(cup.pose[:2] - sample["pose"][0, :2].numpy()).max() < 1.0
    return cup
