"""benchmarks/model.py's degraded exports (what each does to a DRR, its geometry and truth),
its misgiven geometries, and its robustness tables (degraded images, surgical hardware, the
geometry given wrong, small and large images)."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml
from markdown_tables import table_cells

from benchmarks import model as bench_model
from benchmarks.model import (
    DEGRADATIONS,
    HARDWARE,
    MISGIVEN,
    as_8_bit,
    blurrier,
    degraded_section,
    geometry_section,
    halved,
    hardware_section,
    jpeg_exported,
    large_section,
    misgiven,
    noisier,
    small_section,
)
from cupnet.ellipse import conic_to_params
from cupnet.geometry import Geometry, pose_to_radians, project_rim, rim_conic
from cupnet.model import CupNet
from data_synth import SynthConfig, synthesize


def _sample() -> dict:
    return synthesize(SynthConfig(image_size=(512, 512), p_anatomy=0.0), 4, 0)


def test_a_halved_export_keeps_its_rims_where_the_halved_geometry_projects_them():
    sample = _sample()
    half = halved(sample)
    assert half["image"].shape == (1, 256, 256)
    pose = pose_to_radians(sample["pose"].double())
    radius = sample["cup_diameter"].double() / 2
    t = torch.linspace(0, 2 * np.pi, 37, dtype=torch.float64)
    full_geometry, half_geometry = (Geometry.from_row(s["geometry"])
                                    for s in (sample, half))
    # A rim point's pixel in the halved image, from pixel centres at integers: the
    # projection under the halved geometry (spacing doubled, principal point moved).
    torch.testing.assert_close(project_rim(pose, radius, half_geometry, t),
                               (project_rim(pose, radius, full_geometry, t) + 0.5) / 2 - 0.5)
    # Its true ellipses: those of the rim's conic under that geometry.
    conic = torch.stack([rim_conic(pose[c:c + 1], radius[c], half_geometry)[0]
                         for c in range(len(pose))])
    truth = conic_to_params(conic)
    valid = sample["cup_valid"].bool()
    torch.testing.assert_close(half["ellipse"][valid, :4].double(), truth[valid, :4],
                               atol=1e-3, rtol=0)
    # Area averaging: the halved image's mean is the 8-bit image's.
    assert abs(float(half["image"].mean()) - as_8_bit(sample).mean() / 255) < 1 / 255


def test_jpeg_loses_more_the_lower_its_quality_and_keeps_the_image_in_place():
    sample = _sample()
    exact = as_8_bit(sample).astype(np.float64) / 255
    errors = [np.abs(jpeg_exported(sample, quality)["image"][0].numpy() - exact).mean()
              for quality in (95, 75, 50)]
    assert 0 < errors[0] < errors[1] < errors[2] < 0.02
    assert jpeg_exported(sample, 50)["geometry"] is sample["geometry"]


def test_added_noise_has_the_asked_deviation_and_each_rng_draws_it_again():
    sample = _sample()
    first = noisier(sample, 0.03, np.random.default_rng(5))["image"][0].numpy()
    again = noisier(sample, 0.03, np.random.default_rng(5))["image"][0].numpy()
    np.testing.assert_array_equal(first, again)
    exact = sample["image"][0].numpy()
    unclipped = (exact > 0.15) & (exact < 0.85)
    # The 8-bit rounding adds 1 / (255 sqrt 12) in quadrature.
    assert abs((first - exact)[unclipped].std() - np.hypot(0.03, 1 / 255 / 12**0.5)) < 0.002


def test_added_blur_keeps_the_mean_and_smooths_the_detail():
    sample = _sample()
    exact, blurred = as_8_bit(sample) / 255, blurrier(sample, 2.0)["image"][0].numpy()
    assert abs(blurred.mean() - exact.mean()) < 1 / 255
    detail = [np.abs(np.diff(image, axis=1)).mean() for image in (exact, blurred)]
    assert detail[1] < 0.8 * detail[0]


def test_every_degradation_gives_an_image_detect_takes():
    sample = _sample()
    for label, degrade in DEGRADATIONS.items():
        image = degrade(sample, np.random.default_rng(0))["image"]
        assert image.dtype == torch.float32 and image.ndim == 3, label
        assert float(image.min()) >= 0 and float(image.max()) <= 1, label


def test_a_misgiven_geometry_changes_what_it_names_and_nothing_else():
    sample = _sample()
    sdd, spacing, *_ = sample["geometry"].tolist()
    given = misgiven(sample, sdd=1.1, spacing=0.8, centred=True, diameter_mm=2.0)
    # A 512 px image's centre, pixel centres at integers.
    assert given["geometry"].tolist() == pytest.approx([1.1 * sdd, 0.8 * spacing, 255.5, 255.5])
    torch.testing.assert_close(given["cup_diameter"], sample["cup_diameter"] + 2.0)
    for key in ("image", "pose", "ellipse", "cup_valid"):
        assert given[key] is sample[key], key
    # The truth's own geometry and sizes stay as drawn (the principal point off the centre).
    assert sample["geometry"].tolist()[:2] == [sdd, spacing]
    assert sample["geometry"].tolist()[2:] != [255.5, 255.5]
    torch.testing.assert_close(misgiven(sample)["geometry"], sample["geometry"])
    # As --assume-defaults fills them (README): SDD 1,040 mm, 300 mm over the image's width,
    # a 52 mm cup; the principal point, unknown, at the centre.
    assumed = misgiven(sample, assumed=True)
    assert assumed["geometry"].tolist() == pytest.approx([1040.0, 300.0 / 512, 255.5, 255.5])
    assert assumed["cup_diameter"].tolist() == [52.0] * len(sample["cup_diameter"])


# Stub scores (the same for every row) and the cells they must give, column by column.
STUB_SCORES = {"mae_theta": 1.5, "mae_phi": 2.5, "mae_k": 3.5, "mae_l": 4.5, "mae_h": 5.5,
               "detected": 0.75, "cups": 8, "false_positives": 3, "false_positives_flagged": 2,
               "median_theta": 0.25, "median_phi": 0.5, "gross": 4, "gross_flagged": 1}
STUB_CELLS = {"settings": "onnx", "MAE theta": "1.5", "MAE phi": "2.5", "MAE k": "3.5",
              "MAE l": "4.5", "MAE h": "5.5", "detected": "75.0 % of 8",
              "false positives": "3 (2 flagged)", "median theta": "0.25",
              "median phi": "0.50", "gross (flagged)": "4 (1)"}
STUB_MODEL = SimpleNamespace(config=SimpleNamespace(enlarge_below=384, enlarge_to=512))


def _robustness_args() -> argparse.Namespace:
    return argparse.Namespace(eval_config="configs/synth_eval.yaml", seed=0, degraded_images=6,
                              hardware_images=4, sizes=[512], runtimes=["onnx"],
                              seed_presets=[])


def test_each_degraded_row_puts_its_figures_under_their_headers(monkeypatch):
    """Each figure read back by its column's name, so that no two columns can trade places
    unseen."""
    monkeypatch.setattr(bench_model, "samples", lambda *_: [])
    monkeypatch.setattr(bench_model, "accuracy", lambda *_: STUB_SCORES)
    text = degraded_section({"onnx": STUB_MODEL}, _robustness_args())
    header, *rows = table_cells(text, "images")
    assert [row[0] for row in rows] == list(DEGRADATIONS)
    for row in rows:
        assert dict(zip(header[1:], row[1:], strict=True)) == STUB_CELLS, row[0]


def test_each_hardware_row_scores_the_same_scenes_with_its_hardware(monkeypatch):
    """Every row draws the same seed's scenes from the eval config with its hardware's
    fields set (the scenes stay the same, tests/test_synth_dataset.py), and puts its
    figures under their headers."""
    drawn = []
    monkeypatch.setattr(bench_model, "samples",
                        lambda config, *rest: drawn.append((config, *rest)) or [])
    monkeypatch.setattr(bench_model, "accuracy", lambda *_: STUB_SCORES)
    args = _robustness_args()
    header, *rows = table_cells(hardware_section({"onnx": STUB_MODEL}, args), "images")
    assert [row[0] for row in rows] == list(HARDWARE)
    for row in rows:
        assert dict(zip(header[1:], row[1:], strict=True)) == STUB_CELLS, row[0]
    eval_fields = yaml.safe_load(Path(args.eval_config).read_text())
    assert [config for config, *_ in drawn] == [{**eval_fields, **fields}
                                                 for fields in HARDWARE.values()]
    assert [rest for _, *rest in drawn] == [[51, 4, [512]]] * len(HARDWARE)


def test_each_geometry_row_gives_the_same_images_its_misgiven_geometry(monkeypatch):
    """Every row scores the one draw of images, each told the geometry its entry of
    :data:`MISGIVEN` gives, and puts its figures under their headers."""
    sample = _sample()
    told = []
    monkeypatch.setattr(bench_model, "samples", lambda *_: [sample])
    monkeypatch.setattr(bench_model, "accuracy", lambda _, images: told.append(
        (images[0]["image"], images[0]["geometry"], images[0]["cup_diameter"])) or STUB_SCORES)
    args = argparse.Namespace(eval_config="configs/synth_eval.yaml", seed=0, geometry_images=1,
                              sizes=[512], runtimes=["onnx"], seed_presets=[])
    header, *rows = table_cells(geometry_section({"onnx": STUB_MODEL}, args), "images")
    assert [row[0] for row in rows] == list(MISGIVEN)
    for row in rows:
        assert dict(zip(header[1:], row[1:], strict=True)) == STUB_CELLS, row[0]
    assert all(image is sample["image"] for image, _, _ in told)
    for (_, geometry, diameter), given in zip(told, MISGIVEN.values(), strict=True):
        expected = misgiven(sample, **given)
        torch.testing.assert_close(geometry, expected["geometry"])
        torch.testing.assert_close(diameter, expected["cup_diameter"])


def test_each_size_is_scored_as_the_model_resizes_it_and_as_given(monkeypatch):
    """A side the model resizes (under ``enlarge_below``, over ``reduce_above``) gets a row
    as it resizes it and a row with the setting off, as ``cupnet predict``'s flag at 0
    sets it; any other side one row; the setting is the model's again after."""
    config = SimpleNamespace(enlarge_below=496, enlarge_to=512, reduce_above=1024,
                             reduce_to=1024)
    stub = SimpleNamespace(config=config)
    stub.resize_factor = lambda height, width: CupNet.resize_factor(stub, height, width)
    settings = []
    monkeypatch.setattr(bench_model, "samples", lambda *_: [])
    monkeypatch.setattr(bench_model, "accuracy", lambda *_: settings.append(
        (config.enlarge_below, config.reduce_above)) or STUB_SCORES)
    args = argparse.Namespace(eval_config="configs/synth_eval.yaml", seed=0, runtimes=["onnx"],
                              small=[256, 384, 512], small_images=3, large=[2048, 1536, 1024],
                              large_images=2)
    cells = {"MAE theta": "1.5", "detected": "75.0 % of 8", "median phi": "0.50",
             "gross failures": "4"}
    for section, sizes, ways, tried in (
            (small_section, ["256", "256", "384", "384", "512"],
             ["enlarged", "as given (`--enlarge-below 0`)"] * 2 + ["as given"],
             [(496, 1024), (0, 1024)] * 2 + [(496, 1024)]),
            (large_section, ["2048", "2048", "1536", "1536", "1024"],
             ["reduced", "as given (`--reduce-above 0`)"] * 2 + ["as given"],
             [(496, 1024), (496, None)] * 2 + [(496, 1024)])):
        settings.clear()
        header, *rows = table_cells(section(stub, args), "side (px)")
        assert [row[0] for row in rows] == sizes and [row[2] for row in rows] == ways
        for row in rows:
            assert {key: value for key, value in zip(header, row, strict=True)
                    if key in cells} == cells
        assert settings == tried
        assert (config.enlarge_below, config.reduce_above) == (496, 1024)
