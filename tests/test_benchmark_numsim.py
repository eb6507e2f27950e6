"""benchmarks/numsim.py scores poses as ``cupnet evaluate`` does."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from markdown_tables import table_cells

from benchmarks import numsim
from benchmarks.numsim import errors, resolve_ambiguity, robust_ratios
from cupnet.evaluate import pose_errors


def test_inclination_errors_wrap_as_evaluate_scores_them():
    """Across phi = +-90 deg: 89.9 for a truth of -89.9 is 0.2 deg off, not 179.8."""
    truth = torch.tensor([[20.0, -89.9, 1.0, 2.0, 300.0], [30.0, 10.0, 0.0, 0.0, 200.0]],
                         dtype=torch.float64)
    estimate = torch.tensor([[21.0, 89.9, 1.5, 2.0, 310.0], [30.0, 14.0, 0.0, -1.0, 205.0]],
                            dtype=torch.float64)
    got = errors(estimate, truth)
    reference = pose_errors(estimate.numpy(), truth.numpy())
    assert np.allclose(got["phi"].numpy(), np.abs(reference["inclination_deg"]))
    assert np.allclose(got["phi"].numpy(), [0.2, 4.0])
    assert got["theta"].tolist() == [1.0, 0.0] and got["h"].tolist() == [10.0, 5.0]
    # The pose across the boundary is the nearer one of a pair.
    alt = estimate + torch.tensor([0.0, -170.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert torch.equal(resolve_ambiguity(estimate, alt, truth)[0], estimate[0])


def _poses(*rows: list[float]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


def test_k_and_l_errors_pool_both_coordinates_of_every_case():
    """The k/l MAE is over 2 values a case: k alone had halved what l adds."""
    truth = _poses([20.0, 10.0, 0.0, 0.0, 300.0], [30.0, 10.0, 5.0, 5.0, 200.0])
    estimate = _poses([20.0, 10.0, 1.0, -3.0, 300.0], [30.0, 10.0, 5.0, 7.0, 200.0])
    assert errors(estimate, truth)["kl"].tolist() == [1.0, 3.0, 0.0, 2.0]


def test_of_an_ambiguous_pair_the_pose_nearer_the_truth_is_kept():
    """Row 0: the second pose is right and the first 10 deg off; row 1: the first is right
    and the second 10 deg off; row 2: no second pose (NaN), the first kept."""
    truth = _poses(*[[20.0, 10.0, 0.0, 0.0, 300.0]] * 3)
    off = _poses(*[[30.0, 10.0, 0.0, 0.0, 300.0]] * 3)
    nan = torch.full((5,), math.nan, dtype=torch.float64)
    pose = torch.stack([off[0], truth[1], truth[2]])
    alt = torch.stack([truth[0], off[1], nan])
    assert torch.equal(resolve_ambiguity(pose, alt, truth), truth)
    # By orientation: of a pair 22 mm off in h alike, the pose 1.4 deg off is kept over the
    # one 16 deg off that lies 0.03 mm nearer in h (numsim's case 24 at 200 deg, 1 px).
    near = _poses([21.37, 10.0, 0.0, 0.0, 322.39])
    far = _poses([4.0, 10.0, 0.0, 0.0, 322.36])
    assert torch.equal(resolve_ambiguity(far, near, truth[:1]), near)
    assert torch.equal(resolve_ambiguity(near, far, truth[:1]), near)


def test_the_efficiency_ratio_is_one_where_the_median_error_is_0_6745_bounds():
    """A Gaussian's median |error| is 0.6745 sigma, so at the bound the ratio is 1.0; the
    rows outside the subset (here 5 bounds off) are left out."""
    bound = _poses(*[[1.0, 2.0, 3.0, 4.0, 5.0]] * 2, *[[1.0, 1.0, 1.0, 1.0, 0.5]] * 3)
    # |error| / bound: 0.6745 in rows 0 and 1 (of either sign), 5 in rows 2-4.
    scale = torch.tensor([0.6745, -0.6745, 5.0, 5.0, -5.0], dtype=torch.float64)[:, None]
    truth = _poses(*[[20.0, 10.0, 0.0, 0.0, 300.0]] * 5)
    estimate = truth + bound * scale
    subset = torch.tensor([True, True, False, False, False])
    assert robust_ratios(estimate, truth, bound, subset) == pytest.approx([1.0] * 5)
    everything = torch.ones(5, dtype=torch.bool)
    assert robust_ratios(estimate, truth, bound, everything) == pytest.approx(
        [5 / 0.6745] * 5)


# run()'s stub solver: per case the first pose's error, the second pose's (NaN: none), and
# whether it solved. Case 1 is an ambiguous pair whose second pose is right; case 2 is 8 deg
# off in theta only (a gross failure); case 3 failed.
TRUTH = _poses([20.0, 10.0, 0.0, 0.0, 300.0], [25.0, -20.0, 10.0, -10.0, 400.0],
               [35.0, 30.0, -5.0, 5.0, 250.0], [10.0, 0.0, 0.0, 0.0, 200.0])
FIRST_ERROR = _poses([2.0, 1.0, 1.0, -3.0, 4.0], [20.0, 10.0, 0.0, 0.0, 30.0],
                     [8.0, -1.0, 0.0, 2.0, -10.0], [0.0, 0.0, 0.0, 0.0, 0.0])
ALT_ERROR = _poses([math.nan] * 5, [0.0] * 5, [math.nan] * 5, [math.nan] * 5)
SOLVED = torch.tensor([True, True, True, False])


def _stub_solve(points: torch.Tensor, *_: object, **__: object) -> SimpleNamespace:
    n = len(points)
    valid = SOLVED[:n]
    pose = torch.where(valid[:, None], TRUTH[:n] + FIRST_ERROR[:n], math.nan)
    return SimpleNamespace(pose=pose, alt_pose=TRUTH[:n] + ALT_ERROR[:n], valid=valid,
                           ambiguous=~ALT_ERROR[:n, 0].isnan(),
                           ellipse=torch.zeros(n, 5, dtype=torch.float64))


def _ticks() -> Callable[[], float]:
    """A clock that advances one second a reading."""
    count = itertools.count()
    return lambda: float(next(count))


def test_the_simulation_table_scores_the_solved_poses_by_hand(monkeypatch):
    """Each condition's row from fixed errors of 4 cases (3 solved): the first pose's MAEs,
    the resolved pose's MAEs and P95s, fail % (|d theta| or |d phi| > 5 deg, of the solved),
    err % (of all), and the noise sigma the bound is computed for (rounding adds 1/12 px^2)."""
    sigmas = []

    def stub_crb(poses: torch.Tensor, _t: torch.Tensor, sigma: float) -> torch.Tensor:
        sigmas.append(sigma)
        return torch.ones(len(poses), 5, dtype=torch.float64)

    monkeypatch.setattr(numsim, "sample_poses", lambda n, _: TRUTH[:n])
    monkeypatch.setattr(numsim, "solve_pose", _stub_solve)
    monkeypatch.setattr(numsim, "crb", stub_crb)
    monkeypatch.setattr(numsim, "pose_standard_errors",
                        lambda pose, *_: torch.ones_like(pose))
    monkeypatch.setattr(numsim, "orthographic_pose", lambda ellipse: torch.zeros_like(ellipse))
    monkeypatch.setattr(numsim, "time", SimpleNamespace(perf_counter=_ticks(),
                                                        process_time=_ticks()))
    header, *rows = table_cells(numsim.run(4, 0, 0), "condition")
    assert [row[0] for row in rows] == [
        f"{arc} {noise}px{rnd}" for arc in ("full", "200deg") for noise in ("0", "0.5", "1", "2")
        for rnd in ("", " rnd")]
    # Columns by position: "phi MAE", "k/l MAE", "h MAE" name the first pose's and then the
    # resolved pose's.
    expected = {
        1: "10", 2: "4", 3: "1", 4: "14.67",  # first pose: (2+20+8)/3, (1+10+1)/3, 6/6, 44/3
        5: "25.0",  # 1 ambiguous of 4
        # resolved (case 1's second pose, exact): theta 2, 0, 8; phi 1, 0, 1; h 4, 0, 10
        6: "3.333", 7: "7.4",  # P95 of (0, 2, 8): 2 + 0.9 * 6
        8: "0.6667", 9: "1", 10: "4.667", 11: "9.4",  # P95 of (0, 4, 10): 4 + 0.9 * 6
        12: "33.3",  # case 2, 8 deg off in theta alone, of 3 solved
        13: "25.0",  # 1 unsolved of 4
        14: "4", 15: "4",  # 4 poses in one second of the stub clock
    }
    assert [header[i] for i in (6, 7, 11, 12, 13, 14)] == [
        "resolved theta MAE", "theta P95", "h P95", "fail %", "err %", "poses/s"]
    for row in rows:
        assert {i: row[i] for i in expected} == expected, row[0]
    # The bound's noise, per condition with noise (full arc, then 200 deg).
    assert sigmas == pytest.approx(2 * [math.sqrt(noise**2 + extra) for noise in (0.5, 1, 2)
                                         for extra in (0, 1 / 12)])
