"""benchmarks/predict.py's folder: images at the asked size, their geometry scaled to match."""

from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from markdown_tables import table_cells

from benchmarks import predict as bench_predict
from benchmarks.predict import make_folder, measure


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


# A run's figures as the child process prints them, and its results.csv rows (image, status).
CHILD_FIGURES = {"startup_s": 3.0, "run_s": 4.0, "cpu_s": 5.0, "peak_rss_mb": 900.0}
RESULTS = [("a.png", "ok"), ("a.png", "ambiguous"), ("b.png", "no_cup"),
           ("c.png", "error: unreadable"), ("d.png", "ok")]


def fake_predict(command: list[str], **_: object) -> SimpleNamespace:
    """``cupnet predict`` in a child process, stubbed: writes results.csv where the timed run
    would, and prints the child's figures."""
    run = json.loads(command[-1])[1]
    out = Path(run[run.index("--out") + 1])
    out.mkdir(parents=True)
    with (out / "results.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["image", "status"])
        writer.writerows(RESULTS)
    return SimpleNamespace(stdout="start-up noise\n" + json.dumps(CHILD_FIGURES) + "\n")


def test_a_run_counts_its_images_cups_found_and_error_rows(tmp_path, monkeypatch):
    """Cups found: the ok and the ambiguous rows (both have a pose); images: distinct names;
    error rows: statuses starting "error"."""
    monkeypatch.setattr(bench_predict, "subprocess", SimpleNamespace(run=fake_predict))
    images = tmp_path / "images"
    images.mkdir()
    (images / "a.png").write_bytes(b"")
    figures = measure(images, tmp_path / "meta.csv", tmp_path / "out", False, None)
    assert figures == {**CHILD_FIGURES, "images": 4, "cups": 3, "errors": 1}


def test_the_table_gives_rates_per_second_and_the_bound_with_free_cores(tmp_path, monkeypatch):
    """10 images in 4 s of wall time and 5 s of CPU time on 4 cores: 2.5 images/s, 0.5 CPU s
    an image, and 4 / 0.5 = 8 images/s with the cores to itself."""
    written = {}
    monkeypatch.setattr(sys, "argv", ["predict", "--images", "10"])
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    monkeypatch.setattr(bench_predict, "make_folder",
                        lambda root, *_: (root / "images", root / "meta.csv"))
    monkeypatch.setattr(bench_predict, "measure", lambda *_: {
        **CHILD_FIGURES, "images": 10, "cups": 12, "errors": 1})
    monkeypatch.setattr(bench_predict, "write_section",
                        lambda name, body: written.update({name: body}))
    bench_predict.main()
    header, first, *_ = table_cells(written["predict"], "runtime")
    assert dict(zip(header, first, strict=True)) == {
        "runtime": "torch", "speed preset": "default", "overlays": "off", "images": "10",
        "cups found": "12", "error rows": "1", "run (s)": "4", "images / s": "2.5",
        "CPU s / image": "0.5", "images / s if cores were free": "8",
        "peak memory (MB)": "900", "process start-up (s)": "3"}
