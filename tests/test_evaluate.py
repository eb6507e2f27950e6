"""cupnet evaluate: matching, known perturbations give known errors, Hausdorff, report."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.distance import directed_hausdorff

from cupnet.cli import main
from cupnet.evaluate import ELLIPSE, POSE, evaluate_results, hausdorff_ellipses, true_ellipses

# theta, phi, k, l, h | cx, cy, a, b, alpha
TRUTH = {
    "a.png": [[20.0, 30.0, -40.0, 10.0, 300.0, 200.0, 300.0, 60.0, 20.0, 120.0],
              [35.0, -40.0, 60.0, 5.0, 250.0, 700.0, 310.0, 55.0, 30.0, 50.0]],
    "b.png": [[10.0, 89.0, 0.0, 0.0, 400.0, 512.0, 512.0, 70.0, 12.0, 179.0]],
    "c.png": [[45.0, 10.0, 20.0, -30.0, 150.0, 600.0, 400.0, 50.0, 35.0, 100.0]],  # missed
    "d.png": [],  # no cup, none predicted
    "e.png": [[30.0, 20.0, 0.0, 0.0, 300.0, 400.0, 400.0, 50.0, 40.0, 0.0]],  # not predicted
}
OFFSET = np.array([2.0, -3.0, 1.5, -0.5, 10.0])  # the known pose error


def write_csv(path: Path, rows: list[dict]) -> Path:
    columns = list(dict.fromkeys(k for row in rows for k in row))
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        writer.writerows(rows)
    return path


def posed(values: list[float]) -> dict[str, float]:
    """A row's pose and ellipse columns from ``values`` in :data:`POSE` + :data:`ELLIPSE` order."""
    return dict(zip(POSE + ELLIPSE, values, strict=True))


def truth_rows() -> list[dict]:
    """Truth in cupnet synth's columns (theta_deg, phi_deg); d.png has no row (no cup)."""
    names = ("theta_deg", "phi_deg", *POSE[2:], *ELLIPSE)
    return [{"image": image, "cup": j, **dict(zip(names, cup, strict=True))}
            for image, cups in TRUTH.items() for j, cup in enumerate(cups)]


def predicted_rows() -> list[dict]:
    """Every cup off by OFFSET, its ellipse 2 px longer; cups of a.png in reverse order."""
    rows = []
    for image, cups in TRUTH.items():
        if image == "e.png":
            continue
        if image in ("c.png", "d.png"):
            rows.append({"image": image, "status": "no_cup", "seconds": 0.5})
            continue
        for cup in reversed(cups):
            pose = np.array(cup[:5]) + OFFSET
            pose[1] = (pose[1] + 90) % 180 - 90  # 89 - 3 = 86 stays; wrap is tested below
            ellipse = np.array(cup[5:]) + [0, 0, 2.0, 0, 0]
            rows.append({"image": image, "status": "ok", "seconds": 0.5,
                         **posed([*pose, *ellipse])})
    # A false positive far from every true cup.
    rows.append({"image": "b.png", "status": "ok", "seconds": 0.5,
                 **posed([20, 20, 0, 0, 300, 50, 50, 30, 20, 0])})
    return rows


def test_known_perturbation_gives_known_errors(tmp_path: Path) -> None:
    truth = write_csv(tmp_path / "truth.csv", truth_rows())
    pred = write_csv(tmp_path / "pred.csv", predicted_rows())
    metrics = evaluate_results(pred, truth)
    assert metrics["true_cups"] == 4 and metrics["matched_cups"] == 3
    assert metrics["detection_rate"] == pytest.approx(0.75)
    assert metrics["false_positives"] == 1
    assert metrics["images"] == 4 and metrics["seconds_per_image"] == pytest.approx(0.5)
    assert metrics["truth_images_not_predicted"] == 1  # e.png: left out, not a missed cup
    for i, name in enumerate(POSE):
        stats = metrics["perspective"][name]
        for key in ("mae", "median", "p95"):
            assert stats[key] == pytest.approx(abs(OFFSET[i]), abs=1e-9), (name, key)
    assert metrics["perspective"]["kl_mm"]["mae"] == pytest.approx(math.hypot(1.5, 0.5))
    # Semi-major axis 2 px longer, everything else equal: the Hausdorff distance is 2 px.
    assert metrics["perspective"]["hausdorff_px"]["mae"] == pytest.approx(2.0, abs=1e-3)
    assert metrics["gross_failures"] == 0


