"""Closed-form pose, ML refinement, range choice, gradients, bad input."""

from __future__ import annotations

import math

import pytest
import torch
from cup_cases import paper_poses, rim_landmarks

from cupnet.geometry import Geometry, pose_to_degrees, pose_to_radians, project_rim, rim_conic
from cupnet.pose import (
    PoseError,
    _closest_rim_parameters,
    _curvature_offsets,
    _noise_variance,
    _normal_jacobian,
    _rim,
    canonical_pose,
    cramer_rao_bound,
    orthographic_pose,
    other_circle_pose,
    pose_standard_errors,
    poses_from_conic,
    range_violation,
    refine_pose,
    rim_distances,
    solve_pose,
    solve_pose_paper,
)

GEOMETRY = Geometry(1040.0, 1.0, 0.0, 0.0)


def test_closed_form_round_trip_over_the_paper_ranges(generator):
    """Pose -> rim conic -> both candidates: one of them is the pose (deg / mm)."""
    truth = paper_poses(2000, generator)
    conic = rim_conic(pose_to_radians(truth), 25.0, GEOMETRY)
    candidates = pose_to_degrees(canonical_pose(poses_from_conic(conic, GEOMETRY, 25.0)))
    err = (candidates - truth[:, None]).abs().max(-1).values.min(-1).values
    assert err.quantile(0.99) < 1e-7
    assert err.max() < 1e-4  # rims seen almost edge-on (b/a ~ 1e-3) are ill-conditioned


def test_solve_pose_noise_free_is_exact_and_flags_ambiguity(generator):
    truth = paper_poses(500, generator)
    geometry = Geometry(1040.0, 0.4, 700.0, 650.0)
    sol = solve_pose(rim_landmarks(truth, geometry), geometry, 50.0)
    assert sol.valid.all()
    err = (sol.pose - truth).abs().max(-1).values
    alt_err = (sol.alt_pose - truth).abs().max(-1).values
    # Unambiguous: exact. Ambiguous: the truth is one of the two poses returned.
    assert err[~sol.ambiguous].max() < 1e-6
    assert torch.minimum(err, alt_err)[sol.ambiguous].max() < 1e-6
    assert set(sol.status) <= {"ok", "ambiguous"}
    assert (sol.residual_px < 1e-6).all()
    # Both returned poses lie in the CONVENTIONS ranges.
    for pose in (sol.pose, sol.alt_pose[sol.ambiguous]):
        assert (pose[:, 0] >= 0).all() and (pose[:, 0] <= 90).all()
        assert (pose[:, 1].abs() <= 90).all()



def test_a_cup_at_inclination_plus_90_is_reported_first_inside_the_range():
    """phi's range is (-90, 90]: exact landmarks of a cup at +90 deg have their mirror pose
    at -90, with the larger theta, and that end of the range had been reported first."""
    truth = torch.tensor([[20.0, 90.0, 0.0, 0.0, 300.0]], dtype=torch.float64)
    geometry = Geometry(1040.0, 0.3, 511.5, 511.5)
    sol = solve_pose(rim_landmarks(truth, geometry, 52.0, 60), geometry, 52.0)
    torch.testing.assert_close(sol.pose, truth, atol=1e-6, rtol=0)
    assert bool(sol.ambiguous[0]) and float(sol.alt_pose[0, 1]) == -90.0
    assert float(sol.alt_pose[0, 0]) > 20.0  # the mirror, preferred by its theta before

def test_edge_on_and_face_on_cups():
    # On the central ray the mirror pose is (-theta, phi) = (theta, phi - 180): both in range
    # (within the 1 deg margin) near theta = 0 and near phi = 90.
    truth = torch.tensor([[0.3, 20.0, 0.0, 0.0, 300.0],     # almost edge-on: ambiguous
                          [89.5, 10.0, 0.0, 0.0, 200.0],    # almost face-on
                          [30.0, 89.8, 0.0, 0.0, 300.0]], dtype=torch.float64)
    sol = solve_pose(rim_landmarks(truth, GEOMETRY), GEOMETRY, 50.0)
    assert bool(sol.ambiguous[0]) and bool(sol.ambiguous[2])
    err = torch.minimum((sol.pose - truth).abs().max(-1).values,
                        (sol.alt_pose - truth).abs().nan_to_num(1e9).max(-1).values)
    assert err[[0, 2]].max() < 1e-5
    # Face-on: phi is ill-defined, the rest is exact.
    assert (sol.pose[1, [0, 2, 3, 4]] - truth[1, [0, 2, 3, 4]]).abs().max() < 1e-3


def test_other_circle_pose_is_the_solvers_second_pose(generator):
    """From a pose alone: the second pose of its rim's ellipse, and whether it is in range,
    as solve_pose finds them from exact landmarks of that rim (an independent path: a fit,
    the closed form, the ML refinement); the other pose's other pose is the pose again."""
    truth = paper_poses(400, generator)
    geometry = Geometry(1040.0, 0.4, 700.0, 650.0)
    radius = torch.full((len(truth),), 25.0, dtype=torch.float64)
    sol = solve_pose(rim_landmarks(truth, geometry), geometry, 50.0)
    other, in_range = other_circle_pose(sol.pose, radius, geometry)
    # Away from the range's 1 deg margin, where round-off could tip either judgement.
    raw = poses_from_conic(rim_conic(pose_to_radians(sol.pose), radius, geometry), geometry,
                           radius)
    # (The pose's own violation is 0: the larger one is the other pose's.)
    margin = (torch.rad2deg(range_violation(raw)).max(-1).values - 1.0).abs() > 1e-3
    assert (in_range == sol.ambiguous)[margin].all() and 20 < int(sol.ambiguous.sum()) < 380
    # 1e-4: nearly edge-on rims are ill-conditioned (as in the round trip above).
    torch.testing.assert_close(other[sol.ambiguous], sol.alt_pose[sol.ambiguous],
                               atol=1e-4, rtol=0)
    # Where the other pose lies strictly in range (not clamped to it), its other is the pose.
    inside = torch.rad2deg(range_violation(raw)).max(-1).values < 1e-9
    back, _ = other_circle_pose(other[inside], radius[inside], geometry)
    torch.testing.assert_close(back, sol.pose[inside], atol=1e-4, rtol=0)
    assert int(inside.sum()) > 20


