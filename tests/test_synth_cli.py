"""cupnet synth: images, meta.csv and truth.csv on disk, DICOM tags, errors."""

from __future__ import annotations

import csv

import cv2
import numpy as np
import pytest
import torch

from cupnet.cli import main
from data_synth import SynthConfig, synthesize
from data_synth.cli import META_COLUMNS, TRUTH_COLUMNS, rims_overhanging

POSE_COLUMNS = ["theta_deg", "phi_deg", "k_mm", "l_mm", "h_mm"]
ELLIPSE_COLUMNS = ["ellipse_cx_px", "ellipse_cy_px", "ellipse_a_px", "ellipse_b_px",
                   "ellipse_angle_deg"]


def read_csv(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def test_png_output_matches_synthesize(tmp_path):
    out = tmp_path / "synth"
    assert main(["synth", "--n", "3", "--out", str(out), "--size", "64", "48",
                 "--seed", "4"]) == 0
    meta, truth = read_csv(out / "meta.csv"), read_csv(out / "truth.csv")
    assert list(meta[0]) == META_COLUMNS and [r["image"] for r in meta] == [
        f"synth_{i:06d}.png" for i in range(3)]
    if truth:
        assert list(truth[0]) == TRUTH_COLUMNS
    config = SynthConfig(image_size=(64, 48))
    rows = 0
    for i, row in enumerate(meta):
        sample = synthesize(config, 4, i)
        pixels = cv2.imread(str(out / "images" / row["image"]), cv2.IMREAD_UNCHANGED)
        assert pixels.dtype == np.uint16 and pixels.shape == (48, 64)
        np.testing.assert_array_equal(pixels, np.round(sample["image"][0].numpy() * 65535))
        geometry = [float(row[k]) for k in ("sdd_mm", "pixel_spacing_mm", "principal_u_px",
                                            "principal_v_px")]
        np.testing.assert_allclose(geometry, sample["geometry"].numpy(), atol=1e-5)
        cups = [r for r in truth if r["image"] == row["image"]]
        assert len(cups) == int(sample["cup_valid"].sum())
        for cup in cups:
            # Every column, by name: the pose's five, the ellipse's five (a cx / cy swap
            # had passed), the diameter.
            j = int(cup["cup"])
            for columns, truth_values in ((POSE_COLUMNS, sample["pose"][j]),
                                          (ELLIPSE_COLUMNS, sample["ellipse"][j]),
                                          (["cup_diameter_mm"], sample["cup_diameter"][j:j + 1])):
                np.testing.assert_allclose([float(cup[k]) for k in columns],
                                           truth_values.numpy(), atol=1e-5, err_msg=str(columns))
        rows += len(cups)
    assert rows == len(truth) and rows > 0


def test_dicom_output_carries_the_geometry(tmp_path):
    import pydicom

    out = tmp_path / "dcm"
    assert main(["synth", "--n", "1", "--out", str(out), "--size", "40", "32",
                 "--format", "dcm"]) == 0
    meta = read_csv(out / "meta.csv")[0]
    ds = pydicom.dcmread(out / "images" / meta["image"])
    assert ds.Rows == 32 and ds.Columns == 40 and ds.pixel_array.dtype == np.uint16
    assert float(ds.DistanceSourceToDetector) == pytest.approx(float(meta["sdd_mm"]), abs=1e-3)
    assert [float(v) for v in ds.ImagerPixelSpacing] == pytest.approx(
        [float(meta["pixel_spacing_mm"])] * 2, abs=1e-5)
    # A seed gives the same files again, UIDs included (they had been random); another
    # seed other UIDs.
    again, other = tmp_path / "again", tmp_path / "other"
    for folder, seed in ((again, "0"), (other, "1")):
        assert main(["synth", "--n", "1", "--out", str(folder), "--size", "40", "32",
                     "--format", "dcm", "--seed", seed]) == 0
    name = meta["image"]
    assert (again / "images" / name).read_bytes() == (out / "images" / name).read_bytes()
    assert pydicom.dcmread(other / "images" / name).SOPInstanceUID != ds.SOPInstanceUID


def test_refuses_to_overwrite_and_names_bad_config_keys(tmp_path, capsys):
    out = tmp_path / "synth"
    assert main(["synth", "--n", "1", "--out", str(out), "--size", "32", "32"]) == 0
    assert main(["synth", "--n", "1", "--out", str(out), "--size", "32", "32"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["synth", "--n", "1", "--out", str(out), "--size", "32", "32",
                 "--overwrite"]) == 0
    config = tmp_path / "bad.yaml"
    config.write_text("p_bilateral: 2.0\n")
    assert main(["synth", "--n", "1", "--out", str(tmp_path / "x"), "--config",
                 str(config)]) == 2
    assert "p_bilateral" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    assert main(["synth", "--n", "1", "--out", str(tmp_path / "afile")]) == 2
    assert "is a file; give a folder" in capsys.readouterr().err


def test_a_bad_config_or_anatomy_is_named_before_any_output_is_made(tmp_path, capsys):
    """A config that is no YAML, a folder given as the config, an anatomy bank without maps
    and an output under a file had each ended in a traceback; the bank's, mid-run, had left
    empty outputs behind that made the corrected rerun ask for --overwrite."""
    def synth(out: str, *extra: str) -> int:
        return main(["synth", "--n", "1", "--out", str(tmp_path / out), "--size", "32", "32",
                     *extra])

    (tmp_path / "broken.yaml").write_text("image_size: [512, 512\n")
    assert synth("a", "--config", str(tmp_path / "broken.yaml")) == 2
    assert "broken.yaml is no YAML file" in capsys.readouterr().err
    assert synth("a", "--config", str(tmp_path)) == 2
    assert "Is a directory" in capsys.readouterr().err
    np.savez(tmp_path / "nomaps.npz", x=np.zeros(3))
    (tmp_path / "nomaps.yaml").write_text(f"anatomy_bank: {tmp_path / 'nomaps.npz'}\n"
                                          "p_anatomy: 1.0\n")
    assert synth("b", "--config", str(tmp_path / "nomaps.yaml")) == 2
    assert "nomaps.npz cannot be used: anatomy bank" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()
    assert synth("b") == 0  # the rerun, its config mended
    (tmp_path / "afile").write_text("")
    assert synth("afile/sub") == 2
    assert "cannot make" in capsys.readouterr().err


def test_cups_the_field_cannot_hold_are_counted(tmp_path, capsys):
    """A field too narrow for the cups (64 px at 0.3 mm: 19 mm) keeps each cup centred, its
    rim past the image: the run says how many, where it had said nothing; a wide field has
    none to count."""
    narrow = tmp_path / "narrow.yaml"
    narrow.write_text("pixel_spacing_mm: [0.3, 0.3]\np_no_cup: 0.0\np_bilateral: 0.0\n")
    assert main(["synth", "--n", "2", "--out", str(tmp_path / "a"), "--size", "64", "64",
                 "--config", str(narrow)]) == 0
    assert "warning: 2 of 2 cups reach past the image's edge" in capsys.readouterr().err
    assert main(["synth", "--n", "2", "--out", str(tmp_path / "b"), "--size", "64", "64"]) == 0
    assert "reach past" not in capsys.readouterr().err


def rim_sample(width: int, height: int, rims: list[tuple[float, float]]) -> dict:
    """A synthesize-like sample of a ``width x height`` image whose cups each have one rim
    point where ``rims`` says and the others at the image's centre, all valid."""
    rim = torch.zeros(len(rims), 64, 2, dtype=torch.float64)
    rim[..., 0], rim[..., 1] = (width - 1) / 2, (height - 1) / 2
    rim[:, 0] = torch.tensor(rims, dtype=torch.float64)
    return {"image": torch.zeros(1, height, width), "rim": rim,
            "cup_valid": torch.ones(len(rims), dtype=torch.bool)}


@pytest.mark.parametrize(
    ("size", "rims", "expected"),
    [
        # Wide image: below its last row but left of its last column is past the edge.
        ((80, 40), [(40.0, 45.0), (40.0, 39.0)], [True, False]),
        ((80, 40), [(79.5, 20.0), (79.0, 0.0)], [True, False]),
        # Tall image: right of its last column but above its last row is past the edge.
        ((40, 80), [(45.0, 40.0), (39.0, 79.0)], [True, False]),
        ((40, 80), [(20.0, 79.5), (-0.5, 40.0)], [True, True]),
    ],
)
def test_overhang_is_judged_against_each_of_the_images_sides(size, rims, expected):
    """A rim point is past the edge when u leaves [0, W - 1] or v leaves [0, H - 1]:
    on a non-square image, v checked against the width had missed (or made up) overhangs."""
    assert rims_overhanging(rim_sample(*size, rims)).tolist() == expected