def test_a_far_false_cup_does_not_outbid_a_found_one(tmp_path: Path) -> None:
    """Two true cups (u 300 and 700), one found 10 px off the left one, a false cup at u 0:
    the assignment over all distances had paired the false cup with the left cup (300 px)
    and the found one with the right (390 px; 690 in all, against 10 + 700), and both
    pairs, past the semi-major axis, were dropped: 0 of 2 found, 2 false positives."""
    pose = [20.0, 30.0, 0.0, 0.0, 300.0]
    truth = write_csv(tmp_path / "truth.csv", [
        {"image": "x.png", "cup": j, **posed([*pose[:4], h, u, 300, 40, 25, 0])}
        for j, (u, h) in enumerate(((300, 300.0), (700, 310.0)))])
    found = [21.0, *pose[1:], 310, 300, 40, 25, 0]
    false = [*pose, 0, 300, 40, 25, 0]
    pred = write_csv(tmp_path / "pred.csv", [
        {"image": "x.png", "cup": j, "status": "ok", "seconds": 1.0,
         **posed(values)}
        for j, values in enumerate((found, false))])
    metrics = evaluate_results(pred, truth)
    assert metrics["matched_cups"] == 1 and metrics["false_positives"] == 1
    assert metrics["perspective"]["anteversion_deg"]["mae"] == pytest.approx(1.0)


def test_a_cup_found_within_the_true_semi_major_axis_is_matched(tmp_path: Path) -> None:
    """Pairs match within the true ellipse's semi-major axis: a cup found 30 px along the
    axis of a 60 x 20 px rim is found, not missed beside a false positive."""
    truth = write_csv(tmp_path / "truth.csv", [
        {"image": "x.png", "cup": 0, **posed([20.0, 30.0, 0, 0, 300, 300, 300, 60, 20, 0])}])
    pred = write_csv(tmp_path / "pred.csv", [
        {"image": "x.png", "cup": 0, "status": "ok", "seconds": 1.0,
         **posed([20.0, 30.0, 0, 0, 300, 330, 300, 60, 20, 0])}])
    metrics = evaluate_results(pred, truth)
    assert metrics["matched_cups"] == 1 and metrics["detection_rate"] == 1.0
    assert metrics["false_positives"] == 0


def test_statistics_and_rates_over_unequal_cups_and_images(tmp_path: Path) -> None:
    """The fixture gives every cup one error and every image one time, and predicts as many
    cups as are true, so a median taken as a mean, a 90th percentile for the 95th, a rate
    over predicted cups or a mean time over rows would pass it. Here: k errors -1, 2 and
    10 mm; a.png (two cups) 1 s, the other images 0.5 s; no false cup (3 predicted of 4
    true); f.png failed with an error row for each of its two cups (one image)."""
    rows = [row for row in predicted_rows() if row.get("ellipse_cx_px") != 50]  # the false cup
    found = [row for row in rows if row["status"] == "ok"]  # a.png's two cups, then b.png's
    for row, error in zip(found, (-1.0, 2.0, 10.0), strict=True):
        row["k_mm"] += error - OFFSET[2]
    for row in rows:
        row["seconds"] = 1.0 if row["image"] == "a.png" else 0.5
    rows += [{"image": "f.png", "cup": cup, "status": "error: cannot read file", "seconds": 0.5}
             for cup in (0, 1)]
    metrics = evaluate_results(write_csv(tmp_path / "pred.csv", rows),
                               write_csv(tmp_path / "truth.csv", truth_rows()))
    # numpy's (linear) percentile of 1, 2, 10: 2 + 0.9 * (10 - 2).
    assert metrics["perspective"]["k_mm"] == pytest.approx(
        {"mae": 13 / 3, "median": 2.0, "p95": 9.2})
    assert (metrics["true_cups"], metrics["predicted_cups"], metrics["matched_cups"]) == (4, 3, 3)
    assert metrics["detection_rate"] == pytest.approx(0.75) and metrics["false_positives"] == 0
    assert metrics["images"] == 5 and metrics["error_images"] == 1
    assert metrics["seconds_per_image"] == pytest.approx((1.0 + 4 * 0.5) / 5)