def test_range_violation_and_canonical_pose():
    rad = pose_to_radians(torch.tensor([[20.0, 30.0, 0, 0, 100], [20.0, 120.0, 0, 0, 100],
                                        [-5.0, 10.0, 0, 0, 100]], dtype=torch.float64))
    violation = torch.rad2deg(range_violation(rad))
    torch.testing.assert_close(violation, torch.tensor([0.0, 20.0, 5.0], dtype=torch.float64))
    canon = pose_to_degrees(canonical_pose(rad))
    # (-5, 10) is the same rim circle as (5, -170): out of range, nearest boundary theta = 0.
    assert canon[2, 0] == 0.0 and abs(float(canon[2, 1]) - 10.0) < 1e-9


def test_refinement_lowers_the_rim_residual_and_reaches_a_stationary_point(generator):
    truth = paper_poses(64, generator)
    truth[:, 0] = truth[:, 0].clamp(min=15.0)
    points = rim_landmarks(truth, GEOMETRY) + torch.randn(64, 100, 2, generator=generator,
                                                          dtype=torch.float64)
    closed = solve_pose(points, GEOMETRY, 50.0, refine=False, on_error="flag")
    refined = solve_pose(points, GEOMETRY, 50.0, on_error="flag")
    assert (refined.residual_px <= closed.residual_px + 1e-9).all()
    assert refined.residual_px.mean() < closed.residual_px.mean()
    # Residual of the ML fit ~ the noise's normal component (1 px), a little less (5 dof).
    assert 0.85 < float(refined.residual_px.mean()) < 1.0


def test_rim_distances_on_nearly_edge_on_rims_match_a_dense_search(generator):
    """Landmarks 0.3 px off rims 1-2 px wide (theta under 3 deg): each landmark's distance is
    the least over 20,000 rim points (an independent search), not that of a point on the
    rim's far side, where the homography's start had trapped the Newton steps (the RMS had
    come out up to ten times the true one)."""
    truth = paper_poses(200, generator)
    truth[:, 0] = 0.3 + 2.5 * torch.rand(200, generator=generator, dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, n=40) + 0.3 * torch.randn(
        200, 40, 2, generator=generator, dtype=torch.float64)
    pose, radius = pose_to_radians(truth), torch.full((200,), 25.0, dtype=torch.float64)
    found = rim_distances(pose, points, radius, GEOMETRY)
    t = torch.linspace(0, 2 * math.pi, 20_001, dtype=torch.float64)[:-1]

    def dense_distances(landmarks: torch.Tensor, rim_pose: torch.Tensor) -> torch.Tensor:
        """Each landmark's least distance to 20,000 points of its rim (25 mm), px."""
        return torch.cat([torch.cdist(p, project_rim(q, 25.0, GEOMETRY, t)).min(-1).values
                          for p, q in zip(landmarks.split(20), rim_pose.split(20),
                                          strict=True)])

    dense = dense_distances(points, pose)
    assert (found >= dense - 0.01).all()  # half the dense rim's spacing: under 0.01 px
    assert (found - dense).quantile(0.999) < 0.02
    rms = found.pow(2).mean(-1).sqrt() / dense.pow(2).mean(-1).sqrt()
    assert rms.max() < 1.03
    # and so the solver's residual: the reported pose's RMS distance, as a dense search finds
    sol = solve_pose(points, GEOMETRY, 50.0, on_error="flag")
    ok = sol.valid
    nearest = dense_distances(points[ok], pose_to_radians(sol.pose[ok]))
    torch.testing.assert_close(sol.residual_px[ok], nearest.pow(2).mean(-1).sqrt(),
                               atol=0.01, rtol=0.01)


def test_cramer_rao_bound_matches_the_spread_of_the_ml_estimate(generator):
    truth = torch.tensor([[40.0, 25.0, 30.0, -20.0, 300.0]], dtype=torch.float64)
    trials = 400
    t = torch.arange(100, dtype=torch.float64) * (2 * math.pi / 100)
    clean = rim_landmarks(truth, GEOMETRY)
    points = clean + torch.randn(trials, 100, 2, generator=generator, dtype=torch.float64)
    est = solve_pose(points, GEOMETRY, 50.0).pose
    bound = cramer_rao_bound(pose_to_radians(truth), 25.0, GEOMETRY, t, 1.0)[0]
    ratio = est.std(0) / bound
    assert ((ratio > 0.85) & (ratio < 1.15)).all(), ratio


@pytest.mark.parametrize("sigma", [1.0, 2.5])
def test_standard_errors_from_the_residuals_match_the_bound_and_the_spread(generator, sigma):
    """The errors a solve reports, with the noise measured from its own residuals, are the
    Cramer-Rao bound at the true noise (jacfwd of the projection, an independent
    derivation), and about 95 % of the poses lie within 1.96 of them of the truth."""
    truth = torch.tensor([[40.0, 25.0, 30.0, -20.0, 300.0]], dtype=torch.float64)
    t = torch.arange(100, dtype=torch.float64) * (2 * math.pi / 100)
    points = rim_landmarks(truth, GEOMETRY) + sigma * torch.randn(
        400, 100, 2, generator=generator, dtype=torch.float64)
    sol = solve_pose(points, GEOMETRY, 50.0)
    errors = pose_standard_errors(sol.pose, points, GEOMETRY, 50.0)
    bound = cramer_rao_bound(pose_to_radians(truth), 25.0, GEOMETRY, t, sigma)[0]
    assert ((errors.mean(0) / bound - 1).abs() < 0.02).all(), errors.mean(0) / bound
    # Each solve's own: a noise level measured on 95 degrees of freedom varies by about
    # 1 / sqrt(2 * 95) = 7 %, and the bound with the solved pose.
    assert ((errors.std(0) / errors.mean(0)) < 0.15).all()
    covered = ((sol.pose - truth).abs() < 1.96 * errors).double().mean(0)
    assert ((covered > 0.92) & (covered < 0.98)).all(), covered


