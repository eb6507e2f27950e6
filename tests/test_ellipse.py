"""Direct ellipse fit against OpenCV, exactness, stability, gradients and bad input."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from cupnet.ellipse import (
    EllipseFitError,
    conic_to_params,
    ellipse_points,
    fit_ellipse,
    params_to_conic,
)


def opencv_params(points: np.ndarray) -> np.ndarray:
    """cv2.fitEllipseDirect in CONVENTIONS parameters (cx, cy, a, b, alpha in [0, 180))."""
    (cx, cy), (w, h), angle = cv2.fitEllipseDirect(points.astype(np.float32))
    alpha = angle if w >= h else angle + 90.0
    return np.array([cx, cy, max(w, h) / 2, min(w, h) / 2, alpha % 180.0])


def angle_diff(a: float, b: float) -> float:
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def test_matches_opencv_on_noisy_points(generator):
    for _ in range(20):
        truth = torch.tensor([
            300 * torch.rand(1, generator=generator).item() + 50,
            300 * torch.rand(1, generator=generator).item() + 50,
            40 + 60 * torch.rand(1, generator=generator).item(),
            10 + 25 * torch.rand(1, generator=generator).item(),
            180 * torch.rand(1, generator=generator).item()], dtype=torch.float64)
        t = 2 * math.pi * torch.rand(60, generator=generator, dtype=torch.float64)
        points = ellipse_points(truth, t) + torch.randn(60, 2, generator=generator,
                                                        dtype=torch.float64)
        # OpenCV works on float32 internally for its input: give both the same numbers.
        points = points.float().double()
        ours = fit_ellipse(points).params[0].numpy()
        ref = opencv_params(points.numpy())
        np.testing.assert_allclose(ours[:4], ref[:4], rtol=1e-6)
        assert angle_diff(ours[4], ref[4]) < 1e-5


@pytest.mark.parametrize("centre, a, b", [((2500.0, 4900.0), 300.0, 3.0),  # b/a = 0.01, far
                                          ((10.0, 20.0), 5.0, 4.0),
                                          ((4990.0, 10.0), 800.0, 8.0)])
def test_exact_on_noise_free_points(centre, a, b):
    truth = torch.tensor([*centre, a, b, 33.0], dtype=torch.float64)
    t = torch.linspace(0, 2 * math.pi, 50, dtype=torch.float64)[:-1]
    fit = fit_ellipse(ellipse_points(truth, t))
    err = (fit.params[0] - truth).abs()
    assert (err[:4] / truth[2]).max() < 1e-8  # relative to the major axis
    assert err[4] < 1e-7


def test_partial_arc_noise_free_is_exact():
    truth = torch.tensor([100.0, 80.0, 60.0, 20.0, 120.0], dtype=torch.float64)
    t = torch.linspace(0, math.radians(90), 20, dtype=torch.float64)
    fit = fit_ellipse(ellipse_points(truth, t))
    torch.testing.assert_close(fit.params[0], truth, rtol=1e-8, atol=1e-7)


def test_zero_weight_drops_points_and_batches_ragged_sets():
    truth = torch.tensor([[0.0, 0.0, 30.0, 10.0, 10.0], [5.0, -5.0, 12.0, 11.0, 170.0]],
                         dtype=torch.float64)
    t = torch.linspace(0, 2 * math.pi, 13, dtype=torch.float64)[:-1]
    points = ellipse_points(truth, t)
    weights = torch.ones(2, 12, dtype=torch.float64)
    weights[1, 6:] = 0
    points[1, 6:] = torch.nan  # ignored, since their weight is zero
    fit = fit_ellipse(points, weights)
    torch.testing.assert_close(fit.params, truth, rtol=1e-8, atol=1e-7)


def test_params_conic_round_trip():
    params = torch.tensor([[10.0, -3.0, 7.0, 2.0, 0.0], [1.0, 2.0, 50.0, 49.0, 179.0],
                           [300.0, 200.0, 9.0, 3.0, 91.0]], dtype=torch.float64)
    torch.testing.assert_close(conic_to_params(params_to_conic(params)), params)


def test_gradcheck_points_and_weights(generator):
    truth = torch.tensor([3.0, -2.0, 6.0, 2.5, 30.0], dtype=torch.float64)
    t = torch.linspace(0, 2 * math.pi, 9, dtype=torch.float64)[:-1]
    points = (ellipse_points(truth, t) + 0.1 * torch.randn(8, 2, generator=generator,
                                                           dtype=torch.float64))[None]
    weights = (0.5 + torch.rand(1, 8, generator=generator, dtype=torch.float64))
    points.requires_grad_(True)
    weights.requires_grad_(True)
    # Eight noisy points leave ~1e-10 of round-off in the forward: step 1e-4, not 1e-6.
    assert torch.autograd.gradcheck(lambda p, w: fit_ellipse(p, w).params, (points, weights),
                                    eps=1e-4)


@pytest.mark.parametrize("points, message", [
    (torch.zeros(4, 2, dtype=torch.float64) + torch.arange(4.0)[:, None], "too few points"),
    (torch.stack([torch.arange(8.0), 2 * torch.arange(8.0)], -1).double(), "collinear"),
    (torch.full((8, 2), 3.0, dtype=torch.float64), "collinear"),
    (torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [math.nan, 2.0],
                   [2.0, 3.0]], dtype=torch.float64), "non-finite"),
])
def test_bad_input_raises_a_clear_error(points, message):
    with pytest.raises(EllipseFitError, match=message):
        fit_ellipse(points)


def test_flag_mode_reports_per_item_and_keeps_the_good_ones():
    t = torch.linspace(0, 2 * math.pi, 11, dtype=torch.float64)[:-1]
    good = ellipse_points(torch.tensor([0.0, 0.0, 5.0, 3.0, 0.0], dtype=torch.float64), t)
    line = torch.stack([t, t], -1)
    fit = fit_ellipse(torch.stack([good, line]), on_error="flag")
    assert fit.status[0] == "ok" and "collinear" in fit.status[1]
    assert fit.valid.tolist() == [True, False]
    assert torch.isfinite(fit.params[0]).all() and torch.isnan(fit.params[1]).all()


def test_empty_batch_gives_empty_results():
    # An image with no cup yields a batch of zero point sets.
    fit = fit_ellipse(torch.zeros(0, 12, 2, dtype=torch.float64), on_error="flag")
    assert fit.params.shape == (0, 5) and fit.valid.dtype == torch.bool and fit.status == []


def test_hyperbola_points_are_not_an_ellipse():
    x = torch.linspace(1, 3, 10, dtype=torch.float64)
    points = torch.cat([torch.stack([x, 1 / x], -1), torch.stack([-x, -1 / x], -1)])
    fit = fit_ellipse(points, on_error="flag")
    # The ellipse-specific fit always returns an ellipse, even for hyperbola points.
    assert fit.valid.all() and fit.params[0, 2] >= fit.params[0, 3] > 0