@pytest.mark.parametrize(("anteversion", "inclination", "inclination_error", "gross"), [
    (10.0, -88.0, 3.0, 0),  # 89 to -88 is 3 degrees, not 177
    (16.5, -88.0, 3.0, 1),  # anteversion 6.5 off
    (15.0, -88.0, 3.0, 0),  # anteversion exactly 5 off: not gross (gross is more than 5)
    (10.0, -85.0, 6.0, 1),  # inclination alone 6 off
    (10.0, -86.0, 5.0, 0),  # inclination exactly 5 off
])
def test_inclination_error_wraps_and_gross_failures(tmp_path: Path, anteversion: float,
                                                    inclination: float, inclination_error: float,
                                                    gross: int) -> None:
    """A gross failure is either angle off by more than 5 degrees, inclination errors wrapped
    (phi is defined modulo 180; the values are exact in binary, so 5 is 5). The predicted
    ellipse's major axis at 91 degrees gives the orthographic inclination -89: 2 degrees off
    the true 89 once wrapped too."""
    truth = write_csv(tmp_path / "truth.csv", truth_rows()[2:3])  # b.png, theta 10, phi 89
    row = {"image": "b.png", "status": "ok", "seconds": 1.0,
           **posed([anteversion, inclination, 0, 0, 400, 512, 512, 70, 12, 91])}
    metrics = evaluate_results(write_csv(tmp_path / "p.csv", [row]), truth)
    assert metrics["perspective"]["inclination_deg"]["mae"] == pytest.approx(inclination_error)
    assert metrics["gross_failures"] == gross and metrics["gross_failure_rate"] == gross
    assert metrics["orthographic"]["inclination_deg"]["mae"] == pytest.approx(2.0)


def test_cups_flagged_to_check_are_counted_and_set_apart(tmp_path: Path) -> None:
    """Of the three matched cups, the one flagged ``check`` (given a gross anteversion
    error here) is counted, with its gross failure; the MAE of the others is OFFSET's."""
    truth = write_csv(tmp_path / "truth.csv", truth_rows())
    rows = predicted_rows()
    for row in rows:
        row["check"] = 0 if row["status"] == "ok" else ""
    flagged = next(r for r in rows if r.get("k_mm") == 60.0 + OFFSET[2])  # a.png's second
    flagged["check"], flagged["anteversion_deg"] = 1, 35.0 + 30.0
    metrics = evaluate_results(write_csv(tmp_path / "pred.csv", rows), truth)
    assert metrics["check"]["flagged"] == 1 and metrics["check"]["gross_flagged"] == 1
    assert metrics["gross_failures"] == 1
    assert metrics["perspective"]["anteversion_deg"]["mae"] == pytest.approx((2 + 2 + 30) / 3)
    for i, name in enumerate(POSE):
        assert metrics["check"]["unflagged"][name]["mae"] == pytest.approx(abs(OFFSET[i]))


def test_orthographic_baseline_hand_case(tmp_path: Path) -> None:
    # b / a = 1/2 -> asin = 30 deg; true anteversion 25 -> orthographic error 5 deg.
    truth = write_csv(tmp_path / "t.csv", [{"image": "x.png", **dict(zip(
        POSE + ELLIPSE, [25.0, 40.0, 0, 0, 300, 100, 100, 20, 10, 40.0], strict=True))}])
    pred = write_csv(tmp_path / "p.csv", [{"image": "x.png", "status": "ok", **dict(zip(
        POSE + ELLIPSE, [25.0, 40.0, 0, 0, 300, 100, 100, 20, 10, 40.0], strict=True))}])
    metrics = evaluate_results(pred, truth)
    assert metrics["orthographic"]["anteversion_deg"]["mae"] == pytest.approx(5.0)
    assert metrics["orthographic"]["inclination_deg"]["mae"] == pytest.approx(0.0, abs=1e-9)