def test_weighted_standard_errors_do_not_depend_on_the_weights_scale(generator):
    """Landmarks of two noise levels, weighted 1 / sigma^2 at two scales: the same errors,
    and they match the spread of the weighted solves."""
    truth = torch.tensor([[40.0, 25.0, 30.0, -20.0, 300.0]], dtype=torch.float64)
    sigma = torch.where(torch.arange(100) % 2 == 0, 0.5, 2.0).double()
    points = rim_landmarks(truth, GEOMETRY) + sigma[None, :, None] * torch.randn(
        400, 100, 2, generator=generator, dtype=torch.float64)
    weights = (1 / sigma**2).expand(400, 100)
    sol = solve_pose(points, GEOMETRY, 50.0, weights=weights)
    errors = pose_standard_errors(sol.pose, points, GEOMETRY, 50.0, weights)
    torch.testing.assert_close(pose_standard_errors(sol.pose, points, GEOMETRY, 50.0,
                                                    7 * weights), errors)
    # Padding without weight (NaN, as in a ragged batch) changes nothing.
    padded = torch.cat([points, torch.full((400, 3, 2), math.nan, dtype=torch.float64)], 1)
    torch.testing.assert_close(pose_standard_errors(
        sol.pose, padded, GEOMETRY, 50.0, torch.cat([weights, torch.zeros(400, 3)], 1)), errors)
    ratio = errors.mean(0) / sol.pose.std(0)
    assert ((ratio > 0.9) & (ratio < 1.1)).all(), ratio


def test_standard_errors_are_nan_without_a_pose_or_with_too_few_landmarks():
    truth = torch.tensor([[40.0, 25.0, 30.0, -20.0, 300.0]], dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY)[0]
    no_pose = torch.full((1, 5), math.nan, dtype=torch.float64)
    assert pose_standard_errors(no_pose, points, GEOMETRY, 50.0).isnan().all()
    assert pose_standard_errors(truth, points[:5], GEOMETRY, 50.0).isnan().all()
    # Eight landmarks on two points leave the pose unconstrained: no errors, not huge ones.
    two_points = torch.cat([points[:1].repeat(4, 1), points[50:51].repeat(4, 1)]) + 0.3
    assert pose_standard_errors(truth, two_points, GEOMETRY, 50.0).isnan().all()
    # Six landmarks: one degree of freedom for the noise, still an estimate.
    six = points[::17][:6] + 0.3
    assert torch.isfinite(pose_standard_errors(truth, six, GEOMETRY, 50.0)).all()


def test_curvature_correction_removes_most_of_the_thin_ellipse_bias(generator):
    # theta = 8 deg: the rim's tips bend on a radius of ~0.7 px, below the 1 px noise, and
    # plain ML inflates the ellipse there (h too large, theta too small).
    truth = torch.tensor([[8.0, 30.0, 20.0, -10.0, 300.0]], dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY) + torch.randn(300, 100, 2, generator=generator,
                                                          dtype=torch.float64)
    t = torch.arange(100, dtype=torch.float64) * (2 * math.pi / 100)
    bound = cramer_rao_bound(pose_to_radians(truth), 25.0, GEOMETRY, t, 1.0)[0]
    bias = {c: (solve_pose(points, GEOMETRY, 50.0, corrected=c).pose - truth).mean(0) / bound
            for c in (False, True)}
    assert bias[False][4] > 1.2  # the plain ML bias this corrects, in CRB units
    keep = [0, 2, 3, 4]  # phi has no bias to remove
    assert (bias[True][keep].abs() < 0.5 * bias[False][keep].abs()).all(), bias
    assert bias[True].abs().max() < 0.8, bias


def test_compiled_solver_matches_the_eager_one(generator):
    truth = paper_poses(64, generator)
    points = rim_landmarks(truth, GEOMETRY) + torch.randn(64, 100, 2, generator=generator,
                                                          dtype=torch.float64)
    eager = solve_pose(points, GEOMETRY, 50.0)
    fused = solve_pose(points, GEOMETRY, 50.0, compiled=True)
    assert torch.allclose(fused.pose, eager.pose, rtol=0, atol=1e-6, equal_nan=True)


def test_compiled_solver_falls_back_to_eager_with_a_warning(generator, monkeypatch):
    import cupnet.pose as pose_module

    def no_compiler(function):
        def fail(*args):
            raise RuntimeError("no C++ compiler")
        return fail

    monkeypatch.setattr(pose_module, "_compiled", no_compiler)
    monkeypatch.setattr(pose_module, "_UNCOMPILABLE", set())
    truth = paper_poses(4, generator)
    points = rim_landmarks(truth, GEOMETRY)
    with pytest.warns(UserWarning, match="torch.compile failed"):
        fused = solve_pose(points, GEOMETRY, 50.0, compiled=True)
    assert torch.allclose(fused.pose, solve_pose(points, GEOMETRY, 50.0).pose, equal_nan=True)


