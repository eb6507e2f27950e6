"""benchmarks/model.py's screenshots: the frames they hold, and what detect makes of them."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.model import captured, in_a_disc
from cupnet.field import field_crop
from data_synth import SynthConfig, synthesize


def test_a_capture_holds_the_frame_with_its_geometry_and_cups_moved_along():
    sample = synthesize(SynthConfig(image_size=(512, 512), p_anatomy=0.0), 4, 0)
    frame, capture = in_a_disc(sample), captured(sample)
    left, top = int(0.2 * 512), int(0.08 * 512)
    assert capture["image"].shape == (1, 512 + 2 * top, 512 + 2 * left)
    # The frame's disc, 8-bit, where the capture puts it (the side marker lies on its corner,
    # outside the disc); the true ellipses and principal point moved by the same offset.
    v, u = np.mgrid[:512, :512]
    disc = np.hypot(u - 255.5, v - 255.5) <= 0.49 * 512
    inside = capture["image"][0, top:top + 512, left:left + 512].numpy()[disc]
    np.testing.assert_allclose(inside, frame["image"][0].numpy()[disc], atol=1 / 255)
    offset = torch.tensor([left, top], dtype=torch.float64)
    torch.testing.assert_close(capture["ellipse"][:, :2].double(),
                               sample["ellipse"][:, :2].double() + offset)
    torch.testing.assert_close(capture["geometry"][2:].double(),
                               sample["geometry"][2:].double() + offset)
    # The frame's disc is as wide as training's; in the capture it is narrower, so detect
    # cuts it out, whole, text aside.
    assert field_crop(frame["image"][0]) is None
    u0, v0, side = field_crop(capture["image"][0])
    # (The surround's flat part starts a few pixels out from the disc.)
    assert abs(u0 - left) <= 6 and abs(v0 - top) <= 6 and 0 <= side - 0.98 * 512 <= 12