def test_hausdorff_matches_scipy_on_dense_samples() -> None:
    rng = np.random.default_rng(0)
    first = np.column_stack([rng.uniform(100, 900, 6), rng.uniform(100, 900, 6),
                             rng.uniform(30, 80, 6), rng.uniform(5, 30, 6),
                             rng.uniform(0, 180, 6)])
    second = first + rng.normal(0, 3, first.shape)
    ours = hausdorff_ellipses(first, second)
    t = np.linspace(0, 2 * np.pi, 20000, endpoint=False)

    def samples(e: np.ndarray) -> np.ndarray:
        c, s = np.cos(np.deg2rad(e[4])), np.sin(np.deg2rad(e[4]))
        x, y = e[2] * np.cos(t), e[3] * np.sin(t)
        return np.column_stack([e[0] + c * x - s * y, e[1] + s * x + c * y])

    for i in range(6):
        p, q = samples(first[i]), samples(second[i])
        reference = max(directed_hausdorff(p, q)[0], directed_hausdorff(q, p)[0])
        assert ours[i] == pytest.approx(reference, abs=2e-3)


def test_true_ellipse_from_pose_and_meta_geometry(tmp_path: Path) -> None:
    # Rim facing the source (theta = 90) centred on the principal point: a circle of radius
    # r * H / (H - h) / s = 25 * 1000 / 800 / 0.5 = 62.5 px.
    rows = [{"image": "x.png", "anteversion_deg": "90", "inclination_deg": "0", "k_mm": "0",
             "l_mm": "0", "h_mm": "200"}]
    meta = {"x.png": {"sdd_mm": "1000", "pixel_spacing_mm": "0.5", "cup_diameter_mm": "50",
                      "principal_u_px": "300", "principal_v_px": "200"}}
    ellipse = true_ellipses(rows, meta)[0]
    np.testing.assert_allclose(ellipse[:4], [300, 200, 62.5, 62.5], atol=1e-9)
    with pytest.raises(ValueError, match="no ellipse columns"):
        true_ellipses(rows, {})


def test_cli_writes_report_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    truth = write_csv(tmp_path / "truth.csv", truth_rows())
    pred = write_csv(tmp_path / "pred.csv", predicted_rows())
    assert main(["evaluate", "--pred", str(pred), "--truth", str(truth), "--out",
                 str(tmp_path / "ev")]) == 0
    report = (tmp_path / "ev" / "report.md").read_text()
    assert "| anteversion (deg) | 2 | 2 | 2 |" in report
    # d.png has no truth row: scored as an image without a cup, and the report says so
    assert "1 predicted image(s) have no truth row and count as images without a cup" in report
    for name in ("error_vs_distance.png", "predicted_vs_true.png"):
        assert (tmp_path / "ev" / "plots" / name).stat().st_size > 1000
        assert f"(plots/{name})" in report
    assert json.loads((tmp_path / "ev" / "metrics.json").read_text())["matched_cups"] == 3
    assert "anteversion (deg)" in capsys.readouterr().out
    bad = write_csv(tmp_path / "bad.csv", [{"image": "a.png"}])
    assert main(["evaluate", "--pred", str(bad), "--truth", str(truth), "--out",
                 str(tmp_path / "ev2")]) == 2
    assert "missing column" in capsys.readouterr().err


def test_predictions_of_a_parent_folder_find_their_truth_by_file_name(tmp_path: Path) -> None:
    """`cupnet predict DIR --recursive` names images `images/a.png`; a truth of the images'
    own folder names them `a.png`: they had matched nothing (every cup a false positive)."""
    truth = write_csv(tmp_path / "truth.csv", truth_rows())
    plain = evaluate_results(write_csv(tmp_path / "p.csv", predicted_rows()), truth)
    prefixed = [{**row, "image": f"images/{row['image']}"} for row in predicted_rows()]
    metrics = evaluate_results(write_csv(tmp_path / "q.csv", prefixed), truth)
    assert metrics == plain and metrics["matched_cups"] == 3
    assert metrics["predicted_images_without_truth"] == 1  # d.png: no truth row, no cup