@pytest.mark.parametrize("corrected", [True, False])
def test_gradcheck_refined_pose_wrt_points_and_weights(generator, corrected):
    truth = torch.tensor([[35.0, 20.0, 10.0, 5.0, 250.0]], dtype=torch.float64)
    geometry = Geometry(1040.0, 1.0, 0.0, 0.0)
    t = torch.arange(8, dtype=torch.float64) * (2 * math.pi / 8)
    points = rim_landmarks(truth, geometry, n=8) + 0.3 * torch.randn(
        1, 8, 2, generator=generator, dtype=torch.float64)
    start = poses_from_conic(rim_conic(pose_to_radians(truth), 25.0, geometry), geometry,
                             25.0)[:, 0]
    weights = 0.5 + torch.rand(1, 8, generator=generator, dtype=torch.float64)
    points.requires_grad_(True)
    weights.requires_grad_(True)
    del t

    def refined(p: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return refine_pose(start, p, geometry, 25.0, w, max_iter=100, tol=1e-30,
                           corrected=corrected)[0]

    assert torch.autograd.gradcheck(refined, (points, weights), atol=1e-6, rtol=1e-4)


def test_gradcheck_refined_pose_wrt_geometry_and_cup_diameter(generator):
    """solve_pose's refined pose against finite differences in every geometry field and the
    cup's diameter (its backward had given none: a network learning a calibration or the
    cup's size got a zero or missing gradient)."""
    truth = torch.tensor([[30.0, 25.0, 15.0, -10.0, 280.0]], dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, 50.0, n=16)
    points = points + 0.3 * torch.randn(points.shape, generator=generator, dtype=torch.float64)
    fields = torch.tensor([1040.0, 1.0, 3.0, -2.0, 50.0], dtype=torch.float64,
                          requires_grad=True)  # sdd, spacing, u0, v0 (mm, mm, px, px), diameter

    def pose(f: torch.Tensor) -> torch.Tensor:
        return solve_pose(points, Geometry(*f[:4]), f[4], tol=1e-20, max_iter=50).pose

    assert torch.autograd.gradcheck(pose, (fields,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_converged_says_where_the_gradient_is_that_of_the_solution(generator):
    """Nearly edge-on rims (theta under 3 deg, 0.5 px of noise) whose refinement stops at
    max_iter, along h's flat valley, say so (converged False), and their implicit gradient is
    off (against central differences of the same call); the ones that converged have the
    gradient of their solution. Noise-free landmarks of open rims, and the closed form,
    converge."""
    m = 100
    truth = paper_poses(m, generator)
    truth[:, 0] = 3.0 * torch.rand(m, generator=generator, dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, n=32) + 0.5 * torch.randn(
        m, 32, 2, generator=generator, dtype=torch.float64)
    direction = torch.randn(points.shape, generator=generator, dtype=torch.float64)
    scale = torch.tensor([1.0, 1.0, 0.1, 0.1, 0.02], dtype=torch.float64)

    def pose(p: torch.Tensor) -> torch.Tensor:  # (m,) one weighted sum of each pose
        return (solve_pose(p, GEOMETRY, 50.0, on_error="flag").pose * scale).sum(-1)

    x = points.clone().requires_grad_()
    pose(x).sum().backward()
    analytic = (x.grad * direction).sum((-1, -2))
    numeric = (pose(points + 1e-6 * direction) - pose(points - 1e-6 * direction)) / 2e-6
    error = (analytic - numeric).abs() / numeric.abs().clamp_min(1e-3)
    sol = solve_pose(points, GEOMETRY, 50.0, on_error="flag")
    converged = sol.converged
    assert converged.dtype == torch.bool and 10 <= int((~converged).sum()) <= 60
    assert (error[converged] < 0.1).float().mean() > 0.95
    assert (error[~converged] > 0.1).float().mean() > 0.5
    clean = rim_landmarks(truth + torch.tensor([10.0, 0, 0, 0, 0], dtype=torch.float64),
                          GEOMETRY, n=32)
    assert solve_pose(clean, GEOMETRY, 50.0).converged.all()
    closed = solve_pose(points, GEOMETRY, 50.0, refine=False, on_error="flag")
    assert torch.equal(closed.converged, closed.valid)


def test_second_derivatives_through_the_refined_pose_are_refused_by_name(generator):
    """A graph of the gradient (create_graph=True, as a gradient penalty makes) through the
    refinement's implicit backward: a RuntimeError naming the way round, where the
    Hessian-vector products had come out 20-40 % off without a word; the closed form's
    second derivatives still agree with finite differences of its gradient."""
    truth = torch.tensor([[20.0, 40.0, 10.0, -5.0, 300.0]], dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, n=12) + 0.3 * torch.randn(
        1, 12, 2, generator=generator, dtype=torch.float64)
    x = points.clone().requires_grad_()
    with pytest.raises(RuntimeError, match="second derivatives through the refined pose"):
        torch.autograd.grad(solve_pose(x, GEOMETRY, 50.0).pose[0, 0], x, create_graph=True)

    def gradient(p: torch.Tensor, graph: bool = False) -> torch.Tensor:
        return torch.autograd.grad(solve_pose(p, GEOMETRY, 50.0, refine=False).pose[0, 0], p,
                                   create_graph=graph)[0]

    direction = torch.randn(points.shape, generator=generator, dtype=torch.float64)
    hessian_v = torch.autograd.grad((gradient(x, graph=True) * direction).sum(), x)[0]
    eps = 1e-5
    numeric = (gradient((points + eps * direction).requires_grad_())
               - gradient((points - eps * direction).requires_grad_())) / (2 * eps)
    torch.testing.assert_close(hessian_v, numeric, rtol=1e-5, atol=1e-7)


def test_gradcheck_closed_form_pose_wrt_points(generator):
    truth = torch.tensor([[25.0, -30.0, -10.0, 20.0, 300.0]], dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, n=7) + 0.2 * torch.randn(
        1, 7, 2, generator=generator, dtype=torch.float64)
    points.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: solve_pose(p, GEOMETRY, 50.0, refine=False).pose, (points,))


def test_pose_gradient_reaches_landmarks_through_solve_pose(generator):
    truth = torch.tensor([[30.0, 15.0, 0.0, 0.0, 300.0]], dtype=torch.float64)
    points = (rim_landmarks(truth, GEOMETRY, n=32) + 0.5 * torch.randn(
        1, 32, 2, generator=generator, dtype=torch.float64)).requires_grad_(True)
    sol = solve_pose(points, GEOMETRY, 50.0)
    sol.pose[0, 0].backward()
    assert torch.isfinite(points.grad).all() and points.grad.abs().sum() > 0


@pytest.mark.parametrize("kwargs, message", [
    (dict(geometry=Geometry(1040.0, -1.0, 0.0, 0.0)), "pixel spacing"),
    (dict(geometry=Geometry(0.0, 1.0, 0.0, 0.0)), "source-to-detector"),
    (dict(geometry=Geometry(1040.0, 1.0, 0.0, math.nan)), "principal point"),
    (dict(cup_diameter=-50.0), "radius"),
    (dict(cup_diameter=0.0), "radius"),
    (dict(cup_diameter=400.0), "outside"),  # no cup that big fits between source and detector
])
def test_bad_geometry_raises_naming_the_value(kwargs, message):
    truth = torch.tensor([[30.0, 15.0, 0.0, 0.0, 300.0]], dtype=torch.float64)
    args = dict(points=rim_landmarks(truth, GEOMETRY), geometry=GEOMETRY, cup_diameter=50.0)
    args.update(kwargs)
    with pytest.raises(PoseError, match=message):
        solve_pose(**args)


def test_tiny_ellipse_and_bad_items_are_flagged_while_the_batch_goes_on():
    truth = torch.tensor([[30.0, 15.0, 0.0, 0.0, 300.0]] * 3, dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, n=20).clone()
    points[1] = points[1].mean(0) + (points[1] - points[1].mean(0)) * 0.01  # ~0.3 px ellipse
    points[2, 3] = math.nan
    sol = solve_pose(points, GEOMETRY, 50.0, on_error="flag")
    assert sol.status[0] == "ok"
    assert "too small" in sol.status[1] and "non-finite" in sol.status[2]
    assert torch.isnan(sol.pose[1:]).all() and torch.isfinite(sol.pose[0]).all()
    with pytest.raises(PoseError, match="item 1: ellipse too small"):
        solve_pose(points, GEOMETRY, 50.0)


def test_an_item_in_error_reports_no_second_pose():
    """An almost edge-on cup has two poses in range; given a cup too big to fit between
    source and detector, its row is an error with neither."""
    truth = torch.tensor([[0.3, 20.0, 0.0, 0.0, 300.0]] * 2, dtype=torch.float64)
    sol = solve_pose(rim_landmarks(truth, GEOMETRY), GEOMETRY,
                     torch.tensor([50.0, 400.0], dtype=torch.float64), on_error="flag")
    assert sol.status[0] == "ambiguous" and sol.status[1].startswith("error")
    assert sol.ambiguous.tolist() == [True, False]
    assert torch.isfinite(sol.alt_pose[0]).all() and torch.isnan(sol.alt_pose[1]).all()


def test_orthographic_baseline_is_exact_for_a_distant_source():
    truth = torch.tensor([[35.0, -40.0, 0.0, 0.0, 100.0]], dtype=torch.float64)
    far = Geometry(1e9, 1.0, 0.0, 0.0)
    sol = solve_pose(rim_landmarks(truth, far), far, 50.0)
    ortho = orthographic_pose(sol.ellipse)
    torch.testing.assert_close(ortho[0], truth[0, :2], atol=1e-4, rtol=0)


def test_orthographic_inclination_wraps_the_major_axis_angle_into_its_half_open_range():
    ellipses = torch.tensor([[0.0, 0.0, 30.0, 15.0, alpha] for alpha in (0.0, 90.0, 90.5, 179.0)])
    torch.testing.assert_close(orthographic_pose(ellipses)[:, 1],
                               torch.tensor([0.0, 90.0, -89.5, -1.0]))  # phi in (-90, 90]
    torch.testing.assert_close(orthographic_pose(ellipses)[0, 0], torch.tensor(30.0))  # asin(1/2)


def test_orthographic_baseline_is_biased_off_centre_and_perspective_is_not():
    truth = torch.tensor([[20.0, 30.0, 100.0, 100.0, 150.0]], dtype=torch.float64)
    sol = solve_pose(rim_landmarks(truth, GEOMETRY), GEOMETRY, 50.0)
    assert abs(float(orthographic_pose(sol.ellipse)[0, 0]) - 20.0) > 2.0
    assert abs(float(sol.pose[0, 0]) - 20.0) < 1e-6


def test_paper_mode_converges_from_its_first_best_guess():
    # The second cup's inclination lies across +-90 deg from the 40 deg start: reached only
    # because phi wraps within its range between steps.
    truth = torch.tensor([[28.0, 35.0, 20.0, -10.0, 300.0],
                          [39.6, -57.9, -29.8, 16.3, 221.1]], dtype=torch.float64)
    pose, steps = solve_pose_paper(rim_landmarks(truth, GEOMETRY), GEOMETRY, 50.0, steps=4000)
    assert (pose - truth).abs().max() < 0.05, pose
    assert (10 < steps).all() and (steps <= 4000).all()


def test_float32_landmarks_are_solved_in_float64(generator):
    """Accurate float32 landmarks of a nearly edge-on cup crashed the float32 fit; solved in
    float64 (CONVENTIONS) they give the pose, in float32."""
    truth = torch.tensor([[5.0, 30.0, 0.0, 0.0, 300.0], [20.0, 40.0, 10.0, -5.0, 300.0]],
                         dtype=torch.float64)
    geometry = Geometry(1040.0, 0.3, 511.5, 511.5)
    points = rim_landmarks(truth, geometry, 52.0, n=32)
    points = points + 0.05 * torch.randn(points.shape, generator=generator, dtype=torch.float64)
    sol = solve_pose(points.float(), geometry, 52.0)
    assert sol.pose.dtype == sol.ellipse.dtype == sol.residual_px.dtype == torch.float32
    reference = solve_pose(points.float().double(), geometry, 52.0)
    torch.testing.assert_close(sol.pose.double(), reference.pose, atol=1e-3, rtol=1e-5)
    assert (sol.pose.double() - truth)[:, :2].abs().max() < 1.0


def test_nan_padded_ragged_sets_solve_as_the_sets_alone(generator):
    truth = torch.tensor([[20.0, 40.0, 10.0, -5.0, 300.0], [30.0, -20.0, -30.0, 10.0, 250.0]],
                         dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, 50.0, n=32)
    points = points + 0.5 * torch.randn(points.shape, generator=generator, dtype=torch.float64)
    weights = torch.ones(2, 32, dtype=torch.float64)
    weights[0, 20:] = 0.0
    padded = points.clone()
    padded[0, 20:] = math.nan
    padded.requires_grad_(True)
    sol = solve_pose(padded, GEOMETRY, 50.0, weights)
    alone = solve_pose(points[0, :20], GEOMETRY, 50.0)
    torch.testing.assert_close(sol.pose[:1], alone.pose, atol=1e-6, rtol=0)
    torch.testing.assert_close(sol.residual_px[:1], alone.residual_px, atol=1e-9, rtol=0)
    sol.pose.sum().backward()
    assert torch.isfinite(padded.grad).all() and (padded.grad[0, 20:] == 0).all()


def test_solve_pose_tol_makes_its_gradient_exact(generator):
    """``tol`` reaches the refinement: tightened, the implicit gradient of a thin rim's h
    agrees with finite differences of solve_pose itself."""
    truth = torch.tensor([[6.0, 35.0, 20.0, -10.0, 300.0]], dtype=torch.float64)
    points = rim_landmarks(truth, GEOMETRY, 50.0, n=24)
    points = points + 0.3 * torch.randn(points.shape, generator=generator, dtype=torch.float64)
    points.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: solve_pose(p, GEOMETRY, 50.0, tol=1e-20, max_iter=50).pose[:, [0, 4]],
        (points,), eps=1e-5, atol=1e-5, rtol=1e-3)


def test_batch_sizes_that_disagree_are_named():
    points = rim_landmarks(torch.tensor([[20.0, 40.0, 0.0, 0.0, 300.0]] * 2,
                                        dtype=torch.float64), GEOMETRY, 50.0, n=16)
    three = Geometry(torch.tensor([1040.0, 1000.0, 990.0], dtype=torch.float64), 1.0, 0.0, 0.0)
    with pytest.raises(PoseError, match=r"geometry sdd must be a scalar or one per item \(2\)"):
        solve_pose(points, three, 50.0)
    with pytest.raises(PoseError, match=r"cup_diameter must be a scalar or one per item \(2\)"):
        solve_pose(points, GEOMETRY, torch.tensor([50.0, 52.0, 54.0]))
    with pytest.raises(PoseError, match=r"weights must have the points' shape"):
        solve_pose(points, GEOMETRY, 50.0, torch.ones(16, dtype=torch.float64))


@pytest.mark.parametrize("refine", [True, False])
def test_an_empty_batch_gives_empty_results(refine):
    """No landmark sets (a batch of images without a cup): empty results, as fit_ellipse
    gives (a float mask had failed in torch.where)."""
    sol = solve_pose(torch.zeros(0, 16, 2, dtype=torch.float64), GEOMETRY, 50.0, refine=refine)
    assert sol.pose.shape == sol.alt_pose.shape == sol.ellipse.shape == (0, 5)
    assert sol.valid.shape == sol.residual_px.shape == (0,) and sol.status == []


def test_each_item_of_a_mixed_batch_is_solved_as_if_alone(generator):
    """Items of their own geometry and cup size in one batch: the first, noise-free, leaves
    the solver's working set first, so a later item read by position would take its rows."""
    truth = torch.tensor([[30.0, 15.0, 10.0, -5.0, 300.0], [12.0, -40.0, -30.0, 20.0, 250.0],
                          [45.0, 70.0, 5.0, 5.0, 400.0]], dtype=torch.float64)
    sdd, spacing = [1040.0, 1000.0, 990.0], [1.0, 0.4, 0.2]
    u0, v0 = [0.0, 5.0, -8.0], [0.0, -3.0, 6.0]
    diameters = torch.tensor([50.0, 56.0, 44.0], dtype=torch.float64)
    geometry = Geometry(*(torch.tensor(f, dtype=torch.float64) for f in (sdd, spacing, u0, v0)))
    t = torch.arange(40, dtype=torch.float64) * (2 * math.pi / 40)
    points = project_rim(pose_to_radians(truth), diameters / 2, geometry, t)
    points[1:] += 0.5 * torch.randn(2, 40, 2, generator=generator, dtype=torch.float64)
    batch = solve_pose(points, geometry, diameters)
    errors = pose_standard_errors(batch.pose, points, geometry, diameters)
    bound = cramer_rao_bound(pose_to_radians(truth), diameters / 2, geometry, t, 1.0)
    for i in range(3):
        one = Geometry(sdd[i], spacing[i], u0[i], v0[i])
        alone = solve_pose(points[i:i + 1], one, float(diameters[i]))
        torch.testing.assert_close(batch.pose[i], alone.pose[0], atol=1e-7, rtol=0)
        torch.testing.assert_close(errors[i], pose_standard_errors(
            alone.pose, points[i:i + 1], one, float(diameters[i]))[0], atol=1e-9, rtol=1e-7)
        torch.testing.assert_close(bound[i], cramer_rao_bound(
            pose_to_radians(truth[i:i + 1]), float(diameters[i]) / 2, one, t, 1.0)[0])


def test_rim_derivatives_along_the_rim_match_finite_differences():
    """The solver's inner loop differentiates the projected rim by hand: d(u, v)/dt and
    d^2(u, v)/dt^2 against central differences, off centre and seen obliquely."""
    pose = pose_to_radians(torch.tensor([[35.0, -20.0, 60.0, -40.0, 200.0],
                                         [8.0, 70.0, -80.0, 30.0, 450.0]], dtype=torch.float64))
    geom = torch.tensor([[1040.0, 0.3, 4.0, -6.0], [1000.0, 1.0, 0.0, 0.0]], dtype=torch.float64)
    radius = torch.tensor([25.0, 28.0], dtype=torch.float64)
    t = torch.linspace(0.0, 6.0, 13, dtype=torch.float64).expand(2, -1)
    step = 1e-5
    rim, ahead, behind = (_rim(pose, t + d, radius, geom) for d in (0.0, step, -step))
    torch.testing.assert_close(rim.du, (ahead.u - behind.u) / (2 * step), atol=1e-6, rtol=1e-7)
    torch.testing.assert_close(rim.dv, (ahead.v - behind.v) / (2 * step), atol=1e-6, rtol=1e-7)
    torch.testing.assert_close(rim.ddu, (ahead.du - behind.du) / (2 * step), atol=1e-6,
                               rtol=1e-7)
    torch.testing.assert_close(rim.ddv, (ahead.dv - behind.dv) / (2 * step), atol=1e-6,
                               rtol=1e-7)


def test_curvature_offsets_are_half_the_variance_times_the_curvature_clipped_at_sigma():
    """The corrected score's offsets (Kanatani's hyperaccurate correction): -sigma^2 kappa / 2
    with sigma^2 from the distances over N - 5 degrees of freedom (landmarks of weight 0
    uncounted), clipped at one sigma where the rim bends sharply (a thin ellipse's tips)."""
    pose = pose_to_radians(torch.tensor([[4.0, 30.0, 20.0, -10.0, 300.0]], dtype=torch.float64))
    geom = torch.tensor([[1040.0, 1.0, 0.0, 0.0]], dtype=torch.float64)
    radius = torch.tensor([25.0], dtype=torch.float64)
    t = torch.linspace(0.0, 2 * math.pi, 41, dtype=torch.float64)[None, :-1]
    weights = torch.ones(1, 40, dtype=torch.float64)
    weights[0, :4] = 0.0
    dist = torch.full((1, 40), 2.5, dtype=torch.float64)
    variance = 2.5**2 * 36 / 31
    torch.testing.assert_close(_noise_variance(dist, weights), torch.tensor([[variance]],
                                                                             dtype=torch.float64))
    rim = _rim(pose, t, radius, geom)
    n_u, n_v, _ = _normal_jacobian(pose, rim)
    offsets = _curvature_offsets(dist, weights, rim, n_u, n_v)[0]
    # Signed curvature of the projected rim by central differences, towards the left normal
    # (-dv, du), the solver's.
    step = 1e-4
    x = [project_rim(pose, 25.0, Geometry(1040.0, 1.0, 0.0, 0.0), t + d)[0]
         for d in (-step, 0.0, step)]
    first, second = (x[2] - x[0]) / (2 * step), (x[2] - 2 * x[1] + x[0]) / step**2
    speed = first.norm(dim=-1)
    kappa = (first[:, 0] * second[:, 1] - first[:, 1] * second[:, 0]) / speed**3
    expected = (-0.5 * variance * kappa).clamp(-math.sqrt(variance), math.sqrt(variance))
    torch.testing.assert_close(offsets, expected, atol=1e-5, rtol=1e-5)
    assert (expected.abs() == math.sqrt(variance)).any()  # the tips are clipped ...
    assert (expected.abs() < 0.5 * math.sqrt(variance)).any()  # ... the flanks are not


@pytest.mark.parametrize("offset", [0.5, 1.0, 2.0])
def test_newton_steps_find_the_closest_rim_point_off_a_thin_rims_tip(offset):
    """The tip of a rim seen at theta = 3 deg bends on a radius below a pixel: from 0.05-0.3
    rad along the rim, six safeguarded Newton steps reach the closest rim point of a
    landmark ``offset`` px beyond the tip (a dense search's), where Gauss-Newton's steps
    overshoot and settle nowhere."""
    pose = pose_to_radians(torch.tensor([[3.0, 30.0, 20.0, -10.0, 300.0]], dtype=torch.float64))
    geom = torch.tensor([[1040.0, 1.0, 0.0, 0.0]], dtype=torch.float64)
    radius = torch.tensor([25.0], dtype=torch.float64)
    dense = torch.linspace(0, 2 * math.pi, 200_001, dtype=torch.float64)[None]
    rim = _rim(pose, dense, radius, geom)
    tip = dense[:, rim.speed2.argmin()]
    at_tip = _rim(pose, tip[None], radius, geom)
    outwards = torch.stack([-at_tip.dv, at_tip.du], -1) / at_tip.speed2.sqrt()[..., None]
    landmark = torch.stack([at_tip.u, at_tip.v], -1) + offset * outwards  # (1, 1, 2)
    u, v = landmark.unbind(-1)
    closest = ((rim.u - u) ** 2 + (rim.v - v) ** 2).sqrt().min()
    for start in (0.05, 0.1, 0.2, 0.3):
        t = _closest_rim_parameters(pose, tip[None] + start, (u, v), radius, geom, steps=6)
        found = _rim(pose, t, radius, geom)
        assert float(((found.u - u) ** 2 + (found.v - v) ** 2).sqrt()) == pytest.approx(
            float(closest), abs=1e-6)


def test_the_pose_sees_sdd_and_spacing_through_their_ratio_and_the_cup_size_as_a_scale(
        generator):
    """Hand-derived: a pixel ``u`` sees the ray through ``(u - u0) * s`` at the detector, SDD
    ``H`` from the source, so the same landmarks solved with ``H`` and ``s`` both ``c`` times
    larger give a cup of the same angles, ``k``, ``l`` and distance from the source
    ``H - h`` (its rim lies where it did, seen from a source ``c`` times farther from a
    detector with ``c`` times larger pixels); solved for a cup ``c`` times larger, the same
    angles, its centre ``c`` times farther from the source along its ray: ``k``, ``l`` and
    ``H - h`` times ``c``. So no cup size, and no SDD and spacing of the same ratio, can
    move an angle (docs/benchmarks.md, `CupNet with the geometry given wrong`)."""
    truth = paper_poses(200, generator)
    geometry = Geometry(1040.0, 0.4, 700.0, 650.0)
    points = rim_landmarks(truth, geometry)  # a 50 mm cup
    base = solve_pose(points, geometry, 50.0).pose
    distance = geometry.sdd - base[:, 4]
    for c in (1.1, 1.25):  # shorter would put the nearest cups' rims behind the detector
        far = solve_pose(points, Geometry(c * 1040.0, c * 0.4, 700.0, 650.0), 50.0).pose
        torch.testing.assert_close(far[:, :4], base[:, :4], atol=1e-9, rtol=0)
        torch.testing.assert_close(c * 1040.0 - far[:, 4], distance, atol=1e-9, rtol=0)
    for c in (0.9, 1.1):
        larger = solve_pose(points, geometry, c * 50.0).pose
        torch.testing.assert_close(larger[:, :2], base[:, :2], atol=1e-9, rtol=0)
        torch.testing.assert_close(larger[:, 2:4], c * base[:, 2:4], atol=1e-9, rtol=0)
        torch.testing.assert_close(geometry.sdd - larger[:, 4], c * distance, atol=1e-9, rtol=0)


# -- the lower-level functions at their boundary (a researcher's own batches) ---------------
NOISY_CASES = torch.tensor([[30.0, 40.0, 10.0, -5.0, 300.0], [10.0, -60.0, 40.0, 20.0, 450.0]],
                           dtype=torch.float64)


def noisy_rims(generator: torch.Generator, n: int = 32) -> torch.Tensor:
    """Rim landmarks ``(2, n, 2)`` px of :data:`NOISY_CASES` (52 mm cup) with 0.3 px noise."""
    points = rim_landmarks(NOISY_CASES, GEOMETRY, 52.0, n)
    return points + 0.3 * torch.randn(points.shape, generator=generator, dtype=torch.float64)


def test_refine_pose_takes_nan_padding_at_zero_weight_as_solve_pose_does(generator):
    """Padding had poisoned the cost, and the start came back as the refined pose."""
    points = noisy_rims(generator)
    start = pose_to_radians(NOISY_CASES) + torch.tensor([0.02, -0.02, 1.0, 1.0, 5.0],
                                                        dtype=torch.float64)
    alone, _ = refine_pose(start, points[:, :-4], GEOMETRY, 26.0)
    padded = torch.cat([points[:, :-4], torch.full((2, 4, 2), math.nan, dtype=torch.float64)], 1)
    weights = torch.cat([torch.ones(2, 28), torch.zeros(2, 4)], 1).double()
    refined, _ = refine_pose(start, padded, GEOMETRY, 26.0, weights)
    torch.testing.assert_close(refined, alone, rtol=0, atol=1e-9)
    assert (refined - start).abs().max() > 1.0  # it moved: h by about 5 mm
    # Integer landmarks are refined in float64, as solve_pose solves them.
    rounded = points.round().long()
    assert refine_pose(start, rounded, GEOMETRY, 26.0)[0].dtype == torch.float64


@pytest.mark.parametrize(("change", "message"), [
    ({"weights": torch.zeros(2, 32, dtype=torch.float64)}, r"item 0: too few points: 0 < 5"),
    ({"radius": -26.0}, r"item 0: cup radius must be > 0 mm, got -26.0"),
    ({"radius": torch.tensor([26.0, 26.0, 26.0])}, r"radius must be a scalar or one per item"),
    ({"start": torch.zeros(1, 5, dtype=torch.float64)}, r"start must have shape \(2, 5\)"),
    ({"start": torch.tensor([[0.5, 0.7, 0.0, 0.0, 300.0], [math.nan] * 5])},
     r"item 1: start pose is not finite"),
    ({"weights": torch.ones(32, dtype=torch.float64)}, r"weights must have the points' shape"),
])
def test_refine_pose_names_what_it_cannot_refine(generator, change, message):
    arguments = {"start": pose_to_radians(NOISY_CASES), "points": noisy_rims(generator),
                 "geometry": GEOMETRY, "radius": 26.0, **change}
    with pytest.raises(PoseError, match=message):
        refine_pose(**arguments)


def test_poses_from_conic_gives_nan_for_a_conic_that_is_no_ellipse_and_keeps_the_others():
    conic = rim_conic(pose_to_radians(NOISY_CASES[:1]), 26.0, GEOMETRY)
    hyperbola = conic.clone()
    hyperbola[0, 1, 1] *= -1
    imaginary = torch.eye(3, dtype=torch.float64)[None]
    alone = poses_from_conic(conic, GEOMETRY, 26.0)
    for bad in (hyperbola, imaginary, conic * math.nan):
        poses = poses_from_conic(torch.cat([bad, conic]), GEOMETRY, 26.0)
        assert poses[0].isnan().all()
        torch.testing.assert_close(poses[1:], alone, rtol=0, atol=0)
    with pytest.raises(PoseError, match=r"conic must have shape \(B, 3, 3\), got \(3, 3\)"):
        poses_from_conic(conic[0], GEOMETRY, 26.0)
    with pytest.raises(PoseError, match="item 0: cup radius must be > 0 mm, got -26.0"):
        poses_from_conic(conic, GEOMETRY, -26.0)


def test_standard_errors_check_their_batch_and_take_integer_landmarks_in_float64(generator):
    points = noisy_rims(generator)
    sol = solve_pose(points, GEOMETRY, 52.0)
    errors = pose_standard_errors(sol.pose, points, GEOMETRY, 52.0)
    with pytest.raises(PoseError, match=r"pose_deg must have shape \(1, 5\)"):
        pose_standard_errors(sol.pose, points[:1], GEOMETRY, 52.0)
    rounded = points.round().long()
    from_floats = pose_standard_errors(sol.pose, rounded.double(), GEOMETRY, 52.0)
    from_integers = pose_standard_errors(sol.pose, rounded, GEOMETRY, 52.0)
    assert from_integers.dtype == torch.float64 and torch.isfinite(from_integers).all()
    torch.testing.assert_close(from_integers, from_floats, rtol=0, atol=0)
    # An item whose cup size is unusable gets NaN; the other keeps its errors.
    diameters = torch.tensor([-52.0, 52.0], dtype=torch.float64)
    mixed = pose_standard_errors(sol.pose, points, GEOMETRY, diameters)
    assert mixed[0].isnan().all()
    torch.testing.assert_close(mixed[1], errors[1], rtol=0, atol=0)


def test_cramer_rao_bound_scales_with_the_noise_and_refuses_what_bounds_nothing():
    t = torch.arange(16, dtype=torch.float64) * (2 * math.pi / 16)
    pose = pose_to_radians(NOISY_CASES)
    unit = cramer_rao_bound(pose, 26.0, GEOMETRY, t, 1.0)
    torch.testing.assert_close(cramer_rao_bound(pose, 26.0, GEOMETRY, t, 0.5), unit / 2)
    assert (cramer_rao_bound(pose, 26.0, GEOMETRY, t, 0.0) == 0).all()  # noise-free
    beyond_source = pose.clone()
    beyond_source[1, 4] = 1300.0
    for arguments, message in (
            ((pose, 26.0, GEOMETRY, t, -1.0), "sigma_px must be a noise level >= 0 px"),
            ((pose, 26.0, GEOMETRY, t[:4], 1.0), r"t must hold 5 or more rim parameters"),
            ((pose, -26.0, GEOMETRY, t, 1.0), "item 0: cup radius must be > 0 mm"),
            ((beyond_source, 26.0, GEOMETRY, t, 1.0), r"item 1: h = 1300.0 mm lies outside")):
        with pytest.raises(PoseError, match=message):
            cramer_rao_bound(*arguments)
