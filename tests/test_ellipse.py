"""Direct ellipse fit against OpenCV, exactness, stability, gradients and bad input."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

import cupnet.ellipse
from cupnet.ellipse import (
    EllipseFitError,
    _distinct_counts,
    conic_to_params,
    ellipse_points,
    fit_ellipse,
    is_ellipse,
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


def test_a_conic_that_is_no_ellipse_gives_a_row_of_nan_beside_the_others():
    """A hyperbola's centre is finite and its axes NaN, an imaginary ellipse's axes NaN, a
    parabola has no centre (it raised for the whole batch): each row all NaN, the ellipse's
    row its own."""
    ellipse = params_to_conic(torch.tensor([[100.0, 50.0, 30.0, 10.0, 170.0]],
                                           dtype=torch.float64))
    hyperbola = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))[None]
    imaginary = torch.diag(torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64))[None]
    parabola = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 0.0, -0.5], [0.0, -0.5, 0.0]]],
                            dtype=torch.float64)  # x^2 - y = 0
    params = conic_to_params(torch.cat([ellipse, hyperbola, imaginary, parabola]))
    torch.testing.assert_close(params[0], conic_to_params(ellipse)[0])
    torch.testing.assert_close(params[0], torch.tensor([100.0, 50.0, 30.0, 10.0, 170.0],
                                                       dtype=torch.float64))
    assert params[1:].isnan().all()


def test_gradcheck_points_and_weights(generator):
    truth = torch.tensor([3.0, -2.0, 6.0, 2.5, 30.0], dtype=torch.float64)
    t = torch.linspace(0, 2 * math.pi, 9, dtype=torch.float64)[:-1]
    points = (ellipse_points(truth, t) + 0.1 * torch.randn(8, 2, generator=generator,
                                                           dtype=torch.float64))[None]
    weights = (0.5 + torch.rand(1, 8, generator=generator, dtype=torch.float64))
    points.requires_grad_(True)
    weights.requires_grad_(True)
    # gradcheck's own step, 1e-6: the forward is smooth to round-off. (It had needed 1e-4:
    # where a polish step's pencil was exactly singular, the fit kept its ridged start, and
    # jumped by ~1e-9 px between neighbouring inputs.)
    assert torch.autograd.gradcheck(lambda p, w: fit_ellipse(p, w).params, (points, weights))


@pytest.mark.parametrize("points, message", [
    (torch.zeros(4, 2, dtype=torch.float64) + torch.arange(4.0)[:, None], "too few points"),
    (torch.stack([torch.arange(8.0), 2 * torch.arange(8.0)], -1).double(), "collinear"),
    (torch.full((8, 2), 3.0, dtype=torch.float64), "collinear"),
    # A line with jitter far below any landmark's precision (1e-5 px) is still a line.
    (torch.stack([torch.arange(8.0, dtype=torch.float64), 2 * torch.arange(
        8.0, dtype=torch.float64) + 1e-5 * torch.tensor([1.0, -1.0, 0.5, 2.0, -0.3, 0.7, -1.5,
                                                         0.2], dtype=torch.float64)], -1),
     "collinear"),
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
    # The ellipse-specific fit always returns an ellipse, even for hyperbola points: the
    # same one as OpenCV's direct (Fitzgibbon) fit.
    assert fit.valid.all()
    ref = opencv_params(points.numpy())
    np.testing.assert_allclose(fit.params[0, :4].numpy(), ref[:4], rtol=1e-4, atol=1e-4)
    assert angle_diff(float(fit.params[0, 4]), ref[4]) < 1e-3


def test_float32_and_integer_points_are_fitted_in_float64():
    """CONVENTIONS: fits run in float64. Exact float32 landmarks made the float32 scatter
    matrix singular (its Cholesky factor failed, and with it the batch)."""
    truth = torch.tensor([512.3, 487.9, 121.7, 43.5, 39.9], dtype=torch.float64)
    t = torch.linspace(0, 2 * math.pi, 33, dtype=torch.float64)[:-1]
    points = ellipse_points(truth, t)
    fit32 = fit_ellipse(points.float())
    assert fit32.params.dtype == fit32.conic.dtype == torch.float32
    # Only the float32 rounding of the points (~3e-5 px) moves the fit.
    torch.testing.assert_close(fit32.params[0].double(), fit_ellipse(points.float().double())
                               .params[0], atol=1e-4, rtol=0)
    torch.testing.assert_close(fit32.params[0].double(), truth, atol=1e-3, rtol=0)
    fit_int = fit_ellipse(points.round().long())
    assert fit_int.params.dtype == torch.float64
    assert (fit_int.params[0] - truth)[:4].abs().max() < 0.5


def test_nan_padding_at_zero_weight_drops_out_and_keeps_weight_gradients(generator):
    """A ragged set padded with NaN at weight 0 fits as the set alone; a finite landmark at
    weight 0 stays where it is, so the gradient at that weight is taken at it (one-sided
    finite differences)."""
    truth = torch.tensor([30.0, -12.0, 40.0, 22.0, 65.0], dtype=torch.float64)
    t = torch.linspace(0, 2 * math.pi, 21, dtype=torch.float64)[:-1]
    points = ellipse_points(truth, t) + 0.3 * torch.randn(20, 2, generator=generator,
                                                          dtype=torch.float64)
    padded = torch.cat([points, torch.full((7, 2), math.nan, dtype=torch.float64)])
    weights = torch.cat([torch.ones(20), torch.zeros(7)]).double()
    padded.requires_grad_(True)
    fit = fit_ellipse(padded, weights)
    torch.testing.assert_close(fit.params, fit_ellipse(points).params, atol=1e-9, rtol=0)
    fit.params.sum().backward()
    assert torch.isfinite(padded.grad).all() and (padded.grad[20:] == 0).all()

    weights = torch.ones(20, dtype=torch.float64)
    weights[5] = 0.0
    weights.requires_grad_(True)
    autograd = torch.autograd.grad(fit_ellipse(points, weights).params[0, 2], weights)[0][5]
    step = torch.zeros(20, dtype=torch.float64)
    step[5] = 1e-4  # round-off of ~1e-10 in the forward: a large step, one-sided
    with torch.no_grad():
        upper = fit_ellipse(points, weights + step).params[0, 2]
        lower = fit_ellipse(points, weights).params[0, 2]
    assert float(autograd) == pytest.approx(float((upper - lower) / 1e-4), rel=0.02)
    assert abs(float(autograd)) > 1e-4


def test_repeated_landmarks_count_once():
    """Six landmarks on four distinct points leave a family of ellipses through them."""
    t = torch.linspace(0, 2 * math.pi, 5, dtype=torch.float64)[:-1]
    four = ellipse_points(torch.tensor([0.0, 0.0, 5.0, 3.0, 10.0], dtype=torch.float64), t)
    repeated = torch.cat([four, four[:2]])
    with pytest.raises(EllipseFitError, match=r"too few distinct points: 4 < 5 \(6 landmarks\)"):
        fit_ellipse(repeated)
    # Flagged, the other item of the batch is fitted; the stand-in conic stays finite.
    good = ellipse_points(torch.tensor([0.0, 0.0, 5.0, 3.0, 10.0], dtype=torch.float64),
                          torch.linspace(0, 2 * math.pi, 7, dtype=torch.float64)[:-1])
    fit = fit_ellipse(torch.stack([good, repeated]), on_error="flag")
    assert fit.valid.tolist() == [True, False] and "distinct" in fit.status[1]
    assert torch.isfinite(fit.conic).all()


def test_arguments_it_cannot_take_are_named():
    points = torch.zeros(2, 8, 2, dtype=torch.float64)
    with pytest.raises(EllipseFitError, match=r"weights must have the points' shape \(2, 8\)"):
        fit_ellipse(points, torch.ones(8, dtype=torch.float64))
    with pytest.raises(EllipseFitError, match="on_error must be 'raise' or 'flag'"):
        fit_ellipse(points, on_error="skip")  # type: ignore[arg-type]


def test_alpha_stays_below_180():
    """A major axis a hair below +u wraps to [0, 180), never to 180.0 itself."""
    for alpha in (-1e-12, -1e-14, 0.0):
        params = torch.tensor([100.0, 100.0, 50.0, 20.0, alpha], dtype=torch.float64)
        out = float(conic_to_params(params_to_conic(params))[4])
        assert 0.0 <= out < 180.0 and min(out, 180.0 - out) < 1e-9


def test_distinct_points_counted_exactly(generator):
    """The count against torch.unique on each set's active points."""
    points = torch.randint(0, 4, (30, 12, 2), generator=generator).double()
    active = torch.rand(30, 12, generator=generator) < 0.7
    counts = _distinct_counts(points, active)
    expected = [len(torch.unique(points[i][active[i]], dim=0)) for i in range(30)]
    assert counts.tolist() == expected and len(set(expected)) > 3