def test_an_ambiguous_cup_scores_its_first_pose_and_says_what_the_second_gives(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    truth = write_csv(tmp_path / "truth.csv", truth_rows()[2:3])  # b.png
    true_pose = truth_rows()[2]
    row = {"image": "b.png", "cup": 0, "status": "ambiguous", "seconds": 1.0,
           **posed([25.0, 89.0, 0, 0, 400, 512, 512, 70, 12, 179]),
           **{f"alt_{c}": v for c, v in zip(POSE, [10.0, 89.0, 0.0, 0.0, 400.0],
                                              strict=True)}}
    assert true_pose["theta_deg"] == 10.0 and true_pose["phi_deg"] == 89.0
    pred = write_csv(tmp_path / "p.csv", [row])
    metrics = evaluate_results(pred, truth)
    assert metrics["perspective"]["anteversion_deg"]["mae"] == pytest.approx(15.0)
    assert (metrics["ambiguous_matched"], metrics["ambiguous_second_nearer"],
            metrics["gross_second_right"], metrics["gross_failures"]) == (1, 1, 1, 1)
    assert main(["evaluate", "--pred", str(pred), "--truth", str(truth), "--out",
                 str(tmp_path / "out")]) == 0
    report = (tmp_path / "out" / "report.md").read_text()
    assert "1 matched cup(s) ambiguous" in report and "their first pose is scored" in report


def test_what_the_files_hold_that_cannot_be_scored_is_said(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture
                                                           ) -> None:
    """A byte-order mark is read; rows repeated (two files appended) are an error naming
    them; truth rows without a whole pose are counted as left out."""
    rows = truth_rows()
    truth = tmp_path / "truth.csv"
    write_csv(truth, rows)
    truth.write_text(truth.read_text(), encoding="utf-8-sig")
    pred = write_csv(tmp_path / "p.csv", predicted_rows())
    assert evaluate_results(pred, truth)["matched_cups"] == 3
    out = ["--out", str(tmp_path / "out")]
    assert main(["evaluate", "--pred", str(pred), "--truth",
                 str(write_csv(tmp_path / "twice.csv", rows + rows[:1])), *out]) == 2
    assert "two truth rows alike for image a.png" in capsys.readouterr().err
    assert main(["evaluate", "--pred", str(write_csv(tmp_path / "q.csv", predicted_rows()
                                                     + predicted_rows()[:1])),
                 "--truth", str(truth), *out]) == 2
    assert "two prediction rows alike for image a.png" in capsys.readouterr().err
    blank = [{**row, "h_mm": ""} if row["image"] == "b.png" else row for row in rows]
    metrics = evaluate_results(pred, write_csv(tmp_path / "blank.csv", blank))
    assert metrics["truth_rows_incomplete"] == 1 and metrics["true_cups"] == 3
    # Its cup, found, is no false positive (it had counted as one): the far one alone is.
    assert metrics["false_positives"] == 1
    # Left-out rows discount no more than the image's unpaired cups: a.png's two rows left
    # out, one of its cups found; the far cup in b.png is still the one false positive.
    blank = [{**row, "h_mm": ""} if row["image"] == "a.png" else row for row in rows]
    lone = [row for row in predicted_rows() if row.get("k_mm") != 60.0 + OFFSET[2]]
    metrics = evaluate_results(write_csv(tmp_path / "lone.csv", lone),
                               write_csv(tmp_path / "blank_a.csv", blank))
    assert metrics["truth_rows_incomplete"] == 2 and metrics["false_positives"] == 1
    # A status no results.csv holds ('OK' from a spreadsheet) had read as a missed cup.
    shouted = [{**row, "status": "OK"} if row["image"] == "a.png" else row
               for row in predicted_rows()]
    assert main(["evaluate", "--pred", str(write_csv(tmp_path / "shout.csv", shouted)),
                 "--truth", str(truth), *out]) == 2
    assert "unknown status value(s) 'OK'" in capsys.readouterr().err
    # A row cut short before its status had ended the command in a traceback.
    cut = write_csv(tmp_path / "cut.csv", predicted_rows())
    with cut.open("a") as f:
        f.write("b.png\n")
    assert main(["evaluate", "--pred", str(cut), "--truth", str(truth), *out]) == 2
    assert "unknown status value(s) None" in capsys.readouterr().err
    # A found cup without a whole pose had been left out of that angle's MAE silently.
    partial = [{**row, POSE[0]: ""} if row["image"] == "a.png" else row
               for row in predicted_rows()]
    assert main(["evaluate", "--pred", str(write_csv(tmp_path / "partial.csv", partial)),
                 "--truth", str(truth), *out]) == 2
    assert "2 row(s) of status ok or ambiguous without a whole pose (first: a.png)" in \
        capsys.readouterr().err
