"""The benchmarks' figures from hand-made detections: MAEs, percentiles, detection rates,
bootstrap intervals, pooled means and rates, checked against values worked out by hand (the
shipped model is stubbed out, so these run in a blink)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmarks import model as bench_model
from benchmarks import solver_speed
from benchmarks.model import accuracy, interval, oblong_section, scored
from benchmarks.throughput import scores, table_row

TRUTH = [20.0, 10.0, 0.0, 0.0, 300.0]


def detection(u: float, error: list[float], check: bool = False,
              alt_error: list[float] | None = None) -> SimpleNamespace:
    """A detection centred at ``(u, 100)`` px whose pose is off :data:`TRUTH` by ``error``
    (and whose second pose, where given, by ``alt_error``)."""
    pose = np.add(TRUTH, error)
    return SimpleNamespace(ellipse=np.array([u, 100.0, 40.0, 30.0, 0.0]), pose=pose,
                           check=check,
                           alt_pose=None if alt_error is None else np.add(TRUTH, alt_error))


def image(cups: int, detections: list[SimpleNamespace]) -> dict:
    """A sample of ``cups`` true cups at ``u`` = 100, 200, ... (all at :data:`TRUTH`), and the
    detections a stub model finds in it."""
    ellipse = torch.tensor([[100.0 * (c + 1), 100.0, 40.0, 30.0, 0.0] for c in range(cups)])
    return {"pose": torch.tensor([TRUTH] * cups), "ellipse": ellipse,
            "cup_valid": torch.ones(cups), "detections": detections}


@pytest.fixture
def stub_detect(monkeypatch: pytest.MonkeyPatch) -> None:
    """``accuracy``'s model call returns each sample's hand-made detections."""
    monkeypatch.setattr(bench_model, "detect_sample", lambda _model, s: s["detections"])


def test_accuracy_scores_hand_made_detections(stub_detect):
    """Five true cups in two images: four found (errors below), one missed, and one
    detection away from every cup (a false positive, flagged)."""
    data = [
        image(3, [detection(100, [1, 0, 2, 0, 4]),
                  # Gross by phi alone; an ambiguous pair whose second pose is right.
                  detection(200, [2, 6, 0, 2, 8], check=True, alt_error=[0, 0, 0, 0, 0]),
                  detection(900, [0, 0, 0, 0, 0], check=True)]),  # no true cup there
        image(2, [detection(100, [3, 0, 4, 0, 0]),
                  detection(200, [10, 0, 0, 4, 12], check=True)]),  # gross by theta
    ]
    cases: list = []
    res = accuracy(None, data, cases)
    assert len(cases) == 5 and [err is None for *_, err in cases] == [False, False, True,
                                                                       False, False]
    # theta errors 1, 2, 3, 10: the 90th percentile (linear) is 3 + 0.7 * (10 - 3).
    assert (res["mae_theta"], res["median_theta"], res["p90_theta"]) == pytest.approx(
        (4.0, 2.5, 7.9))
    assert (res["mae_phi"], res["mae_k"], res["mae_l"], res["mae_h"]) == pytest.approx(
        (1.5, 1.5, 1.5, 6.0))
    # Found over the true cups (not over the detections, false positives among them).
    assert res["detected"] == pytest.approx(4 / 5)
    assert (res["cups"], res["false_positives"], res["false_positives_flagged"]) == (5, 1, 1)
    # Two of the four flagged, both gross (one by phi alone); the unflagged two's MAEs.
    assert (res["flagged"], res["gross"], res["gross_flagged"], res["gross_alt_right"]) == (
        2, 2, 2, 1)
    assert (res["ambiguous"], res["ambiguous_gross"], res["gross_silent"]) == (1, 1, 0)
    assert [res[f"unflagged_mae_{n}"] for n in ("theta", "phi", "k", "l", "h")] == \
        pytest.approx([2.0, 0.0, 3.0, 0.0, 2.0])
    assert scored(res)[5:] == ["80.0 % of 5", "1 (1 flagged)"]


def test_the_pooled_oblong_mae_weights_each_shape_by_its_found_cups(monkeypatch):
    """Shape one: theta MAE 1 over 4 of 4 cups found; shape two: 4 over 2 of 4. Pooled over
    the cups found: (4 * 1 + 2 * 4) / 6 = 2 deg (by true cups it had read 2.5); the gross
    failures (none, then 2 with 1 flagged) summed."""
    results = iter([
        {"mae_theta": 1.0, "mae_phi": 2.0, "mae_k": 3.0, "mae_l": 4.0, "mae_h": 6.0,
         "detected": 1.0, "cups": 4, "false_positives": 1, "false_positives_flagged": 0,
         "gross": 0, "gross_flagged": 0},
        {"mae_theta": 4.0, "mae_phi": 5.0, "mae_k": 0.0, "mae_l": 1.0, "mae_h": 3.0,
         "detected": 0.5, "cups": 4, "false_positives": 2, "false_positives_flagged": 1,
         "gross": 2, "gross_flagged": 1},
    ])
    monkeypatch.setattr(bench_model, "samples", lambda *_: [])
    monkeypatch.setattr(bench_model, "accuracy", lambda *_: next(results))
    args = argparse.Namespace(oblong=[(768, 512), (512, 768)], oblong_images=10,
                              eval_config="configs/synth_eval.yaml", seed=0)
    text = oblong_section({"onnx": None}, args)
    *_, second, pooled = text.splitlines()
    assert second.endswith("| 50.0 % of 4 | 2 (1 flagged) | 2 (1 flagged) |")
    assert pooled == ("| onnx | all | 10 | 2 | 3 | 2 | 3 | 5 | 75.0 % of 8 | 3 (1 flagged) "
                      "| 2 (1 flagged) |")


def test_a_seed_section_pools_what_the_check_flag_marks_over_its_seeds(stub_detect,
                                                                        monkeypatch):
    """Two seeds, each the images below: per seed 6 cups found, 2 flagged, both gross (one an
    ambiguous pair whose second pose is right), an unflagged ambiguous pair in the wrong
    order, a gross failure nothing warns of, 1 missed, and an ambiguous pair whose first
    pose is right. Pooled: 4 of 12 flagged, 4 of 8 gross flagged, 4 of 6 pairs in the wrong
    order, 2 gross with no warning; the unflagged cups' errors (twice): theta 1, 3, 0, 6,
    phi 0, 0, 7, 0, h 4, 0, 0, 0."""
    data = [
        image(3, [detection(100, [1, 0, 2, 0, 4], alt_error=[20, 0, 0, 0, 0]),
                  detection(200, [2, 6, 0, 2, 8], check=True, alt_error=[0, 0, 0, 0, 0])]),
        image(2, [detection(100, [3, 0, 4, 0, 0]),
                  detection(200, [10, 0, 0, 4, 12], check=True)]),
        image(1, [detection(100, [0, 7, 0, 0, 0])]),
        image(1, [detection(100, [6, 0, 0, 0, 0], alt_error=[0, 0, 0, 0, 0])]),
    ]
    monkeypatch.setattr(bench_model, "samples", lambda *_: data)
    args = argparse.Namespace(fresh_seeds=[1, 2], fresh_images=2, sizes=[512], seed=0,
                              eval_config="configs/synth_eval.yaml", runtimes=["onnx"],
                              checkpoint=str(bench_model.DEFAULT_CHECKPOINT), seed_presets=[])
    model = SimpleNamespace(config=SimpleNamespace(check_doubt=1.4))
    pooled = bench_model.fresh_seed_section({"onnx": model}, args).splitlines()[-1]
    assert pooled.startswith("Pooled, onnx flags 4 of the 12 detected cups (33.3 %) `check` "
                             "(its doubt >= `check_doubt` 1.4), 4 of the 8 gross failures")
    assert "; 4 of those 8 are ambiguous pairs" in pooled
    assert "; with no warning at all: 2 of the 8;" in pooled
    assert pooled.endswith("the cups not flagged have MAE theta 2.5 deg, phi 1.75 deg, h 1 mm. "
                           "Found cups `ambiguous`: 6; the pose reported first lies within 5 "
                           "deg for 2 of them, the second for 4 of the other 4.")


def test_a_bootstrap_interval_of_a_constant_is_the_constant():
    values = np.tile([[2.5, -1.0]], (7, 1))
    np.testing.assert_allclose(interval(values), [[2.5, -1.0], [2.5, -1.0]])


def test_a_bootstrap_interval_of_a_share_spans_1_96_standard_errors_each_side():
    """0/1 data (cups found), 600 of 2000: the bootstrap means are near normal, with the
    binomial standard error sqrt(0.3 * 0.7 / 2000); a 95 % interval spans 3.92 of them (a
    90 % one, 3.29), about the share."""
    found = np.repeat([1.0, 0.0], [600, 1400])
    low, high = interval(found)
    standard_error = np.sqrt(0.3 * 0.7 / len(found))
    assert 3.6 < (high - low) / standard_error < 4.25
    assert low < 0.3 < high and abs((low + high) / 2 - 0.3) < 0.5 * standard_error


def test_throughput_scores_a_missed_cup_against_the_true_cups():
    """Two images, three true cups: two found (errors below), one missed; a detection
    matching no cup is not scored."""
    found = [[detection(100, [1, 2, 3, 4, 5]), detection(900, [50, 50, 50, 50, 50])],
             [detection(200, [3, 0, 1, 0, 1])]]
    data = [image(1, []), image(2, [])]
    quality = scores(found, data)
    assert quality == pytest.approx({"theta": 2.0, "phi": 1.0, "k": 2.0, "l": 2.0, "h": 3.0,
                                     "found": 2 / 3})


def test_a_throughput_row_gives_images_per_second_and_milliseconds_per_image(capsys):
    quality = {"theta": 1.0, "phi": 2.5, "k": 0.125, "l": 3.0, "h": 10.0, "found": 0.9}
    row = table_row("`detect`", "fp32", 8, images=10, seconds=2.0, quality=quality)
    assert row == ["`detect`", "fp32", 8, "5.0", "200.00", "1.00", "2.50", "0.12", "3.00",
                   "10.00", "90.0 %"]
    assert capsys.readouterr().out.startswith("| `detect` | fp32 | 8 | 5.0 | 200.00 |")


def test_best_rate_gives_the_wall_rate_then_the_cpu_rate_of_the_fastest_repeat(monkeypatch):
    """Two repeats of 10 items, read off clocks that say the wall took 4 s then 2 s and the
    CPU 3 s then 1 s: 5 items a second of wall clock, 10 a CPU second."""
    def readings(*values: float) -> Callable[[], float]:
        return iter(values).__next__

    monkeypatch.setattr(solver_speed, "time", SimpleNamespace(
        perf_counter=readings(0.0, 4.0, 10.0, 12.0), process_time=readings(0.0, 3.0, 3.0, 4.0)))
    assert solver_speed.best_rate(lambda: None, 10, 2) == (5.0, 10.0)