def test_a_negative_weight_is_named():
    points = ellipse_points(torch.tensor([50.0, 40.0, 20.0, 10.0, 30.0], dtype=torch.float64),
                            torch.linspace(0, 6, 12, dtype=torch.float64))
    weights = torch.ones(12, dtype=torch.float64)
    weights[3] = -1.0
    with pytest.raises(EllipseFitError, match="negative"):
        fit_ellipse(points, weights)


def test_degenerate_conics_are_no_ellipse():
    """A parabola-like conic (singular quadratic part), a point ellipse and an imaginary one
    are none: only a definite quadratic part with det(C) of the trace's opposite sign is a
    real ellipse (of either sign: a conic's scale is free)."""
    conics = torch.tensor([[[1.0, 0, 0], [0, 1, 0], [0, 0, -1]],  # the unit circle
                           [[-1.0, 0, 0], [0, -1, 0], [0, 0, 1]],  # ... negated
                           [[1.0, 0, 0], [0, 0, 0], [0, 0, -1]],  # two lines x = +-1
                           [[1.0, 0, 0], [0, 1, 0], [0, 0, 0]],  # a single point
                           [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]],  # no real point
                          dtype=torch.float64)
    assert is_ellipse(conics).tolist() == [True, True, False, False, False]


def test_a_fit_that_is_no_ellipse_raises_naming_it(monkeypatch: pytest.MonkeyPatch):
    """The ellipse-specific fit returns an ellipse whenever the scatter matrix allows one;
    round-off may still leave a degenerate conic, which must be an error, not a result."""
    monkeypatch.setattr(cupnet.ellipse, "is_ellipse",
                        lambda conic: torch.zeros(conic.shape[:-2], dtype=torch.bool))
    points = ellipse_points(torch.tensor([50.0, 40.0, 20.0, 10.0, 30.0], dtype=torch.float64),
                            torch.linspace(0, 6, 12, dtype=torch.float64))
    with pytest.raises(EllipseFitError, match="not an ellipse"):
        fit_ellipse(points)
    assert not fit_ellipse(points, on_error="flag").valid.any()
