"""benchmarks/predict.py's folder: images at the asked size, their geometry scaled to match."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks.predict import make_folder


def read_meta(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_resized_images_keep_their_detector_and_rendered_ones_are_the_synth_images(
        tmp_path: Path) -> None:
    native_images, native_meta = make_folder(tmp_path / "native", 3, 2, 7, 64, 64)
    resized_images, resized_meta = make_folder(tmp_path / "resized", 3, 2, 7, 128, 64)
    synth = tmp_path / "native" / "synth"
    native, resized = read_meta(native_meta), read_meta(resized_meta)
    assert [row["image"] for row in native] == [f"bench_{i:05d}.png" for i in range(3)]
    for i, (a, b) in enumerate(zip(native, resized, strict=True)):
        image = cv2.imread(str(native_images / a["image"]), cv2.IMREAD_UNCHANGED)
        big = cv2.imread(str(resized_images / b["image"]), cv2.IMREAD_UNCHANGED)
        assert image.dtype == big.dtype == np.uint16
        assert image.shape == (64, 64) and big.shape == (128, 128)
        # Rendered at its size: the synthesised file itself (the third repeats the first).
        source = cv2.imread(str(synth / "images" / f"synth_{i % 2:06d}.png"),
                            cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(image, source)
        # Twice the pixels over the same detector: half the spacing, the principal point's
        # pixel centre at the same place (pixel centres at integers in both grids).
        assert float(b["pixel_spacing_mm"]) == pytest.approx(float(a["pixel_spacing_mm"]) / 2)
        for key in ("principal_u_px", "principal_v_px"):
            assert float(b[key]) == pytest.approx((float(a[key]) + 0.5) * 2 - 0.5)
        assert b["sdd_mm"] == a["sdd_mm"] and b["cup_diameter_mm"] == a["cup_diameter_mm"]
