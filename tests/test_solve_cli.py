"""`cupnet solve` on both landmark formats, geometry precedence, bad rows, no overwrite."""

from __future__ import annotations

import csv
import math
import random
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from cup_cases import rim_landmarks

from cupnet.cli import main
from cupnet.geometry import Geometry, pose_to_radians
from cupnet.io.landmarks import read_landmarks
from cupnet.io.meta import ImageTable, read_meta, row_for_image
from cupnet.io.results import MURRAY_COLUMNS, SD_COLUMNS
from cupnet.pose import cramer_rao_bound

TRUTH = torch.tensor([[30.0, 20.0, 10.0, -20.0, 300.0], [15.0, -40.0, -50.0, 30.0, 200.0]],
                     dtype=torch.float64)


def write_long(path: Path, geometry: Geometry, extra: str = "") -> None:
    points = rim_landmarks(TRUTH, geometry, n=40)
    lines = ["image,u,v"] + [f"{name},{u},{v}" for name, pts in zip(("a.png", "b.png"), points,
                                                                     strict=True)
                             for u, v in pts.tolist()]
    path.write_text("\n".join(lines) + "\n" + extra)


def write_paper(path: Path) -> None:
    points = rim_landmarks(TRUTH, Geometry(1040.0, 1.0, 255.5, 255.5), n=30)
    header = ("image_name,image_width,image_height,source_to_detection_distance,radius,"
              "n_landmarks," + ",".join(f"landmark_{i}_x,landmark_{i}_y" for i in range(1, 31)))
    rows = [f"{name},512,512,1040,25,30," + ",".join(f"{u},{v}" for u, v in pts.tolist())
            for name, pts in zip(("p1.png", "p2.png"), points, strict=True)]
    path.write_text("\n".join([header, *rows]) + "\n")


