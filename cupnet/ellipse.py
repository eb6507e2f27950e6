"""Ellipses: conic <-> parameters, a differentiable direct ellipse-specific fit, distances.

Parameters follow CONVENTIONS.md: ``(cx, cy, a, b, alpha)`` with the centre in pixels,
semi-axes ``a >= b`` in pixels and ``alpha`` in ``[0, 180)`` degrees, the angle of the major
axis from +u towards +v. A conic is the symmetric ``(..., 3, 3)`` matrix ``C`` with
``(u, v, 1) C (u, v, 1)^T = 0`` on the curve.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx

from cupnet.batchwise import atan2, matmul, quadratic_form, weighted_scatter
from cupnet.geometry import normalize_conic

MIN_POINTS = 5
# Relative ridge added to the reduced scatter matrix so its Cholesky factor exists when the
# points lie exactly on an ellipse (singular scatter); it moves the solution by ~1e-12.
_RIDGE = 1e-12
# The Rayleigh-quotient polish's shift off an exactly singular pencil, relative to the
# scatter matrix's trace (:class:`_PencilEigenvector`).
_NUDGE = 1e-13
# Smallest ratio of the point cloud's two principal spreads before it counts as a line.
_COLLINEAR_RATIO = 1e-10


class EllipseFitError(ValueError):
    """An ellipse fit that cannot give an ellipse; the message names the cause."""


def coefficients_to_conic(coeffs: Tensor) -> Tensor:
    """``(..., 6)`` coefficients of ``Ax^2 + Bxy + Cy^2 + Dx + Ey + F`` -> ``(..., 3, 3)``."""
    a, b, c, d, e, f = coeffs.unbind(-1)
    rows = [
        torch.stack([a, b / 2, d / 2], -1),
        torch.stack([b / 2, c, e / 2], -1),
        torch.stack([d / 2, e / 2, f], -1),
    ]
    return torch.stack(rows, -2)


def conic_to_params(conic: Tensor) -> Tensor:
    """Ellipse parameters of a conic.

    Args:
        conic: ``(..., 3, 3)`` ellipse conics (any scale and sign).
    Returns:
        ``(..., 5)``: ``(cx, cy, a, b, alpha)`` pixels, pixels, pixels, pixels, degrees.
        Not an ellipse (hyperbola, parabola, imaginary): a row of NaN, whatever else is in
        the batch; :func:`is_ellipse` tells them apart beforehand.
    """
    quad = conic[..., :2, :2]
    lin = conic[..., :2, 2]
    # solve_ex: a parabola's singular quadratic part gives a non-finite centre, where
    # solve raised for the whole batch.
    centre = torch.linalg.solve_ex(quad, -lin.unsqueeze(-1))[0].squeeze(-1)
    # Value of the conic at the centre: the centred form is x^T quad x + f_c = 0.
    f_c = conic[..., 2, 2] + (lin * centre).sum(-1)
    p = quad[..., 0, 0] / -f_c
    r = quad[..., 1, 1] / -f_c
    q = quad[..., 0, 1] / -f_c
    mean = (p + r) / 2
    # Closed-form 2x2 eigenvalues: no eigh, so a circle (equal eigenvalues) stays finite.
    half_gap = torch.sqrt((((p - r) / 2) ** 2 + q**2).clamp_min(1e-300))
    lam_small, lam_big = mean - half_gap, mean + half_gap
    a = torch.rsqrt(lam_small)
    b = torch.rsqrt(lam_big)
    # atan2(2q, p - r) = 2 * (direction of the larger eigenvalue = minor axis); +90 deg -> major.
    alpha = torch.rad2deg(0.5 * atan2(-2 * q, r - p)) % 180.0
    # A tiny negative angle wraps to exactly 180.0 in floating point: keep [0, 180).
    alpha = torch.where(alpha >= 180.0, alpha - 180.0, alpha)
    params = torch.stack([centre[..., 0], centre[..., 1], a, b, alpha], -1)
    # A hyperbola's or imaginary conic's axes are NaN where its centre is finite: no part
    # of such a row is an ellipse's.
    return torch.where(torch.isfinite(params).all(-1, keepdim=True), params, math.nan)


def params_to_conic(params: Tensor) -> Tensor:
    """``(..., 5)`` ``(cx, cy, a, b, alpha_deg)`` -> unit-norm ``(..., 3, 3)`` conic."""
    cx, cy, a, b, alpha = params.unbind(-1)
    ang = torch.deg2rad(alpha)
    c, s = torch.cos(ang), torch.sin(ang)
    ia, ib = 1 / a**2, 1 / b**2
    qa = c * c * ia + s * s * ib
    qb = s * c * (ia - ib)
    qc = s * s * ia + c * c * ib
    qd = -(qa * cx + qb * cy)
    qe = -(qb * cx + qc * cy)
    qf = qa * cx * cx + 2 * qb * cx * cy + qc * cy * cy - 1
    rows = [torch.stack([qa, qb, qd], -1), torch.stack([qb, qc, qe], -1),
            torch.stack([qd, qe, qf], -1)]
    return normalize_conic(torch.stack(rows, -2))


def is_ellipse(conic: Tensor) -> Tensor:
    """``(..., 3, 3)`` -> ``(...)`` bool: a real, non-degenerate ellipse."""
    quad_det = conic[..., 0, 0] * conic[..., 1, 1] - conic[..., 0, 1] ** 2
    det = torch.linalg.det(conic)
    trace = conic[..., 0, 0] + conic[..., 1, 1]
    # Real ellipse: positive-definite quadratic part, and det of opposite sign to the trace.
    return (quad_det > 0) & (det * trace < 0) & torch.isfinite(det)


def ellipse_points(params: Tensor, t: Tensor) -> Tensor:
    """Points on ellipses: ``(..., 5)`` params, ``(N,)`` angles (rad) -> ``(..., N, 2)`` pixels."""
    cx, cy, a, b, alpha = (x[..., None] for x in params.unbind(-1))
    ang = torch.deg2rad(alpha)
    x, y = a * torch.cos(t), b * torch.sin(t)
    return torch.stack([cx + x * torch.cos(ang) - y * torch.sin(ang),
                        cy + x * torch.sin(ang) + y * torch.cos(ang)], -1)


def algebraic_residual(conic: Tensor, points: Tensor) -> Tensor:
    """``p~^T C p~`` for ``(B, 3, 3)`` conics and ``(B, N, 2)`` points -> ``(B, N)``."""
    hom = torch.cat([points, torch.ones_like(points[..., :1])], -1)
    return quadratic_form(hom, conic)


def sampson_distance(conic: Tensor, points: Tensor) -> Tensor:
    """Signed first-order geometric distance of points to conics (pixels).

    Args:
        conic: ``(B, 3, 3)``.
        points: ``(B, N, 2)`` pixels.
    Returns:
        ``(B, N)``: ``p~^T C p~ / (2 |grad|)``, negative inside for conics scaled by
        :func:`cupnet.geometry.normalize_conic`. A first-order distance: close to the true
        one near the curve only (a circle of radius 10 px: -49.5 px at 1 px from its centre,
        -inf with a NaN gradient at the centre itself).
    """
    hom = torch.cat([points, torch.ones_like(points[..., :1])], -1)
    grad = matmul(hom, conic[..., :2, :].transpose(-1, -2))
    value = (grad * points).sum(-1) + (conic[..., None, 2, :] * hom).sum(-1)
    return value / (2 * torch.linalg.vector_norm(grad, dim=-1))


@dataclass
class EllipseFit:
    """Result of :func:`fit_ellipse` for a batch of ``B`` point sets.

    Attributes:
        conic: ``(B, 3, 3)`` unit-norm conics in pixels (the unit circle at the origin,
            ``diag(1, 1, -1) / sqrt(3)``, where invalid).
        params: ``(B, 5)`` ``(cx, cy, a, b, alpha_deg)``; NaN where invalid.
        valid: ``(B,)`` bool.
        status: ``B`` strings, ``"ok"`` or the reason the fit failed.
    """

    conic: Tensor
    params: Tensor
    valid: Tensor
    status: list[str]


def _dot(first: Tensor, second: Tensor) -> Tensor:
    """``x^T y`` of column vectors ``(B, I, 1)`` -> ``(B, 1, 1)``."""
    return (first * second).sum(-2, keepdim=True)


class _PencilEigenvector(torch.autograd.Function):
    """Unit eigenvector ``v`` of the pencil ``S v = lambda C v`` nearest a starting vector,
    by Rayleigh-quotient iteration; backward by the implicit function theorem.

    Differentiating ``S v = lambda C v`` with ``|v| = 1`` gives the bordered system
    ``[[S - lambda C, v], [v^T, 0]] (dv, 0) = (-(dS - dlambda C) v, 0)``, with
    ``dlambda = v^T dS v / v^T C v``. The bordered matrix is symmetric and well conditioned
    where ``lambda`` is simple, unlike the near-singular ``S - lambda C`` the iteration
    solves, whose own backward would lose most digits at convergence.
    """

    @staticmethod
    def forward(ctx: FunctionCtx, scatter: Tensor, constraint: Tensor,  # type: ignore[override]
                vec: Tensor, steps: int) -> Tensor:
        # A hair of the scatter's size: a shift that far off the eigenvalue still gives
        # the eigenvector's direction to ~1e-13.
        nudge = _NUDGE * scatter.diagonal(dim1=-2, dim2=-1).abs().sum(-1)[:, None, None]
        for _ in range(steps):
            c_vec = matmul(constraint, vec)
            rayleigh = _dot(vec, matmul(scatter, vec)) / _dot(vec, c_vec)
            step, info = torch.linalg.solve_ex(scatter - rayleigh * constraint, c_vec)
            # An exactly singular pencil: the quotient is the eigenvalue to the last digit,
            # but the vector may still be ~1e-11 off its eigenvector (it kept the ridged
            # start, and the fit jumped by that between neighbouring inputs): solved again
            # with the shift nudged off the eigenvalue.
            off, off_info = torch.linalg.solve_ex(scatter - (rayleigh + nudge) * constraint,
                                                  c_vec)
            singular = info != 0
            step = torch.where(singular[:, None, None], off, step)
            info = torch.where(singular, off_info, info)
            step = step / torch.linalg.vector_norm(step, dim=-2, keepdim=True)
            usable = (info == 0)[:, None, None] & torch.isfinite(step).all(-2, keepdim=True)
            vec = torch.where(usable, step, vec)
        ctx.save_for_backward(scatter, constraint, vec)
        return vec

    @staticmethod
    def backward(ctx: FunctionCtx, grad_vec: Tensor  # type: ignore[override]
                 ) -> tuple[Tensor, None, None, None]:
        scatter, constraint, vec = ctx.saved_tensors
        vt = vec.transpose(-1, -2)
        c_vec = matmul(constraint, vec)
        rayleigh = _dot(vec, matmul(scatter, vec)) / _dot(vec, c_vec)
        bordered = torch.cat([torch.cat([scatter - rayleigh * constraint, vec], -1),
                              torch.cat([vt, torch.zeros_like(vt[..., :1])], -1)], -2)
        rhs = torch.cat([grad_vec, torch.zeros_like(grad_vec[..., :1, :])], -2)
        z = torch.linalg.solve(bordered, rhs)[..., :3, :]
        along = _dot(z, c_vec) / _dot(vec, c_vec)
        return -matmul(z, vt) + along * matmul(vec, vt), None, None, None


def landmark_batch(points: Tensor, weights: Tensor | None, on_error: str,
                   error: type[ValueError] = EllipseFitError
                   ) -> tuple[Tensor, Tensor, torch.dtype]:
    """Landmarks as the fit and the pose solver take them, checked at their boundary.

    CONVENTIONS.md fits and solves in float64: in float32 the scatter matrix of accurate
    landmarks is singular to working precision, and its Cholesky factor fails.

    Args:
        points: ``(B, N, 2)`` or ``(N, 2)`` pixels, any real dtype.
        weights: ``(B, N)`` or ``(N,)`` (as ``points``), or None (ones).
        on_error: ``"raise"`` or ``"flag"``; error: the exception a bad argument raises.
    Returns:
        ``(B, N, 2)`` float64 points, ``(B, N)`` float64 weights, and the dtype results are
        given back in (the points' floating dtype, float64 for integer points). Non-finite
        coordinates of zero-weight landmarks (the NaN padding of ragged sets) become 0, so
        they drop out of every sum; finite ones stay where they are, so that a weight's
        gradient at 0 is taken at its own landmark.
    """
    if on_error not in ("raise", "flag"):
        raise error(f"on_error must be 'raise' or 'flag', got {on_error!r}")
    if points.ndim == 2:
        points = points[None]
        weights = None if weights is None else weights[None]
    if points.ndim != 3 or points.shape[-1] != 2:
        raise error(f"points must have shape (B, N, 2) or (N, 2), got {tuple(points.shape)}")
    if points.is_complex() or points.dtype == torch.bool:
        raise error(f"points must be real pixel coordinates, got dtype {points.dtype}")
    dtype = points.dtype if points.is_floating_point() else torch.float64
    points = points.to(torch.float64)
    if weights is None:
        weights = torch.ones(points.shape[:2], dtype=torch.float64, device=points.device)
    elif weights.shape != points.shape[:2]:
        raise error(f"weights must have the points' shape {tuple(points.shape[:2])} "
                    f"(one per landmark), got {tuple(weights.shape)}")
    weights = weights.to(torch.float64)
    padding = (weights == 0)[..., None] & ~torch.isfinite(points)
    points = torch.where(padding, torch.zeros_like(points), points)
    return points, weights, dtype


def _distinct_counts(points: Tensor, active: Tensor) -> Tensor:
    """``(B,)`` number of distinct points among the active ones of ``(B, N, 2)`` ``points``
    (``active``: ``(B, N)`` bool, finite there), by sorting each set lexicographically."""
    inactive = torch.full_like(points[..., 0], math.inf)
    u = torch.where(active, points[..., 0], inactive)
    v = torch.where(active, points[..., 1], inactive)
    # Stable sorts, the last key first: (u, v) order.
    order = torch.sort(v, dim=-1, stable=True).indices
    u, v = u.gather(-1, order), v.gather(-1, order)
    order = torch.sort(u, dim=-1, stable=True).indices
    u, v = u.gather(-1, order), v.gather(-1, order)
    first = torch.ones_like(u[:, :1], dtype=torch.bool)
    new = torch.cat([first, (u[:, 1:] != u[:, :-1]) | (v[:, 1:] != v[:, :-1])], -1)
    return (new & torch.isfinite(u)).sum(-1)


def landmark_problems(points: Tensor, weights: Tensor) -> list[str]:
    """Per-item reason the landmarks determine no ellipse, nor so a pose ('ok' where they
    do). points (B,N,2), weights (B,N), as :func:`landmark_batch` gives them."""
    active = weights > 0
    finite = torch.isfinite(points).all(-1)
    counts = active.sum(-1)
    bad_value = ((active & ~finite).any(-1) | ~torch.isfinite(weights).all(-1)
                 | (weights < 0).any(-1))
    # Spread of the active points: a line (or one point) has a vanishing minor spread.
    w = torch.where(active & finite, weights, torch.zeros_like(weights))
    p = torch.where((active & finite)[..., None], points, torch.zeros_like(points))
    total = w.sum(-1).clamp_min(1e-300)
    mean = (w[..., None] * p).sum(-2) / total[..., None]
    d = p - mean[:, None]
    cov = weighted_scatter(w, d, d) / total[:, None, None]
    evals = torch.linalg.eigvalsh(cov)
    flat = evals[:, 0] <= _COLLINEAR_RATIO * evals[:, 1].clamp_min(1e-300)
    # Repeated landmarks add weight, not constraints: 6 landmarks on 4 distinct points leave
    # a family of ellipses through them.
    distinct = _distinct_counts(points, active & finite)
    reasons = []
    # Python lists: indexing tensors element by element costs more than the fit itself.
    for bad, count, unique, line in zip(bad_value.tolist(), counts.tolist(), distinct.tolist(),
                                        flat.tolist(), strict=True):
        if bad:
            reasons.append("non-finite or negative landmark coordinates or weights")
        elif count < MIN_POINTS:
            reasons.append(f"too few points: {count} < {MIN_POINTS}")
        elif line:
            reasons.append("points are collinear or coincide")
        elif unique < MIN_POINTS:
            reasons.append(f"too few distinct points: {unique} < {MIN_POINTS} "
                           f"({count} landmarks)")
        else:
            reasons.append("ok")
    return reasons


def fit_ellipse(
    points: Tensor,
    weights: Tensor | None = None,
    *,
    on_error: Literal["raise", "flag"] = "raise",
) -> EllipseFit:
    """Direct least-squares ellipse-specific fit (Fitzgibbon 1999, Halir-Flusser 1998 form).

    Minimises the weighted algebraic distance ``sum_i w_i (x_i^T a)^2`` subject to the ellipse
    constraint ``4AC - B^2 = 1``, on points normalised to zero weighted mean and unit RMS
    spread (the fit is similarity-covariant, so this changes only the conditioning). The
    constrained problem is solved as a symmetric eigenproblem
    ``L^-1 C1 L^-T`` (``L`` the Cholesky factor of the slightly ridged reduced scatter
    matrix), whose single positive eigenvalue gives the ellipse; Rayleigh-quotient steps then
    remove the ridge's bias. The fit is differentiable with respect to the points and the
    weights through the exact eigenvector (implicit function theorem).

    Args:
        points: ``(B, N, 2)`` or ``(N, 2)`` pixels (fitted in float64, CONVENTIONS.md).
        weights: ``(B, N)`` or ``(N,)`` non-negative; zero drops a point (ragged sets, whose
            padding may be NaN).
        on_error: ``"raise"`` raises :class:`EllipseFitError` naming the first bad item;
            ``"flag"`` returns ``valid=False`` and the reason in ``status`` instead.
    Returns:
        :class:`EllipseFit` (batched even for an unbatched input) in the points' floating
        dtype (float64 for integer points).
    """
    points, weights, out_dtype = landmark_batch(points, weights, on_error)
    status = landmark_problems(points.detach(), weights.detach())
    bad = [i for i, s in enumerate(status) if s != "ok"]
    if bad and on_error == "raise":
        raise EllipseFitError(f"ellipse fit of item {bad[0]}: {status[bad[0]]}")
    valid = torch.tensor([s == "ok" for s in status], dtype=torch.bool, device=points.device)

    # Invalid items get unit weights and zero points, and below identity blocks in place of
    # their (singular) scatter matrices, so the batch stays finite; their results are masked.
    if bad:
        points = torch.where(valid[:, None, None], points, torch.zeros_like(points))
        weights = torch.where(valid[:, None], weights, torch.ones_like(weights))

    w = weights / weights.sum(-1, keepdim=True)
    mean = (w[..., None] * points).sum(-2)
    centred = points - mean[:, None]
    scale = torch.sqrt((w * (centred**2).sum(-1)).sum(-1) / 2)
    x, y = (centred / scale[:, None, None]).unbind(-1)
    quad = torch.stack([x * x, x * y, y * y], -1)
    lin = torch.stack([x, y, torch.ones_like(x)], -1)
    s1 = weighted_scatter(w, quad, quad)
    s2 = weighted_scatter(w, quad, lin)
    s3 = weighted_scatter(w, lin, lin)
    eye = torch.eye(3, dtype=points.dtype, device=points.device)
    s3 = torch.where(valid[:, None, None], s3, eye)
    lin_from_quad = -torch.linalg.solve(s3, s2.transpose(-1, -2))  # (B, 3, 3)
    reduced = s1 + matmul(s2, lin_from_quad)
    reduced = torch.where(valid[:, None, None], 0.5 * (reduced + reduced.transpose(-1, -2)), eye)
    constraint = torch.tensor([[0.0, 0.0, 2.0], [0.0, -1.0, 0.0], [2.0, 0.0, 0.0]],
                              dtype=points.dtype, device=points.device)
    # The ridged problem only starts the polish below (gradients come from the exact
    # eigenvector there), so it is solved without a graph.
    with torch.no_grad():
        trace = reduced.diagonal(dim1=-2, dim2=-1).sum(-1)
        chol, info = torch.linalg.cholesky_ex(reduced + (_RIDGE * trace)[:, None, None] * eye)
        # Not expected after the checks above; flagged, not raised, so one item cannot end
        # the batch.
        singular = info != 0
        if singular.any():
            for i in singular.nonzero()[:, 0].tolist():
                status[i] = "scatter matrix is singular (points too few or degenerate)"
            valid = valid & ~singular
            reduced = torch.where(valid[:, None, None], reduced, eye)
            chol = torch.where(valid[:, None, None], chol, eye)
        half = torch.linalg.solve_triangular(chol, constraint.expand_as(chol), upper=False)
        sym = torch.linalg.solve_triangular(chol, half.transpose(-1, -2), upper=False)
        sym = 0.5 * (sym + sym.transpose(-1, -2))
        _, vecs = torch.linalg.eigh(sym)
        top = vecs[..., -1:]  # the single positive eigenvalue is the largest
        quad_coef = torch.linalg.solve_triangular(chol.transpose(-1, -2), top, upper=True)
    if valid.any():  # polishing a stand-in block could meet an exactly singular system
        # Rayleigh-quotient polish removes the ridge's bias, so points exactly on an
        # ellipse give it to machine precision.
        polished = _PencilEigenvector.apply(reduced[valid], constraint, quad_coef[valid], 3)
        quad_coef = quad_coef.clone()
        quad_coef[valid] = polished
    lin_coef = matmul(lin_from_quad, quad_coef)
    coeffs = torch.cat([quad_coef, lin_coef], -2).squeeze(-1)
    conic_norm = coefficients_to_conic(coeffs)
    # Back to pixels: x_n = (p - mean) / scale, i.e. (x_n, 1) = N (p, 1).
    zero, one = torch.zeros_like(scale), torch.ones_like(scale)
    to_norm = torch.stack([
        torch.stack([1 / scale, zero, -mean[:, 0] / scale], -1),
        torch.stack([zero, 1 / scale, -mean[:, 1] / scale], -1),
        torch.stack([zero, zero, one], -1)], -2)
    conic = normalize_conic(matmul(matmul(to_norm.transpose(-1, -2), conic_norm), to_norm))

    # One copy from the device, not one per item.
    for i, ellipse in enumerate(is_ellipse(conic).detach().tolist()):
        if status[i] == "ok" and not ellipse:
            status[i] = "fit is not an ellipse (degenerate conic)"
    valid = torch.tensor([s == "ok" for s in status], dtype=torch.bool, device=points.device)
    if not valid.all() and on_error == "raise":
        first = int((~valid).nonzero()[0])
        raise EllipseFitError(f"ellipse fit of item {first}: {status[first]}")
    # Parameters from the normalised conic (well conditioned), then back to pixels.
    params_norm = conic_to_params(conic_norm)
    params = torch.cat([mean + scale[:, None] * params_norm[:, :2],
                        scale[:, None] * params_norm[:, 2:4], params_norm[:, 4:]], -1)
    params = torch.where(valid[:, None], params, torch.full_like(params, math.nan))
    # An invalid item's stand-in points all lie at 0 (no spread), so its conic is NaN.
    placeholder = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=conic.dtype,
                                          device=conic.device)) / math.sqrt(3.0)
    conic = torch.where(valid[:, None, None], conic, placeholder)
    return EllipseFit(conic=conic.to(out_dtype), params=params.to(out_dtype), valid=valid,
                      status=status)