def results(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def murray(theta: float, phi: float) -> list[float]:
    """Murray's conversion formulas: operative then anatomic anteversion and inclination (deg),
    the inclinations with the side's sign."""
    ra, ri = math.radians(theta), math.radians(abs(phi))
    side = math.copysign(1.0, phi)
    return [math.degrees(v) for v in (math.atan(math.tan(ra) / math.cos(ri)),
                                      side * math.asin(math.sin(ri) * math.cos(ra)),
                                      math.atan(math.tan(ra) / math.sin(ri)),
                                      side * math.acos(math.cos(ri) * math.cos(ra)))]


def assert_poses(rows: list[dict[str, str]]) -> None:
    for row, truth in zip(rows, TRUTH[:len(rows)].tolist(), strict=True):
        got = [float(row[c]) for c in ("anteversion_deg", "inclination_deg", "k_mm", "l_mm",
                                       "h_mm")]
        assert got == pytest.approx(truth, abs=1e-3)
        assert row["status"] == "ok" and float(row["residual_px"]) < 1e-6
        assert row["doubt"] == "" and row["check"] == "0"
        assert [float(row[c]) for c in MURRAY_COLUMNS] == pytest.approx(murray(*truth[:2]),
                                                                        abs=1e-3)


def test_paper_format_is_detected_and_solved_in_its_pixel_equals_mm_units(tmp_path):
    write_paper(tmp_path / "label.csv")
    assert main(["solve", str(tmp_path / "label.csv"), "--out", str(tmp_path / "r.csv")]) == 0
    assert_poses(results(tmp_path / "r.csv"))


def test_long_format_with_flags_and_bad_rows(tmp_path):
    geometry = Geometry(1000.0, 0.4, 300.0, 250.0)
    write_long(tmp_path / "lm.csv", geometry, extra="c.png,1,2\nc.png,3,4\nd.png,abc,3\n")
    out = tmp_path / "r.csv"
    code = main(["solve", str(tmp_path / "lm.csv"), "--sdd", "1000", "--pixel-spacing", "0.4",
                 "--cup-diameter", "50", "--principal-point", "300", "250", "--out", str(out)])
    assert code == 0
    rows = results(out)
    assert_poses(rows[:2])
    assert rows[2]["image"] == "c.png" and "too few points" in rows[2]["status"]
    assert rows[3]["image"] == "d.png" and "line" in rows[3]["status"]


def test_meta_wins_over_flags_and_missing_values_are_named(tmp_path):
    geometry = Geometry(1040.0, 0.5, 255.5, 255.5)
    write_long(tmp_path / "lm.csv", geometry)
    (tmp_path / "meta.csv").write_text(
        "image,sdd_mm,pixel_spacing_mm,cup_diameter_mm,principal_u_px,principal_v_px\n"
        "a.png,1040,0.5,50,255.5,255.5\n")
    out = tmp_path / "r.csv"
    # Wrong flags for a.png are overridden by meta.csv; b.png has no principal point.
    assert main(["solve", str(tmp_path / "lm.csv"), "--meta", str(tmp_path / "meta.csv"),
                 "--sdd", "900", "--pixel-spacing", "0.5", "--cup-diameter", "50",
                 "--out", str(out)]) == 0  # a cup solved: not the exit of a run with none
    rows = results(out)
    assert_poses(rows[:1])
    assert rows[1]["status"].startswith("error: missing principal point")
    assert rows[1]["cup"] == "0"  # the file's cup, as a solved row gives it


def test_a_bilateral_images_error_rows_keep_their_cups_and_evaluate_takes_them(tmp_path,
                                                                               capsys):
    """Two cups of an image without geometry: two error rows, cups 0 and 1 (they had both
    been blank, and cupnet evaluate refused the file as two appended ones), counted as two
    errors in the summary, as its rows are."""
    rows = ["image,cup,u,v"]
    for cup, (cx, cy) in enumerate(((100.0, 120.0), (300.0, 140.0))):
        rows += [f"x.png,{cup},{cx + 40 * np.cos(t):.4f},{cy + 25 * np.sin(t):.4f}"
                 for t in np.linspace(0, 2 * np.pi, 24, endpoint=False)]
    (tmp_path / "lm.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "r.csv"
    assert main(["solve", str(tmp_path / "lm.csv"), "--out", str(out)]) == 1
    assert [(r["cup"], r["status"][:6]) for r in results(out)] == [("0", "error:"),
                                                                   ("1", "error:")]
    assert f"1 images, 0 cups solved, 2 errors -> {out}" in capsys.readouterr().out
    (tmp_path / "truth.csv").write_text(
        "image,cup,theta_deg,phi_deg,k_mm,l_mm,h_mm,ellipse_cx_px,ellipse_cy_px,ellipse_a_px,"
        "ellipse_b_px,ellipse_angle_deg\n"
        "x.png,0,20,30,0,0,300,100,120,40,25,0\nx.png,1,20,-30,0,0,300,300,140,40,25,0\n")
    assert main(["evaluate", "--pred", str(out), "--truth", str(tmp_path / "truth.csv"),
                 "--out", str(tmp_path / "ev")]) == 0


def test_an_out_that_is_a_folder_is_named(tmp_path, capsys):
    write_paper(tmp_path / "label.csv")
    assert main(["solve", str(tmp_path / "label.csv"), "--out", str(tmp_path),
                 "--overwrite"]) == 2  # it had failed with a bare IsADirectoryError
    assert "is a folder; give the results file" in capsys.readouterr().err
    # A folder not yet made, named with its trailing slash: argparse's Path had dropped the
    # slash, and the results went to a file of the folder's name.
    with pytest.raises(SystemExit) as stop:
        main(["solve", str(tmp_path / "label.csv"), "--out", f"{tmp_path / 'new'}/"])
    assert stop.value.code == 2
    assert "new/ names a folder; give the results file" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_existing_output_is_not_overwritten(tmp_path, capsys):
    write_paper(tmp_path / "label.csv")
    out = tmp_path / "r.csv"
    out.write_text("keep me")
    assert main(["solve", str(tmp_path / "label.csv"), "--out", str(out)]) == 2
    assert out.read_text() == "keep me" and "--overwrite" in capsys.readouterr().err
    assert main(["solve", str(tmp_path / "label.csv"), "--out", str(out), "--overwrite"]) == 0
    assert_poses(results(out))


@pytest.mark.parametrize(("flag", "value"), [("--sdd", "-1040"), ("--pixel-spacing", "0"),
                                             ("--cup-diameter", "nan")])
def test_a_flag_that_is_no_positive_size_stops_the_command(tmp_path, capsys, flag, value):
    """A geometry flag holds for every image: a bad one is named once, before any row, and
    nothing is written (as `cupnet predict` does)."""
    write_long(tmp_path / "lm.csv", Geometry(1000.0, 0.4, 300.0, 250.0))
    out = tmp_path / "r.csv"
    given = {"--sdd": "1000", "--pixel-spacing": "0.4", "--cup-diameter": "50", flag: value}
    args = [item for pair in given.items() for item in pair]
    assert main(["solve", str(tmp_path / "lm.csv"), *args, "--out", str(out)]) == 2
    assert f"{flag} must be a positive number of mm, got {float(value)}" in \
        capsys.readouterr().err
    assert not out.exists()
    # A principal point that is not finite likewise (it had given every row an error).
    assert main(["solve", str(tmp_path / "lm.csv"), "--sdd", "1000", "--principal-point", "nan",
                 "300", "--out", str(out)]) == 2
    assert "--principal-point must be two finite pixel positions, got nan 300.0" in \
        capsys.readouterr().err


def test_unknown_format_and_empty_file_are_clear_errors(tmp_path):
    (tmp_path / "x.csv").write_text("a,b,c\n1,2,3\n")
    with pytest.raises(ValueError, match="unknown landmark format"):
        read_landmarks(tmp_path / "x.csv")
    (tmp_path / "e.csv").write_text("")
    with pytest.raises(ValueError, match="empty"):
        read_landmarks(tmp_path / "e.csv")


def test_implausible_geometry_is_warned_of_once_and_still_solved(tmp_path, capsys):
    geometry = Geometry(1000.0, 0.4, 300.0, 250.0)
    write_long(tmp_path / "lm.csv", geometry)
    out = tmp_path / "r.csv"
    # The radius given for the diameter: h comes out twice too near the source, not refused.
    assert main(["solve", str(tmp_path / "lm.csv"), "--sdd", "1000", "--pixel-spacing", "0.4",
                 "--cup-diameter", "25", "--principal-point", "300", "250",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert err.count("warning: cup diameter 25 mm (its radius?) lies outside 36-80 mm: "
                     "first in a.png") == 1
    assert "pixel spacing" not in err and "source-to-detector" not in err
    assert all(row["status"] in ("ok", "ambiguous") for row in results(out))


def test_assume_defaults_fill_what_the_file_lacks_as_predict_does(tmp_path, capsys):
    # The rims were drawn with the assumed SDD; the cup is 50 mm, given on the command line.
    geometry = Geometry(1040.0, 0.5, 255.5, 255.5)
    write_long(tmp_path / "lm.csv", geometry)
    out = tmp_path / "r.csv"
    flags = ["--pixel-spacing", "0.5", "--cup-diameter", "50"]
    # Every row an error: exit 1, as cupnet predict (the rows still written, saying why).
    assert main(["solve", str(tmp_path / "lm.csv"), *flags, "--principal-point", "255.5",
                 "255.5", "--out", str(out)]) == 1
    assert all(row["status"] == "error: missing source-to-detector distance (--sdd or meta.csv "
               "sdd_mm); or use --assume-defaults" for row in results(out))
    capsys.readouterr()
    assert main(["solve", str(tmp_path / "lm.csv"), *flags, "--principal-point", "255.5",
                 "255.5", "--assume-defaults", "--out", str(out), "--overwrite"]) == 0
    assert_poses(results(out))
    # What it assumed is said once, as predict says it (solve had said nothing).
    err = capsys.readouterr().err
    assert err.count("assuming source-to-detector distance = 1040 mm where not given "
                     "(--assume-defaults)") == 1
    assert "assuming" not in err.replace("assuming source-to-detector", "")
    # The long format gives no image size: the principal point is still the user's to give.
    assert main(["solve", str(tmp_path / "lm.csv"), *flags, "--assume-defaults",
                 "--out", str(out), "--overwrite"]) == 1
    assert all(row["status"].startswith("error: missing principal point")
               and "--assume-defaults" not in row["status"] for row in results(out))


def solved_sets(tmp_path: Path, sets: dict[str, torch.Tensor]) -> dict[str, dict[str, str]]:
    """``cupnet solve`` of landmark sets ``{image: (N, 2) px}`` (or ``(C, N, 2)``: the
    image's cups 0 to C - 1) and a two-point set ``few.png``, in the geometry of
    :func:`rim_landmarks`'s cups below (SDD 1,000 mm, 0.4 mm a pixel, a 50 mm cup); the
    rows by image, an image's cups past its first by ``image:cup``."""
    lines = ["image,cup,u,v"]
    for name, points in sets.items():
        for cup, cup_points in enumerate(points.reshape(-1, points.shape[-2], 2)):
            lines += [f"{name},{cup},{u},{v}" for u, v in cup_points.tolist()]
    lines += ["few.png,0,1,2", "few.png,0,3,4"]
    (tmp_path / "lm.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "r.csv"
    assert main(["solve", str(tmp_path / "lm.csv"), "--sdd", "1000", "--pixel-spacing", "0.4",
                 "--cup-diameter", "50", "--principal-point", "300", "250", "--out",
                 str(out)]) == 0
    return {row["image"] if row["cup"] == "0" else f"{row['image']}:{row['cup']}": row
            for row in results(out)}


def test_landmarks_that_are_no_rim_are_flagged_check(tmp_path, capsys):
    """A noisy clicked rim passes; random points and two cups' rims in one set still give an
    ``ok`` pose, and are flagged ``check`` (RMS distance to the rim over a tenth of its
    semi-major axis); a set too small to solve has no flag at all."""
    geometry = Geometry(1000.0, 0.4, 300.0, 250.0)
    rims = rim_landmarks(TRUTH, geometry, n=40)
    generator = torch.Generator().manual_seed(0)
    sets = {"clicked.png": rims[0] + 1.5 * torch.randn(40, 2, generator=generator,
                                                        dtype=torch.float64),
            "random.png": 100 + 400 * torch.rand(40, 2, generator=generator,
                                                 dtype=torch.float64),
            "two_rims.png": torch.cat([rims[0][::2], rims[1][::2]])}
    rows = solved_sets(tmp_path, sets)
    clicked = rows["clicked.png"]
    assert clicked["check"] == "0" and 1.0 < float(clicked["residual_px"]) < 2.0
    for name in ("random.png", "two_rims.png"):
        row = rows[name]
        assert row["status"] in ("ok", "ambiguous") and row["check"] == "1", row
        # off the rim by over a tenth of the points' extent, their own ellipse's semi-major
        # axis (OpenCV's fit); the row's ellipse is the pose's rim, here far larger
        axes = cv2.fitEllipse(sets[name].numpy().astype(np.float32))[1]
        assert float(row["residual_px"]) > 0.1 * max(axes) / 2
    assert rows["few.png"]["status"].startswith("error") and rows["few.png"]["check"] == ""
    assert "2 cup(s) flagged check=1: their landmarks lie off the solved rim" in \
        capsys.readouterr().out


def off_rim(points: torch.Tensor, fraction: float) -> torch.Tensor:
    """Landmarks ``(N, 2)`` on a rim (``N`` even) moved out and in by turns along its normal
    by ``fraction`` of its semi-major axis: no ellipse passes nearer them than the rim, so
    their RMS distance to the solved rim is about that fraction of its axis."""
    tangent = points.roll(-1, 0) - points.roll(1, 0)
    normal = torch.stack([tangent[:, 1], -tangent[:, 0]], 1)
    normal = normal / normal.norm(dim=1, keepdim=True)
    semi_major = (points - points.mean(0)).norm(dim=1).max()
    sign = torch.tensor([1.0, -1.0], dtype=torch.float64).repeat(len(points) // 2)
    return points + (fraction * semi_major * sign)[:, None] * normal


def test_the_off_rim_limit_is_a_tenth_of_the_semi_major_axis(tmp_path, capsys):
    """Landmarks about 0.05 of the axis off their rim pass; about 0.15 off (between the
    limit and twice it), both cups of a bilateral image are flagged, and counted both."""
    geometry = Geometry(1000.0, 0.4, 300.0, 250.0)
    rims = rim_landmarks(TRUTH, geometry, n=40)
    rows = solved_sets(tmp_path, {"near.png": off_rim(rims[0], 0.05),
                                  "off.png": torch.stack([off_rim(rim, 0.15) for rim in rims])})
    near = rows["near.png"]
    assert 0.03 < float(near["residual_px"]) / float(near["ellipse_a_px"]) < 0.07
    assert near["status"] == "ok" and near["check"] == "0"
    for row in (rows["off.png"], rows["off.png:1"]):
        assert 0.1 < float(row["residual_px"]) / float(row["ellipse_a_px"]) < 0.2, row
        assert row["status"] == "ok" and row["check"] == "1"
        assert 25.0 < float(row["h_mm"]) < 750.0  # flagged off the rim, not by the pose
    # Each of the image's rows carries the image's time (cupnet evaluate reads the first).
    assert rows["off.png"]["seconds"] == rows["off.png:1"]["seconds"]
    assert float(rows["off.png"]["seconds"]) > 0
    assert "2 cup(s) flagged check=1" in capsys.readouterr().out


def test_two_whole_rims_in_one_set_are_flagged_by_their_cup_near_the_source(tmp_path):
    """A bilateral pair's whole rims in one set fit a wide ellipse between them, within a
    tenth of its axis, whose pose lies near the source: flagged by the pose."""
    geometry = Geometry(1000.0, 0.4, 300.0, 250.0)
    pair = torch.tensor([[40.0, 35.0, -100.0, 10.0, 300.0], [40.0, -35.0, 100.0, 10.0, 300.0]],
                        dtype=torch.float64)
    row = solved_sets(tmp_path, {"pair.png": rim_landmarks(pair, geometry, n=40).reshape(-1, 2)}
                      )["pair.png"]
    assert float(row["residual_px"]) < 0.1 * float(row["ellipse_a_px"])  # the rim test passes
    assert float(row["h_mm"]) > 0.75 * 1000.0 and row["check"] == "1"
    # A rim too small for the cup's diameter (a 35.8 mm cup's, solved as 50 mm): the cup comes
    # out within its radius of the detector, its dome through it. Flagged too.
    small = rim_landmarks(torch.tensor([[30.0, 20.0, 10.0, -20.0, 300.0]], dtype=torch.float64),
                          geometry, diameter=35.8, n=40)[0]
    (tmp_path / "small").mkdir()
    row = solved_sets(tmp_path / "small", {"small.png": small})["small.png"]
    assert 0 < float(row["h_mm"]) < 25.0 and row["status"] == "ok" and row["check"] == "1"


def test_clicked_landmarks_give_the_poses_standard_errors(tmp_path):
    """Three clicked rims of the same cup, 1.5 px of noise each: each row's standard errors
    are the Cramer-Rao bound at that noise (measured from its own scatter, so within the
    spread of a noise level estimated from 40 landmarks), and the poses lie within 3 of
    them of the truth; a set too small to solve has none."""
    geometry = Geometry(1000.0, 0.4, 300.0, 250.0)
    generator = torch.Generator().manual_seed(1)
    clicks = rim_landmarks(TRUTH[:1], geometry, n=40)[0] + 1.5 * torch.randn(
        3, 40, 2, generator=generator, dtype=torch.float64)
    rows = solved_sets(tmp_path, {f"c{i}.png": points for i, points in enumerate(clicks)})
    t = torch.arange(40, dtype=torch.float64) * (2 * math.pi / 40)
    bound = cramer_rao_bound(pose_to_radians(TRUTH[:1]), 25.0, geometry, t, 1.5)[0].tolist()
    for i in range(3):
        row = rows[f"c{i}.png"]
        errors = [float(row[c]) for c in SD_COLUMNS]
        assert errors == pytest.approx(bound, rel=0.35)
        pose = [float(row[c]) for c in ("anteversion_deg", "inclination_deg", "k_mm", "l_mm",
                                        "h_mm")]
        assert all(abs(p - q) < 3 * e for p, q, e in zip(pose, TRUTH[0].tolist(), errors,
                                                         strict=True))
    assert all(rows["few.png"][c] == "" for c in SD_COLUMNS)


def test_csv_files_saved_by_excel_with_a_byte_order_mark_are_read(tmp_path):
    """Excel's "CSV UTF-8" starts with a byte-order mark, which had hidden the first
    column's name ("meta.csv needs an 'image' column", "unknown landmark format")."""
    (tmp_path / "lm.csv").write_text("image,u,v\na.png,1,2\n", encoding="utf-8-sig")
    assert list(read_landmarks(tmp_path / "lm.csv")) == ["a.png"]
    (tmp_path / "meta.csv").write_text("image,sdd_mm\na.png,1000\n", encoding="utf-8-sig")
    assert read_meta(tmp_path / "meta.csv") == {"a.png": {"sdd_mm": 1000.0}}


def test_csv_files_in_another_encoding_are_named_with_the_fix(tmp_path):
    """Excel's plain "CSV" writes the system's code page: the decoder's message had named
    neither the file nor what to do."""
    for name, text in (("meta.csv", "image,sdd_mm\nJosé.png,1000\n"),
                       ("lm.csv", "image,u,v\nJosé.png,1,2\n")):
        (tmp_path / name).write_text(text, encoding="latin-1")
    # The byte of the e acute: after the header and "Jos".
    for read, name, byte in ((read_meta, "meta.csv", 16), (read_landmarks, "lm.csv", 13)):
        with pytest.raises(ValueError, match=rf"{name}: not UTF-8 text \(byte {byte}: invalid "
                                             r"continuation byte\); save it as UTF-8"):
            read(tmp_path / name)


def test_a_trailing_comma_in_meta_csv_is_read_and_an_extra_value_refused(tmp_path):
    """A spreadsheet's trailing comma gives a row a cell past the header: it had stopped
    predict and solve with a TypeError."""
    (tmp_path / "comma.csv").write_text("image,sdd_mm\na.png,1000,\nb.png,990, \n")
    assert read_meta(tmp_path / "comma.csv") == {"a.png": {"sdd_mm": 1000.0},
                                                 "b.png": {"sdd_mm": 990.0}}
    (tmp_path / "extra.csv").write_text("image,sdd_mm\na.png,1000\nb.png,990,0.3\n")
    with pytest.raises(ValueError, match=r"extra.csv, line 3: 1 cell\(s\) more than the "
                                         r"header's columns \(image, sdd_mm\)"):
        read_meta(tmp_path / "extra.csv")


def test_a_paper_row_whose_image_size_is_no_count_is_its_images_error(tmp_path):
    """inf had stopped the run (OverflowError), 0 or a negative width given a principal
    point off the image and a pose without a word."""
    write_paper(tmp_path / "label.csv")
    lines = (tmp_path / "label.csv").read_text().splitlines()
    bad = [lines[2].replace("p2.png,512,", f"{name},{width},", 1)
           for name, width in (("inf.png", "inf"), ("zero.png", "0"), ("minus.png", "-512"),
                               ("half.png", "511.5"))]
    (tmp_path / "label.csv").write_text("\n".join([*lines, *bad]) + "\n")
    assert main(["solve", str(tmp_path / "label.csv"), "--out", str(tmp_path / "r.csv")]) == 0
    rows = {row["image"]: row for row in results(tmp_path / "r.csv")}
    assert_poses([rows["p1.png"], rows["p2.png"]])
    for name, width, line in (("inf.png", "inf", 4), ("zero.png", "0", 5),
                              ("minus.png", "-512", 6), ("half.png", "511.5", 7)):
        assert rows[name]["status"] == (f"error: landmark file line {line}: image_width must "
                                        f"be a whole number >= 1, got '{width}'")


def test_a_meta_row_given_twice_with_other_values_is_refused(tmp_path):
    """The later of two rows for one image had silently won; the same row twice is fine."""
    (tmp_path / "same.csv").write_text("image,sdd_mm\na.png,1000\na.png,1000.0\n")
    assert read_meta(tmp_path / "same.csv") == {"a.png": {"sdd_mm": 1000.0}}
    (tmp_path / "meta.csv").write_text("image,sdd_mm\na.png,1077\nb.png,990\na.png,1000\n")
    with pytest.raises(ValueError, match="line 4: a.png is given again, with other values"):
        read_meta(tmp_path / "meta.csv")


def test_an_images_row_is_found_by_its_name_its_files_or_a_keys_file_name():
    table = {"a.png": 1, "run/b.png": 2, "x/c.png": 3, "y/c.png": 4, "d.dcm": 5,
             "C:\\images\\e.png": 6}
    assert row_for_image(table, "a.png") == 1
    assert row_for_image(table, "sub/a.png") == 1   # the image in a subfolder of the run
    assert row_for_image(table, "b.png") == 2       # the key with a folder, alone of its name
    assert row_for_image(table, "c.png") is None    # two keys of that name: neither
    assert row_for_image(table, "d.dcm#2") == 5     # a frame: its file's row
    # A '#' of the file's own name is no frame's (the name had been cut at it).
    assert row_for_image({"hash2/hip#2.png": 7}, "hip#2.png") == 7
    assert row_for_image(table, "e.png") == 6       # a Windows path
    assert row_for_image(table, "f.png") is None
    assert row_for_image(table, "A.PNG") == 1       # another case, one key's alone
    assert row_for_image({"x.png": 1, "X.png": 2}, "x.PNG") is None  # two: neither
    # Two inputs of one name, named by their paths: rows given by folder find theirs, the
    # longest key ending the path first; a key "a.png" had been taken for every one.
    by_folder = {"d1/a.png": 1, "d2/a.png": 2, "a.png": 3, "D3/B.png": 4}
    assert row_for_image(by_folder, "../in/d1/a.png") == 1
    assert row_for_image(by_folder, "/data/in/d2/a.png") == 2
    assert row_for_image(by_folder, "/data/in/d4/a.png") == 3
    assert row_for_image(by_folder, "x/d3/b.png") == 4  # another case
    assert row_for_image({"d1/a.png": 1, "e1/d1/a.png": 2}, "e1/d1/a.png") == 2
    assert row_for_image({"x/d1/a.png": 1, "y/d1/a.png": 2}, "d1/a.png") is None


def _key_by_scanning(keys: set[str], name: str, path: str | None) -> str | None:
    """ImageTable.key_for's rules read plainly: every key looked at for each rule."""
    def parts(text: str) -> list[str]:
        return [p for p in text.replace("\\", "/").split("/") if p not in ("", ".")]

    file_name = re.sub(r"#\d+$", "", name)
    if name in keys or file_name in keys:
        return name if name in keys else file_name
    wanted = [parts(file_name)] + ([parts(path)] if path else [])
    for fold in (str, str.casefold):
        for whole in wanted:
            whole = [fold(p) for p in whole]
            ends = {k: len(parts(k)) for k in keys if parts(k)
                    and [fold(p) for p in parts(k)] == whole[len(whole) - len(parts(k)):]}
            if ends:
                longest = [k for k, n in ends.items() if n == max(ends.values())]
                return longest[0] if len(longest) == 1 else None
        same = [k for k in keys if fold(k.replace("\\", "/").rsplit("/", 1)[-1])
                == fold(wanted[0][-1])]
        if same:
            return same[0] if len(same) == 1 else None
    return None


def test_the_tables_index_finds_the_rows_that_scanning_every_row_finds():
    """ImageTable looks up an image among the keys of its file name alone (each lookup had
    read every key: n^2 steps for a run of n images named otherwise than their rows)."""
    rng = random.Random(0)

    def name() -> str:
        folder = rng.choice(["d1", "D1", "e", "x/d1", "", ".", "images", "IMAGES"])
        return ((folder + rng.choice(["/", "\\"]) if folder else "")
                + rng.choice(["a.png", "A.PNG", "b.png", "a.png#2", "c.dcm", "B.png"])
                + rng.choice(["", "", "/", "#3"]))

    found = 0
    for _ in range(600):
        keys = {name() for _ in range(rng.randint(1, 8))}
        table = ImageTable(dict.fromkeys(keys))
        for _ in range(10):
            image, path = name(), rng.choice([None, "/data/" + name(), "../in/" + name()])
            expected = _key_by_scanning(keys, image, path)
            assert table.key_for(image, path) == expected, (keys, image, path)
            found += expected is not None
    assert 1000 < found < 5000  # both outcomes drawn often


def test_a_bad_row_spoils_its_own_cup_alone_and_cups_may_be_written_as_floats(tmp_path):
    """A bad row of cup 1 had turned cup 0 into the error row and left cup 1 solved; a cup
    column written 0.0 / 1.0 (pandas, with a blank somewhere) had spoilt the image."""
    rows = ["image,cup,u,v"]
    for cup, (cx, cy) in enumerate(((100.0, 120.0), (300.0, 140.0))):
        for t in np.linspace(0, 2 * np.pi, 24, endpoint=False):
            rows.append(f"x.png,{cup}.0,{cx + 40 * np.cos(t):.4f},{cy + 25 * np.sin(t):.4f}")
    (tmp_path / "floats.csv").write_text("\n".join(rows) + "\n")
    sets = read_landmarks(tmp_path / "floats.csv")["x.png"]
    assert [(s.cup, s.error, len(s.points)) for s in sets] == [(0, None, 24), (1, None, 24)]
    (tmp_path / "bad.csv").write_text("\n".join([*rows, "x.png,1,n/a,3", "x.png,2.5,1,2",
                                                 "y.png,inf,1,2"]) + "\n")
    landmark_sets = read_landmarks(tmp_path / "bad.csv")
    assert "cannot convert float infinity" in landmark_sets["y.png"][0].error  # not a crash
    sets = landmark_sets["x.png"]
    assert [s.cup for s in sets] == [0, 1, 2] and sets[0].error is None
    assert sets[1].error == "landmark file line 50: could not convert string to float: 'n/a'"
    assert sets[2].error == "landmark file line 51: cup must be a whole number >= 0, got '2.5'"


def test_long_format_landmarks_take_the_image_centre_from_image_size(tmp_path, capsys):
    """The long format gives no image size: the principal point had no default (every row
    'no image size to take its centre from'), nor --assume-defaults' spacing."""
    geometry = Geometry(1040.0, 300.0 / 640, 319.5, 239.5)  # the centre of 640 x 480, 300 mm
    points = rim_landmarks(TRUTH[:1], geometry, n=40)[0]
    (tmp_path / "lm.csv").write_text("image,u,v\n" + "".join(
        f"x.png,{u:.6f},{v:.6f}\n" for u, v in points.tolist()))
    out = tmp_path / "r.csv"
    args = ["solve", str(tmp_path / "lm.csv"), "--out", str(out), "--sdd", "1040",
            "--cup-diameter", "50", "--pixel-spacing", str(300.0 / 640)]
    assert main(args) == 1  # its only row an error
    assert "no image size to take its centre from: give --image-size W H" in results(out)[0][
        "status"]
    assert main([*args, "--image-size", "640", "480", "--overwrite"]) == 0
    row = results(out)[0]
    pose = [float(row[c]) for c in ("anteversion_deg", "inclination_deg", "k_mm", "l_mm", "h_mm")]
    assert pose == pytest.approx(TRUTH[0].tolist(), abs=1e-4)
    # --assume-defaults' spacing, 300 mm over the given width, is the spacing used above.
    capsys.readouterr()
    assert main(["solve", str(tmp_path / "lm.csv"), "--out", str(out), "--assume-defaults",
                 "--sdd", "1040", "--cup-diameter", "50", "--image-size", "640", "480",
                 "--overwrite"]) == 0
    assert float(results(out)[0]["h_mm"]) == pytest.approx(float(TRUTH[0, 4]), abs=1e-3)
    assert ("assuming pixel spacing = 300 mm / image width (e.g. 0.4688 mm/px at 640 px)"
            in capsys.readouterr().err)


def test_a_rows_ellipse_is_its_poses_rim_as_opencv_fits_it(tmp_path):
    """A thin rim's noisy landmarks (the refinement moves the pose off their own fit): the
    row's ellipse columns are those of the reported pose's rim, as OpenCV fits its projected
    points, the ellipse the network's rows and the overlays give; they had been the
    landmarks' own fit, pixels off it."""
    geometry = Geometry(1000.0, 0.4, 300.0, 250.0)
    truth = torch.tensor([[4.0, -8.0, 20.0, 15.0, 280.0]], dtype=torch.float64)
    generator = torch.Generator().manual_seed(5)
    points = rim_landmarks(truth, geometry, n=24)[0]
    points = points + 0.3 * torch.randn(points.shape, generator=generator, dtype=torch.float64)
    row = solved_sets(tmp_path, {"thin.png": points})["thin.png"]
    pose = torch.tensor([[float(row[c]) for c in ("anteversion_deg", "inclination_deg", "k_mm",
                                                   "l_mm", "h_mm")]], dtype=torch.float64)
    rim = rim_landmarks(pose, geometry, diameter=50.0, n=720)[0].numpy().astype(np.float32)
    (cx, cy), (width, height), angle = cv2.fitEllipse(rim)
    # OpenCV gives full axes and the angle of its first axis; CONVENTIONS a >= b, alpha of a.
    if width < height:
        width, height, angle = height, width, angle + 90.0
    expected = [cx, cy, width / 2, height / 2, angle % 180.0]
    got = [float(row[c]) for c in ("ellipse_cx_px", "ellipse_cy_px", "ellipse_a_px",
                                   "ellipse_b_px", "ellipse_angle_deg")]
    assert got[:4] == pytest.approx(expected[:4], abs=2e-3)
    assert abs((got[4] - expected[4] + 90.0) % 180.0 - 90.0) < 1e-2
