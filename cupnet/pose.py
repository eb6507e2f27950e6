"""Cup pose from rim landmarks under cone-beam geometry.

Pipeline of :func:`solve_pose`:

1. weighted direct ellipse fit of the landmarks (:func:`cupnet.ellipse.fit_ellipse`);
2. closed form (:func:`poses_from_conic`): the cone from the X-ray source through the ellipse
   is cut by the two planes that give a circle of the cup's radius (Safaee-Rad et al. 1992,
   Chen et al. 2004), both candidate poses returned;
3. maximum-likelihood refinement (:func:`refine_pose`): batched Levenberg-Marquardt
   orthogonal-distance regression of the projected rim, each landmark's position along the
   rim estimated with the pose (no correspondence needed), with a curvature correction of
   the score that removes its second-order bias on thin ellipses; differentiable by the
   implicit function theorem at the solution;
4. the candidate inside the CONVENTIONS ranges is chosen (:func:`canonical_pose`), and the
   result flagged ``ambiguous`` when the other candidate is in range too.

Poses inside this module are ``(..., 5)`` ``(theta, phi, k, l, h)`` with the angles in
radians; :class:`PoseSolution` carries public units (degrees, mm).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx
from torch.func import jacfwd, vmap

from cupnet.batchwise import atan2, hypot, matmul
from cupnet.ellipse import (
    conic_to_params,
    fit_ellipse,
    is_ellipse,
    landmark_batch,
    landmark_problems,
)
from cupnet.geometry import (
    Geometry,
    camera_matrix,
    cup_axis,
    pose_to_degrees,
    pose_to_radians,
    project_rim,
    rim_conic,
    rotation,
    source_position,
)
from cupnet.outline import outline_distances

HALF_PI = math.pi / 2
# Smallest semi-major axis (pixels) from which a pose is attempted. The semi-minor axis may
# be far below a pixel: a rim seen almost edge-on (theta near 0) is still a valid pose.
MIN_AXIS_PX = 2.0
# Rim radius (mm) of the stand-in cup unusable batch items are solved on, so that the batch
# stays finite; their results are masked.
_STAND_IN_RADIUS_MM = 25.0


class PoseError(ValueError):
    """A pose that cannot be solved; the message names the cause."""


@dataclass
class PoseSolution:
    """Batched solver output, public units.

    Attributes:
        pose: ``(B, 5)`` (theta_deg, phi_deg, k_mm, l_mm, h_mm); NaN where not valid.
        alt_pose: ``(B, 5)`` second in-range pose where ``ambiguous``, else NaN.
        ambiguous: ``(B,)`` bool.
        ellipse: ``(B, 5)`` fitted ellipse (cx, cy, a, b, alpha_deg) px.
        residual_px: ``(B,)`` weighted RMS distance of the landmarks to the solved rim
            (:func:`rim_distances`, to each landmark's closest rim point).
        valid: ``(B,)`` bool.
        status: ``"ok"``, ``"ambiguous"`` or ``"error: <reason>"`` per item.
        converged: ``(B,)`` bool, the refinement of ``pose`` met its stopping test (True
            without refinement, False where not valid). The gradient through ``pose`` is
            that of the solution the refinement stops at: close where it converged (a
            long last step along a flat valley can still leave it some way off), and where
            it stopped short, at ``max_iter``, it can be far off, even in sign: a nearly
            edge-on rim (theta under about 10 deg) leaves ``h`` along a flat valley that ten
            steps may not cross. Leave such items out of a loss: more steps reach the
            maximum-likelihood ``h``, which on such rims lies far along the valley, farther
            from the truth on average (docs/training.md, item 78).
    """

    pose: Tensor
    alt_pose: Tensor
    ambiguous: Tensor
    ellipse: Tensor
    residual_px: Tensor
    valid: Tensor
    status: list[str]
    converged: Tensor


def _batch_geometry(geometry: Geometry, batch: int, dtype: torch.dtype,
                    device: torch.device) -> Tensor:
    """``(B, 4)`` rows (sdd, spacing, u0, v0)."""
    fields = [t.expand(batch) if t.ndim == 0 else t for t in geometry.tensors(dtype, device)]
    return torch.stack(fields, -1)


def check_geometry_batch(geometry: Geometry, batch: int) -> None:
    """A PoseError (a ValueError) naming a geometry field of other than one value or one per
    item of a batch of ``batch``."""
    for name, t in zip(("sdd", "pixel_spacing", "principal_u", "principal_v"),
                       geometry.tensors(), strict=True):
        if t.ndim > 1 or (t.ndim == 1 and t.shape[0] != batch):
            raise PoseError(f"geometry {name} must be a scalar or one per item ({batch}), got "
                            f"shape {tuple(t.shape)}")


def _per_item(value: Tensor | float, name: str, batch: int, dtype: torch.dtype,
              device: torch.device) -> Tensor:
    """``value``, a scalar or one per item, as ``(B,)``; a PoseError naming ``name`` where it
    is neither."""
    value = torch.as_tensor(value, dtype=dtype, device=device)
    if value.numel() not in (1, batch):
        raise PoseError(f"{name} must be a scalar or one per item ({batch}), got "
                        f"{value.numel()} values")
    return value.reshape(-1).expand(batch)


def geometry_problems(geometry: Geometry, radius: Tensor) -> list[str | None]:
    """Per-item reason a geometry / radius is unusable (None where fine).

    Args:
        geometry: batch fields ``(B,)`` or scalars.
        radius: ``(B,)`` mm.
    """
    rows = _batch_geometry(geometry, radius.shape[0], torch.float64, radius.device)
    out: list[str | None] = []
    for (sdd, spacing, u0, v0), r in zip(rows.tolist(), radius.tolist(), strict=True):
        if not math.isfinite(sdd) or sdd <= 0:
            out.append(f"source-to-detector distance must be finite and > 0 mm, got {sdd}")
        elif not math.isfinite(spacing) or spacing <= 0:
            out.append(f"pixel spacing must be finite and > 0 mm/px, got {spacing}")
        elif not (math.isfinite(u0) and math.isfinite(v0)):
            out.append("principal point is not finite")
        elif not math.isfinite(r) or r <= 0:
            out.append(f"cup radius must be > 0 mm, got {r}")
        else:
            out.append(None)
    return out


def poses_from_conic(conic: Tensor, geometry: Geometry, radius: Tensor | float) -> Tensor:
    """Both circle poses whose projected rim is the given image ellipse (closed form):
    :func:`_circle_poses` on checked input.

    Args:
        conic: ``(B, 3, 3)`` conics in pixels; an item that is no real ellipse (a hyperbola,
            an imaginary or degenerate conic, NaN) gets NaN poses, whatever else is in the
            batch.
        geometry: batch fields ``(B,)`` or scalars.
        radius: cup radius, mm, scalar or ``(B,)``.
    Returns:
        ``(B, 2, 5)`` poses (rad, mm), as :func:`_circle_poses` gives them.
    Raises:
        PoseError: a conic batch of another shape, or a geometry or radius that is unusable
        (naming the first such item).
    """
    if conic.ndim != 3 or conic.shape[-2:] != (3, 3):
        raise PoseError(f"conic must have shape (B, 3, 3), got {tuple(conic.shape)}")
    batch, dtype, device = conic.shape[0], conic.dtype, conic.device
    radius = _per_item(radius, "radius", batch, dtype, device)
    check_geometry_batch(geometry, batch)
    _raise_first_problem(geometry_problems(geometry, radius.detach()))
    usable = is_ellipse(conic.detach())
    # Unusable items are solved on a stand-in (one NaN conic fails eigh for the whole batch).
    safe_conic = torch.where(usable[:, None, None], conic,
                             _stand_in_conic(geometry, dtype, device))
    poses = _circle_poses(safe_conic, geometry, radius)
    return torch.where(usable[:, None, None], poses, torch.full_like(poses, math.nan))


def _circle_poses(conic: Tensor, geometry: Geometry, radius: Tensor | float) -> Tensor:
    """Both circle poses whose projected rim is the given image ellipse (closed form).

    The cone ``Q = A^T C A`` (``A`` from :func:`cupnet.geometry.camera_matrix`) has one
    eigenvalue of one sign and two of the other; in its eigenframe, with
    ``l1 >= l2 > 0 > l3``, the planes cutting it in circles have the normals
    ``(+-sqrt((l1 - l2) / (l1 - l3)), 0, sqrt((l2 - l3) / (l1 - l3)))``. Each plane is
    scaled so the circle's radius is the cup's, on the nappe in front of the source.

    Args:
        conic: ``(B, 3, 3)`` ellipse conics in pixels.
        geometry: batch fields ``(B,)`` or scalars.
        radius: cup radius, mm, scalar or ``(B,)``.
    Returns:
        ``(B, 2, 5)`` poses (rad, mm). Their (theta, phi) are the raw angles of the rim
        normal oriented towards the source (theta >= 0); :func:`canonical_pose` maps them
        into the CONVENTIONS ranges.

    Differentiable through ``eigh`` except where two eigenvalues coincide: a circle's
    exact image seen face-on on the central ray (theta = 90 deg, phi undefined), whose
    gradient is NaN. Landmarks with any noise lie off it; :func:`solve_pose`'s default
    (``refine=True``) takes its gradient from the refinement, finite there too.
    """
    dtype, device = conic.dtype, conic.device
    radius = torch.as_tensor(radius, dtype=dtype, device=device).expand(conic.shape[0])
    cam = camera_matrix(geometry, dtype, device).expand(conic.shape[0], 3, 3)
    cone = matmul(matmul(cam.transpose(-1, -2), conic), cam)
    cone = 0.5 * (cone + cone.transpose(-1, -2))
    cone = cone / torch.linalg.matrix_norm(cone)[:, None, None]
    evals, evecs = torch.linalg.eigh(cone)
    # Make exactly one eigenvalue negative: an ellipse's cone has signature (2, 1) or (1, 2).
    flip = (evals[:, 1] < 0)[:, None]
    evals = torch.where(flip, -evals.flip(-1), evals)
    evecs = torch.where(flip[..., None], evecs.flip(-1), evecs)
    l3, l2, l1 = evals.unbind(-1)  # l3 < 0 < l2 <= l1
    # Eigenframe axes ordered (x, y, z) = (l1, l2, l3) eigenvectors.
    frame = torch.stack([evecs[..., 2], evecs[..., 1], evecs[..., 0]], -1)
    span = l1 - l3
    nx = torch.sqrt(((l1 - l2) / span).clamp_min(0))
    nz = torch.sqrt(((l2 - l3) / span).clamp_min(0))
    diag = torch.stack([l1, l2, l3], -1)
    sources = source_position(geometry, dtype, device).expand(conic.shape[0], 3)
    poses = []
    for sign in (1.0, -1.0):
        n = torch.stack([sign * nx, torch.zeros_like(nx), nz], -1)
        e1 = torch.stack([nz, torch.zeros_like(nx), -sign * nx], -1)
        e2 = torch.zeros_like(n)
        e2[:, 1] = 1.0
        basis = torch.stack([e1, e2, n], -1)  # columns; plane n.X = 1 in eigenframe
        slice_ = matmul(basis.transpose(-1, -2) * diag[:, None], basis)
        quad = 0.5 * (slice_[:, 0, 0] + slice_[:, 1, 1])
        centre_2d = -slice_[:, :2, 2] / quad[:, None]
        f0 = slice_[:, 2, 2] + (slice_[:, :2, 2] * centre_2d).sum(-1)
        unit_radius = torch.sqrt((-f0 / quad).clamp_min(1e-300))
        depth = radius / unit_radius
        centre_eig = depth[:, None] * (n + centre_2d[:, :1] * e1 + centre_2d[:, 1:] * e2)
        centre_rel = (frame * centre_eig[:, None]).sum(-1)
        normal = (frame * n[:, None]).sum(-1)
        # The cone's two nappes: the cup lies between source and detector (z_rel < 0).
        front = torch.where(centre_rel[:, 2] > 0, -1.0, 1.0).to(dtype)[:, None]
        centre = sources + front * centre_rel
        normal = torch.where(normal[:, 2:] < 0, -normal, normal)
        theta = atan2(normal[:, 2], torch.linalg.vector_norm(normal[:, :2], dim=-1))
        phi = atan2(-normal[:, 0], normal[:, 1])
        poses.append(torch.cat([theta[:, None], phi[:, None], centre], -1))
    return torch.stack(poses, 1)


def range_violation(pose: Tensor) -> Tensor:
    """How far (rad) a pose's rim circle is from any CONVENTIONS-range description.

    A rim circle with unoriented normal ``m`` is described in range by theta in [0, 90] and
    phi in (-90, 90] iff ``m_y m_z >= 0``. Otherwise the smallest change that brings it in
    range is either moving phi to +-90 or theta to 0.

    Args:
        pose: ``(..., 5)`` rad / mm.
    Returns:
        ``(...)`` rad, 0 in range.
    """
    theta, phi = _oriented_angles(pose)
    return torch.where(phi.abs() <= HALF_PI, torch.zeros_like(phi),
                       torch.minimum(phi.abs() - HALF_PI, theta))


def _oriented_angles(pose: Tensor) -> tuple[Tensor, Tensor]:
    """(theta in [0, pi/2], phi in (-pi, pi]) of the rim normal oriented towards the source."""
    n = cup_axis(pose)
    n = torch.where(n[..., 2:] < 0, -n, n)
    theta = atan2(n[..., 2], torch.linalg.vector_norm(n[..., :2], dim=-1))
    return theta, atan2(-n[..., 0], n[..., 1])


def canonical_pose(pose: Tensor) -> Tensor:
    """The CONVENTIONS-range description of the same rim circle, clamped where none exists.

    Args:
        pose: ``(..., 5)`` rad / mm, any angles.
    Returns:
        ``(..., 5)`` with theta in [0, pi/2], phi in [-pi/2, pi/2]. A circle with no in-range
        description (only from noise, see :func:`range_violation`) is moved to the nearest
        boundary: phi clamped to +-90 deg or theta to 0.
    """
    theta, phi = _oriented_angles(pose)
    out_of_range = phi.abs() > HALF_PI
    clamp_phi = out_of_range & (phi.abs() - HALF_PI <= theta)
    flip = out_of_range & ~clamp_phi
    phi = torch.where(clamp_phi, torch.sign(phi) * HALF_PI, phi)
    phi = torch.where(flip, phi - torch.sign(phi) * math.pi, phi)
    theta = torch.where(flip, torch.zeros_like(theta), theta)
    return torch.cat([theta[..., None], phi[..., None], pose[..., 2:]], -1)


class _Rim(NamedTuple):
    """Projected rim points and what the solver's derivatives need, one ``(B, N)`` tensor
    per component (contiguous components keep the inner loop's elementwise work cheap)."""

    u: Tensor  # px
    v: Tensor
    du: Tensor  # d (u, v) / d t, px per rad
    dv: Tensor
    speed2: Tensor  # du^2 + dv^2
    ddu: Tensor  # d^2 (u, v) / d t^2, px per rad^2
    ddv: Tensor
    focal: Tensor  # sdd / spacing / depth, px per mm
    lat_x: Tensor  # X / depth, Y / depth
    lat_y: Tensor
    rc: Tensor  # r cos t, r sin t, mm
    rs: Tensor


def _pose_axes(pose: Tensor) -> tuple[Tensor, ...]:
    """``(cos theta, sin theta, cos phi, sin phi)``, each ``(B, 1)``."""
    angles = pose[:, :2, None]
    cos, sin = torch.cos(angles), torch.sin(angles)
    return cos[:, 0], sin[:, 0], cos[:, 1], sin[:, 1]


def _rim(pose: Tensor, t: Tensor, radius: Tensor, geom: Tensor) -> _Rim:
    """Projected rim points and their derivative along the rim (the solver's inner loop).

    With ``e1 = R[:, 0] = (cos phi, sin phi, 0)`` and
    ``e3 = R[:, 2] = (sin phi sin theta, -cos phi sin theta, cos theta)``, a rim point is
    ``X = c + r cos t e1 + r sin t e3``; its pixel position is
    ``x = (u0, v0) + f X_xy / (sdd - X_z)``, ``f = sdd / spacing``, so a change ``dX`` of
    the rim point moves it by ``focal (dX_xy + lateral dX_z)`` pixels.

    Args:
        pose: ``(B, 5)`` rad / mm; t: ``(B, N)`` rim parameters; radius: ``(B,)`` mm;
        geom: ``(B, 4)`` (sdd, spacing, u0, v0).
    """
    ct, st, cp, sp = _pose_axes(pose)
    rc = radius[:, None] * torch.cos(t)
    rs = radius[:, None] * torch.sin(t)
    sdd, spacing, u0, v0 = (g[:, None] for g in geom.unbind(-1))
    x = pose[:, 2:3] + cp * rc + (sp * st) * rs
    y = pose[:, 3:4] + sp * rc - (cp * st) * rs
    depth = (sdd - pose[:, 4:5]) - ct * rs
    focal = (sdd / spacing) / depth
    lat_x, lat_y = x / depth, y / depth
    dz = ct * rc  # d X / d t = rc e3 - rs e1
    du = focal * ((sp * st) * rc - cp * rs + lat_x * dz)
    dv = focal * (sp * -rs - (cp * st) * rc + lat_y * dz)
    # d^2 X / d t^2 = -(X - c), and d/dt of (focal, lateral) gives the 2 x' X_z' / depth term.
    bend = 2 * dz / depth
    ddu = focal * (-(x - pose[:, 2:3]) - lat_x * (ct * rs)) + bend * du
    ddv = focal * (-(y - pose[:, 3:4]) - lat_y * (ct * rs)) + bend * dv
    return _Rim(u0 + focal * x, v0 + focal * y, du, dv, du**2 + dv**2, ddu, ddv, focal, lat_x,
                lat_y, rc, rs)


def _closest_rim_parameters(pose: Tensor, t: Tensor, points: tuple[Tensor, Tensor],
                            radius: Tensor, geom: Tensor, steps: int = 1) -> Tensor:
    """``steps`` safeguarded Newton steps of each landmark's rim parameter towards its
    closest rim point. Newton, not Gauss-Newton: near the tips of a thin ellipse the rim's
    radius of curvature falls below the landmark noise, where Gauss-Newton steps overshoot.

    Args: pose ``(B, 5)``, t ``(B, N)``, points ``(u, v)`` px, each ``(B, N)``, radius
    ``(B,)``, geom ``(B, 4)``.
    Returns: the new ``t``, ``(B, N)``.
    """
    for _ in range(steps):
        rim = _rim(pose, t, radius, geom)
        off_u, off_v = points[0] - rim.u, points[1] - rim.v
        # Half the Hessian of |x - rim(t)|^2 / 2; floored where the landmark lies beyond the
        # centre of curvature (there the closest point is far and a bounded step is safer).
        hessian = torch.maximum(rim.speed2 - (off_u * rim.ddu + off_v * rim.ddv),
                                0.25 * rim.speed2)
        step = (off_u * rim.du + off_v * rim.dv) / hessian.clamp_min(1e-30)
        t = t + step.clamp(-0.5, 0.5)
    return t


def _normal_jacobian(pose: Tensor, rim: _Rim) -> tuple[Tensor, Tensor, Tensor]:
    """Unit normals of the projected rim and the pose Jacobian of the rim along them.

    At a landmark's closest rim point the distance changes only through the rim's normal
    motion (its tangential motion is absorbed by ``t``), so the profile Jacobian is
    ``n^T d x / d pose`` and never needs the ``(B, N, 2, 5)`` full Jacobian.

    Returns: normal components ``(B, N)`` each and ``(B, N, 5)`` px per
    (rad, rad, mm, mm, mm).
    """
    ct, st, cp, sp = _pose_axes(pose)
    norm = torch.sqrt(rim.speed2).clamp_min(1e-300)
    n_u, n_v = -rim.dv / norm, rim.du / norm
    # n^T d x / d X for a rim point X.
    pull_x, pull_y = rim.focal * n_u, rim.focal * n_v
    pull_z = pull_x * rim.lat_x + pull_y * rim.lat_y
    d_theta = rim.rs * ((sp * ct) * pull_x - (cp * ct) * pull_y - st * pull_z)  # rs de3/dtheta
    d_phi = rim.rc * (cp * pull_y - sp * pull_x) + rim.rs * st * (cp * pull_x + sp * pull_y)
    return n_u, n_v, torch.stack([d_theta, d_phi, pull_x, pull_y, pull_z], -1)


def _initial_rim_parameters(pose: Tensor, points: Tensor, radius: Tensor, geom: Tensor) -> Tensor:
    """Rim parameter of each landmark: its position on the rim plane through the pose's
    homography, ``t = atan2(beta, alpha)``. Exact for landmarks on the projected rim.

    Args: pose ``(B, 5)``, points ``(B, N, 2)`` px, radius ``(B,)``, geom ``(B, 4)``.
    Returns: ``(B, N)`` rad.
    """
    geometry = Geometry.from_rows(geom)
    rot = rotation(pose[:, 0], pose[:, 1])
    cam = camera_matrix(geometry, pose.dtype, pose.device)
    centre = pose[:, 2:5] - source_position(geometry, pose.dtype, pose.device)
    homography = matmul(cam, torch.stack([rot[..., 0], rot[..., 2], centre], -1))
    hom = torch.cat([points, torch.ones_like(points[..., :1])], -1)
    plane = matmul(hom, torch.linalg.inv(homography).transpose(-1, -2))  # (B, N, 3)
    sign = torch.sign(plane[..., 2])
    return atan2(sign * plane[..., 1], sign * plane[..., 0])


# A rim is searched from more starts where its projected half-width is under this many
# times the geometric mean of its landmarks' RMS distance and its half-length: there the
# homography's start may sit on the far side (over half-lengths of 30-100 px and noise of
# 0.3-3 px it did up to about 5 times, but by more than 1 % of the RMS only below 3).
_THIN_RIM_FACTOR = 3.0
# Those starts: in each of _RIM_SECTORS equal arcs of the rim parameter (two: the rim's
# sides, split at t = 0 and pi, the ends of e1, which lies in the detector plane, so near
# the ellipse's tips), the nearest of _SECTOR_SAMPLES samples, given _SECTOR_STEPS Newton
# steps (a start half a sample off, by a tip whose radius of curvature is far below the
# noise, takes more than two bounded steps).
_RIM_SECTORS, _SECTOR_SAMPLES, _SECTOR_STEPS = 2, 32, 6


def _sector_rim_parameters(pose: Tensor, points: Tensor, radius: Tensor, geom: Tensor
                           ) -> Tensor:
    """``(B, N, _RIM_SECTORS)`` rim parameters: for each landmark and each of
    ``_RIM_SECTORS`` equal arcs of the rim, that of the arc's sample nearest the landmark.

    On a nearly edge-on rim (an ellipse a few pixels wide against pixels of noise) the
    homography sends a landmark off the rim far along it, often past a tip, and a landmark
    between the rim's two sides may lie nearest a sample of the far side; Newton steps then
    end on the wrong side, at up to ten times the true distance. One of these starts lies
    on each side.

    Args: pose ``(B, 5)`` rad / mm, points ``(B, N, 2)`` px, radius ``(B,)``, geom ``(B, 4)``.
    """
    samples = _RIM_SECTORS * _SECTOR_SAMPLES
    grid = torch.linspace(0, 2 * math.pi, samples + 1, dtype=pose.dtype, device=pose.device)
    grid = grid[:-1].expand(pose.shape[0], samples)
    rim = _rim(pose, grid, radius, geom)
    u, v = points.unbind(-1)
    near = (u[..., None] - rim.u[:, None]) ** 2 + (v[..., None] - rim.v[:, None]) ** 2
    nearest = near.unflatten(-1, (_RIM_SECTORS, _SECTOR_SAMPLES)).argmin(-1)
    sector_start = torch.arange(_RIM_SECTORS, device=pose.device) * _SECTOR_SAMPLES
    return grid[0][sector_start + nearest]


def _noise_variance(dist: Tensor, weights: Tensor) -> Tensor:
    """``(B, 1)`` landmark noise variance (unit weight) from signed distances ``(B, N)``,
    with 5 degrees of freedom taken by the pose."""
    used = (weights > 0).sum(-1, keepdim=True)
    mean_square = (weights * dist**2).sum(-1, keepdim=True) / weights.sum(-1, keepdim=True)
    return mean_square * used / (used - 5).clamp_min(1)


def _curvature_offsets(dist: Tensor, weights: Tensor, rim: _Rim, n_u: Tensor,
                       n_v: Tensor) -> Tensor:
    """Expected signed distance of a noisy landmark to the projected rim, ``(B, N)`` px.

    A landmark pushed a distance ``s`` along the rim by noise lies ``kappa s^2 / 2`` off a
    rim of curvature ``kappa`` on its convex side, so its distance to the closest rim point
    is biased by ``-sigma^2 kappa / 2`` along the normal. That bias inflates the maximum-
    likelihood ellipse where the rim bends sharply (the tips of thin ellipses); subtracting
    it makes the estimating equation unbiased to second order (a corrected score, as in
    Kanatani's hyperaccurate correction). Beyond ``sigma kappa ~ 1`` the expansion fails and
    the offset saturates, so it is clipped at one noise standard deviation.
    """
    variance = _noise_variance(dist, weights)
    bend = (n_u * rim.ddu + n_v * rim.ddv) / rim.speed2.clamp_min(1e-30)
    limit = variance.sqrt()
    return torch.clamp(-0.5 * variance * bend, -limit, limit)


def _signed_distances(pose: Tensor, t: Tensor, points: tuple[Tensor, Tensor], weights: Tensor,
                      radius: Tensor, geom: Tensor, corrected: bool
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor, _Rim]:
    """Landmark distances to the rim at ``t`` along its normals, less the curvature offsets
    when ``corrected``; with the pose Jacobian of the rim along the normals.

    Returns: distances ``(B, N)``, Jacobian ``(B, N, 5)``, offsets ``(du, dv)`` ``(B, N)``
    and the rim.
    """
    rim = _rim(pose, t, radius, geom)
    off_u, off_v = points[0] - rim.u, points[1] - rim.v
    n_u, n_v, jac = _normal_jacobian(pose, rim)
    dist = off_u * n_u + off_v * n_v
    if corrected:
        dist = dist - _curvature_offsets(dist, weights, rim, n_u, n_v)
    return dist, jac, off_u, off_v, rim


def _stationarity(pose: Tensor, t: Tensor, points: Tensor, weights: Tensor, geom: Tensor,
                  radius: Tensor, corrected: bool) -> tuple[Tensor, Tensor]:
    """The equations the refined pose solves: ``(B, 5)`` pose and ``(B, N)`` rim parts.

    The rim part puts each landmark's rim point closest to it; on that set the pose part is
    the gradient of the orthogonal-distance objective (or its corrected score).
    """
    dist, jac, off_u, off_v, rim = _signed_distances(pose, t, points.unbind(-1), weights,
                                                     radius, geom, corrected)
    rim_part = -weights * (off_u * rim.du + off_v * rim.dv)
    return -((weights * dist)[..., None] * jac).sum(-2), rim_part


def _normal_equations(pose: Tensor, t: Tensor, u: Tensor, v: Tensor, weights: Tensor,
                      root_w: Tensor, geom: Tensor, radius: Tensor, corrected: bool
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One evaluation of the solver: a Newton step of ``t``, then the pose's normal equations.

    Args: pose ``(B, 5)``, t ``(B, N)``, landmarks ``u, v`` ``(B, N)`` px, weights and their
    roots ``(B, N)``, geom ``(B, 4)``, radius ``(B,)``.
    Returns: ``J^T J`` ``(B, 5, 5)``, ``J^T res`` ``(B, 5)``, cost ``(B,)``, new ``t``.
    """
    t = _closest_rim_parameters(pose, t, (u, v), radius, geom)
    dist, jac, off_u, off_v, _ = _signed_distances(pose, t, (u, v), weights, radius, geom,
                                                   corrected)
    res, jac = root_w * dist, root_w[..., None] * jac
    jtj = matmul(jac.transpose(-1, -2), jac)
    rhs = (jac * res[..., None]).sum(-2)
    # The cost counts the whole offset: its tangential part shrinks as t converges, so the
    # cost falls monotonically with each t step at a fixed pose.
    return jtj, rhs, (weights * (off_u**2 + off_v**2)).sum(-1), t


@functools.cache
def _compiled(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function`` fused by ``torch.compile`` (one C++ loop instead of ~100 elementwise
    passes over memory): about 3x faster on large batches, after a one-off compilation of
    about a minute that Inductor caches on disk."""
    return torch.compile(function, dynamic=True)


_UNCOMPILABLE: set[Callable[..., Any]] = set()  # functions torch.compile failed on


def _run(function: Callable[..., Any], compiled: bool, *args: Any) -> Any:
    """``function(*args)``, through :func:`_compiled` when asked and it works (it needs a
    C++ compiler, and a failure shows only at the first call); else eagerly, with a warning
    the first time."""
    if compiled and function not in _UNCOMPILABLE:
        try:
            return _compiled(function)(*args)
        except Exception as error:  # noqa: BLE001 - any compile failure falls back the same way
            _UNCOMPILABLE.add(function)
            warnings.warn(f"torch.compile failed, running {function.__name__} without it: "
                          f"{error}", stacklevel=2)
    return function(*args)


def _outline_equations(pose: Tensor, points: Tensor, weights: Tensor, radius: Tensor,
                       geom: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The sphere-outline landmarks' share of the normal equations: ``J^T J`` ``(B, 5, 5)``
    and ``J^T res`` ``(B, 5)`` (in the centre's block only) and cost ``(B,)``."""
    dist, jac = outline_distances(pose[:, 2:5], points, radius, geom)
    # The model's outline moves along the normal by -d dist: J = -jac, residual = dist.
    weighted = weights[..., None] * jac
    jtj = torch.zeros(*pose.shape, 5, dtype=pose.dtype, device=pose.device)
    rhs = torch.zeros_like(pose)
    jtj[:, 2:, 2:] = matmul(jac.transpose(-1, -2), weighted)
    rhs[:, 2:] = -(weighted * dist[..., None]).sum(-2)
    return jtj, rhs, (weights * dist**2).sum(-1)


def _levenberg_marquardt(pose: Tensor, t: Tensor, points: Tensor, weights: Tensor,
                         geom: Tensor, radius: Tensor, max_iter: int, tol: float,
                         corrected: bool, compiled: bool = False,
                         outline: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Orthogonal-distance regression of the rim: ``min sum_i w_i |x_i - rim(pose, t_i)|^2``
    over the pose and one rim parameter per landmark, the maximum-likelihood estimate for
    Gaussian landmark noise (with ``corrected``, its curvature-bias-corrected score).

    Variable projection: each evaluation first moves every ``t_i`` to its closest rim point,
    so the pose step is a 5-parameter Levenberg-Marquardt step on the signed distances (the
    Schur complement of the diagonal ``t`` block, in closed form).

    ``outline``: sphere-outline landmarks ``(B, M, 2)`` px and weights ``(B, M)``, whose
    weighted squared distances to the projected sphere (:mod:`cupnet.outline`) join the cost.

    Items that have converged leave the working set. Every tensor has a leading batch dim.
    Returns the pose ``(B, 5)``, rim parameters ``(B, N)`` and whether each item converged
    ``(B,)``: met the stopping test (not one still moving at ``max_iter``, nor one whose
    steps all failed).
    """
    pose, t = pose.clone(), t.clone()
    converged = torch.zeros(pose.shape[0], dtype=torch.bool, device=pose.device)
    root_w = weights.sqrt()
    pts = points.unbind(-1)  # contiguous u and v: strided views slow every elementwise op
    outline_points, outline_weights = (None, None) if outline is None else outline

    def evaluate(p: Tensor, tt: Tensor, x: tuple[Tensor, Tensor], w: Tensor, rw: Tensor,
                 g: Tensor, r: Tensor, active: Tensor
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        jtj, rhs, cost, tt = _run(_normal_equations, compiled, p, tt, x[0], x[1], w, rw, g, r,
                                  corrected)
        if outline_points is not None:
            more = _outline_equations(p, outline_points[active], outline_weights[active], r, g)
            jtj, rhs, cost = jtj + more[0], rhs + more[1], cost + more[2]
        # Newton decrement of the pose equations: the corrected score is not the gradient of
        # the cost, so near its root steps are judged by this instead (plain ML needs none).
        if not corrected:
            return jtj, rhs, cost, torch.zeros_like(cost), tt
        decrement = (rhs * torch.linalg.solve_ex(jtj, rhs[..., None])[0].squeeze(-1)).sum(-1)
        return jtj, rhs, cost, decrement, tt

    active = torch.arange(pose.shape[0], device=pose.device)
    jtj, rhs, cost, decrement, t = evaluate(pose, t, pts, weights, root_w, geom, radius, active)
    lowest, dof = cost, ((weights > 0).sum(-1) - 5).clamp_min(1)
    damping = torch.full(pose.shape[:1], 1e-3, dtype=pose.dtype, device=pose.device)
    for _ in range(max_iter):
        damped = jtj + damping[:, None, None] * torch.diag_embed(jtj.diagonal(dim1=-2, dim2=-1))
        step = torch.linalg.solve_ex(damped, rhs[..., None])[0].squeeze(-1)
        # Converged when the step is statistically negligible: the cost decrease the linear
        # model promises is below tol noise variances (sigma^2 ~ cost / N); such a step is
        # taken without evaluating it. The floor lets exact, noise-free landmarks stop at a
        # residual of ~1e-10 px.
        predicted = (step * rhs).sum(-1)
        done = predicted <= tol * cost / t.shape[1] + 1e-20 * t.shape[1]
        pose[active[done]] += step[done]
        converged[active[done]] = True
        live = ~done
        jtj, rhs, cost, decrement, step, damping, active, lowest, dof = (
            a[live] for a in (jtj, rhs, cost, decrement, step, damping, active, lowest, dof))
        if active.numel() == 0:
            break
        x = tuple(c[active] for c in pts)
        w, rw, g, r = (v[active] for v in (weights, root_w, geom, radius))
        p, tt = pose[active], t[active]
        trial = evaluate(p + step, tt, x, w, rw, g, r, active)
        # Accept ties within round-off, so the last digits still converge. Steps towards the
        # corrected root may raise the cost, but only within two noise variances of the
        # lowest cost seen (the root lies about a standard deviation from the ML pose; on
        # near-degenerate ellipses it can run off, and this keeps the pose beside the ML one).
        within = trial[2] <= lowest + 2 * lowest / dof
        better = torch.isfinite(trial[2]) & (
            (trial[2] <= cost * (1 + 1e-13)) | (corrected & (trial[3] < decrement) & within))
        lowest = torch.where(better, torch.minimum(lowest, trial[2]), lowest)
        pose[active] = torch.where(better[:, None], p + step, p)
        t[active] = torch.where(better[:, None], trial[4], tt)
        damping = torch.where(better, damping / 4, damping * 4)
        keep = damping < 1e12
        jtj, rhs, cost, decrement = (
            torch.where(better.view(-1, *[1] * (a.ndim - 1)), b_, a)[keep]
            for a, b_ in zip((jtj, rhs, cost, decrement), trial[:4], strict=True))
        damping, active, lowest, dof = damping[keep], active[keep], lowest[keep], dof[keep]
    return pose, t, converged


class _RefinePose(torch.autograd.Function):
    """LM forward; backward by the implicit function theorem at the solution.

    The solution ``z* = (pose, t)`` is a root of ``F(z, data)`` (:func:`_stationarity`), so
    ``d z* / d data = -(dF/dz)^-1 dF/d data``, the data being the landmarks, their weights,
    the geometry rows and the radius. ``dF/dz`` has a diagonal ``t`` block, so the
    transposed solve is a 5x5 Schur solve per item, from five forward- and five reverse-mode
    products and one more for the diagonal.
    """

    @staticmethod
    def forward(ctx: FunctionCtx, start: Tensor, points: Tensor,  # type: ignore[override]
                weights: Tensor, geom: Tensor, radius: Tensor, max_iter: int, tol: float,
                corrected: bool, compiled: bool) -> tuple[Tensor, Tensor, Tensor]:
        with torch.no_grad():
            t0 = _initial_rim_parameters(start, points, radius, geom)
            pose, t, converged = _levenberg_marquardt(start, t0, points, weights, geom, radius,
                                                      max_iter, tol, corrected, compiled)
        ctx.save_for_backward(pose, t, points, weights, geom, radius)
        ctx.corrected = corrected
        ctx.mark_non_differentiable(t, converged)
        return pose, t, converged

    @staticmethod
    def backward(ctx: FunctionCtx, grad_pose: Tensor,  # type: ignore[override]
                 _grad_t: Tensor | None, _grad_converged: Tensor | None
                 ) -> tuple[Tensor | None, ...]:
        if torch.is_grad_enabled():  # create_graph: the gradient below has no graph of its own
            raise RuntimeError(
                "second derivatives through the refined pose are not supported (the implicit "
                "gradient is built outside autograd's graph, and its derivative would be "
                "wrong): take "
                "them through solve_pose(..., refine=False), or detach the pose where a "
                "graph of the gradient is made (create_graph=True)")
        pose, t, points, weights, geom, radius = ctx.saved_tensors

        def equations(p: Tensor, tt: Tensor, x: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
            return _stationarity(p, tt, x, w, geom, radius, ctx.corrected)

        with torch.enable_grad():
            eye = torch.eye(5, dtype=pose.dtype, device=pose.device)
            zero_t = torch.zeros_like(t)
            columns = [torch.func.jvp(lambda p, tt: equations(p, tt, points, weights),
                                      (pose, t), (eye[k].expand_as(pose), zero_t))[1]
                       for k in range(5)]
            f_pp = torch.stack([c[0] for c in columns], -1)  # (B, 5, 5)
            f_tp = torch.stack([c[1] for c in columns], -1)  # (B, N, 5)
            f_tt = torch.func.jvp(lambda tt: equations(pose, tt, points, weights)[1], (t,),
                                  (torch.ones_like(t),))[1]  # diagonal, (B, N)
            f_tt = torch.where(f_tt.abs() > 1e-12, f_tt, torch.full_like(f_tt, 1e-12))
            _, pull_t = torch.func.vjp(lambda tt: equations(pose, tt, points, weights)[0], t)
            f_pt = torch.stack([pull_t(eye[k].expand_as(pose))[0] for k in range(5)], 1)
            # (dF/dz)^T v = (grad_pose, 0), t block eliminated.
            schur = f_pp.transpose(-1, -2) - matmul(f_tp.transpose(-1, -2),
                                                    f_pt.transpose(-1, -2) / f_tt[..., None])
            v_pose = torch.linalg.solve(schur, grad_pose[..., None]).squeeze(-1)
            v_t = -(f_pt * v_pose[..., None]).sum(-2) / f_tt
            # The data: the landmarks, their weights, and the geometry and radius they are
            # seen through (a network that learns a calibration or a cup size needs these).
            _, pull = torch.func.vjp(
                lambda x, w, g, r: _stationarity(pose, t, x, w, g, r, ctx.corrected),
                points, weights, geom, radius)
            grads = pull((-v_pose, -v_t))
        return None, *grads, None, None, None, None


def refine_pose(start: Tensor, points: Tensor, geometry: Geometry, radius: Tensor | float,
                weights: Tensor | None = None, max_iter: int = 10, tol: float = 1e-4,
                corrected: bool = True, compiled: bool = False) -> tuple[Tensor, Tensor]:
    """Maximum-likelihood pose: orthogonal-distance regression of the projected rim.

    Minimises ``sum_i w_i |x_i - rim(pose, t_i)|^2`` over the pose and each landmark's rim
    parameter ``t_i`` (positions along the rim are unknown, so they are estimated too).
    With ``corrected`` (the default) it solves the curvature-corrected score instead, which
    removes the second-order bias that noise gives the maximum-likelihood fit of thin
    ellipses (see :func:`_curvature_offsets`); noise-free landmarks give the same pose.
    Gradients with respect to ``points``, ``weights``, ``geometry`` and ``radius`` are exact
    at the solution (implicit function theorem), so only where the refinement reached it
    (:func:`solve_pose` says where it met its stopping test: :attr:`PoseSolution.converged`);
    ``start`` gets none; second derivatives are refused.

    Args:
        start: ``(B, 5)`` initial poses (rad, mm), e.g. from :func:`poses_from_conic`.
        points: ``(B, N, 2)`` or ``(N, 2)`` pixels (refined in float64, CONVENTIONS.md).
        geometry: batch fields ``(B,)`` or scalars.
        radius: mm, scalar or ``(B,)``.
        weights: ``(B, N)`` or ``(N,)`` non-negative, default ones (0 drops a landmark, whose
            coordinates may then be NaN: ragged sets padded).
        max_iter: LM iterations at most.
        tol: stop when a step would lower the cost by less than ``tol`` noise variances
            (1e-4: steps below a hundredth of a standard deviation). Tighten (e.g. 1e-20)
            where the implicit gradient must be exact to many digits.
        corrected: solve the curvature-corrected score rather than plain ML.
        compiled: run the solver's inner loop through ``torch.compile`` (worth it for
            batches of thousands; the first call compiles for about a minute).
    Returns:
        ``(B, 5)`` refined poses (rad, mm) and ``(B, N)`` rim parameters of the landmarks, in
        the points' floating dtype (float64 for integer points).
    Raises:
        PoseError: naming the first item whose landmarks determine no pose (too few,
        collinear, NaN with a weight, a negative weight), whose geometry or radius is
        unusable, or whose start is not finite; or shapes that do not match.
    """
    points, weights, out_dtype = landmark_batch(points, weights, "raise", PoseError)
    batch = points.shape[0]
    if start.shape != (batch, 5):
        raise PoseError(f"start must have shape ({batch}, 5), a pose per landmark set, got "
                        f"{tuple(start.shape)}")
    radius = _per_item(radius, "radius", batch, torch.float64, points.device)
    check_geometry_batch(geometry, batch)
    reasons = zip(landmark_problems(points.detach(), weights.detach()),
                  geometry_problems(geometry, radius.detach()),
                  torch.isfinite(start.detach()).all(-1).tolist(), strict=True)
    _raise_first_problem(fit if fit != "ok" else problem if problem is not None
                         else None if finite else "start pose is not finite"
                         for fit, problem, finite in reasons)
    pose, t, _ = _refined(start.to(torch.float64), points, geometry, radius, weights, max_iter,
                          tol, corrected, compiled)
    return pose.to(out_dtype), t.to(out_dtype)


def _refined(start: Tensor, points: Tensor, geometry: Geometry, radius: Tensor,
             weights: Tensor, max_iter: int, tol: float, corrected: bool,
             compiled: bool) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`refine_pose` on checked input of one dtype: start ``(B, 5)``, points
    ``(B, N, 2)``, radius ``(B,)``, weights ``(B, N)``; with whether each item converged
    ``(B,)`` (:func:`_levenberg_marquardt`)."""
    geom = _batch_geometry(geometry, start.shape[0], start.dtype, start.device)
    return _RefinePose.apply(start.detach(), points, weights, geom, radius.contiguous(),
                             max_iter, tol, corrected, compiled)


def refine_pose_with_outline(start: Tensor, points: Tensor, weights: Tensor,
                             outline_points: Tensor, outline_weights: Tensor,
                             geometry: Geometry, radius: Tensor, max_iter: int = 10,
                             tol: float = 1e-4) -> Tensor:
    """:func:`refine_pose` with the sphere's outline too: the rim landmarks' cost plus the
    weighted squared distances of dome-outline landmarks to the projected sphere
    (:func:`cupnet.outline.outline_distances`), which pins the centre, and so ``h``, where
    the rim alone leaves it loose (a nearly edge-on rim's major axis). Both sets' weights are
    inverse noise variances (px^-2) on one scale. Inference only: no gradient.

    Args:
        start: ``(B, 5)`` rad / mm; points ``(B, N, 2)`` px and weights ``(B, N)`` of the
        rim; outline_points ``(B, M, 2)`` px and outline_weights ``(B, M)`` (0 drops one);
        geometry: fields ``(B,)`` or scalars; radius ``(B,)`` mm.
    Returns:
        ``(B, 5)`` rad / mm.
    """
    with torch.no_grad():
        geom = _batch_geometry(geometry, start.shape[0], start.dtype, start.device)
        t = _initial_rim_parameters(start, points, radius, geom)
        pose, *_ = _levenberg_marquardt(start, t, points, weights, geom, radius, max_iter, tol,
                                        True, outline=(outline_points, outline_weights))
    return pose


def _preferred(solutions: Tensor) -> Tensor:
    """``(B,)`` index of the candidate of ``(B, 2, 5)`` to report first: the one in range (least
    range violation); where both are, one inside phi's range, which is open at -90 deg, then
    the larger theta (the mirror pose of a cup seen off the central ray has the smaller one,
    and clinical anteversion is rarely near 0)."""
    violation = range_violation(solutions)
    theta, phi = _oriented_angles(solutions)
    # Exact landmarks of a cup at phi +90 deg have their mirror pose at -90 (range_violation
    # counts it in range, a limit of poses that are), and its larger theta had put it first.
    rank = theta - 10.0 * (phi <= -HALF_PI + 1e-12)
    tie = (violation[:, 0] - violation[:, 1]).abs() <= 1e-12
    return torch.where(tie, rank[:, 1] > rank[:, 0], violation[:, 1] < violation[:, 0]).long()


def _select(solutions: Tensor, converged: Tensor, ambiguity_tol: float
            ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pick the preferred candidate of ``(B, 2, 5)`` -> (pose, alt pose, ambiguous, whether
    the pose's refinement converged, of the candidates' ``converged`` ``(B, 2)``)."""
    index = _preferred(solutions)
    rows = torch.arange(solutions.shape[0], device=solutions.device)
    chosen, other = solutions[rows, index], solutions[rows, 1 - index]
    ambiguous = range_violation(other) <= ambiguity_tol
    return canonical_pose(chosen), canonical_pose(other), ambiguous, converged[rows, index]


def other_circle_pose(pose: Tensor, radius: Tensor, geometry: Geometry,
                      ambiguity_tol_deg: float = 1.0) -> tuple[Tensor, Tensor]:
    """The second circle pose of the rim ellipse that ``pose`` projects to (the two poses of
    :func:`poses_from_conic`), and whether it lies in the CONVENTIONS ranges (within
    ``ambiguity_tol_deg``, as :func:`solve_pose` judges its candidates).

    A pose refined by more than its rim's landmarks (the dome's outline, say) projects to a
    slightly different ellipse than the landmarks' fit; this tells whether that ellipse, the
    one reported, could as well be the rim of another pose in range.

    Args:
        pose: ``(B, 5)`` deg / mm (public units); radius: ``(B,)`` mm; geometry: fields
        ``(B,)`` or scalars.
    Returns:
        ``(B, 5)`` the other pose, deg / mm, in range (or clamped to it,
        :func:`canonical_pose`); ``(B,)`` bool, in range.
    """
    rad = pose_to_radians(pose)
    candidates = _circle_poses(rim_conic(rad, radius, geometry), geometry, radius)
    # The candidate whose rim normal lies farther from the pose's is the other one.
    alignment = (cup_axis(candidates) * cup_axis(rad)[:, None]).sum(-1).abs()
    other = candidates[torch.arange(len(pose), device=pose.device), alignment.argmin(-1)]
    in_range = range_violation(other) <= math.radians(ambiguity_tol_deg)
    return pose_to_degrees(canonical_pose(other)), in_range


def _newton_distances(pose: Tensor, t: Tensor, u: Tensor, v: Tensor, radius: Tensor,
                      geom: Tensor, iterations: int) -> tuple[Tensor, Tensor]:
    """Landmark distances ``(B, N)`` px to the rim after ``iterations`` Newton steps of
    their rim parameters ``t``, and those parameters; landmarks ``u, v`` ``(B, N)``."""
    t = _closest_rim_parameters(pose, t, (u, v), radius, geom, iterations)
    rim = _rim(pose, t, radius, geom)
    return hypot(u - rim.u, v - rim.v), t


def _closest_rim(pose: Tensor, points: Tensor, radius: Tensor, geom: Tensor, iterations: int,
                 compiled: bool = False, active: Tensor | None = None
                 ) -> tuple[Tensor, Tensor]:
    """Each landmark's closest rim point: ``iterations`` Newton steps from its
    :func:`_initial_rim_parameters`; on a thin rim (its projected half-width, about
    ``r |sin theta|`` magnified, under ``_THIN_RIM_FACTOR`` times the geometric mean of the
    landmarks' RMS distance and the rim's half-length) also at least ``_SECTOR_STEPS`` from
    each of its :func:`_sector_rim_parameters`, the start that ends nearest winning, the
    homography's unless another ends nearer by more than round-off. Rims that are not thin
    get the homography's result to the bit.

    Args: pose ``(B, 5)`` rad / mm, points ``(B, N, 2)`` px, radius ``(B,)``, geom
    ``(B, 4)``; compiled: through ``torch.compile`` (see :func:`refine_pose`); active
    ``(B, N)`` bool, the landmarks the RMS is taken over (None: all; padding, at weight 0,
    lies anywhere and would call every padded rim thin).
    Returns: distances ``(B, N)`` px and rim parameters ``(B, N)`` rad.
    """
    u, v = points.unbind(-1)
    t = _initial_rim_parameters(pose, points, radius, geom)
    home, t = _run(_newton_distances, compiled, pose, t, u, v, radius, geom, iterations)
    sdd, spacing = geom[:, 0], geom[:, 1]
    half_length = radius * sdd / (spacing * (sdd - pose[:, 4]))  # px, at the rim's centre
    half_width = half_length * pose[:, 0].sin().abs()
    active = torch.ones_like(home, dtype=torch.bool) if active is None else active
    rms = (home.pow(2) * active).sum(-1).div(active.sum(-1).clamp_min(1)).sqrt()
    # NaN distances count as thin: the search may find what the homography's start did not
    thin = ~(half_width >= _THIN_RIM_FACTOR * (rms * half_length).sqrt())
    rows = thin.nonzero()[:, 0]
    if len(rows) == 0:
        return home, t
    starts = _sector_rim_parameters(pose[rows], points[rows], radius[rows], geom[rows])
    count = starts.shape[-1]
    others, ends = (found.unflatten(-1, (-1, count)) for found in _run(
        _newton_distances, compiled, pose[rows], starts.flatten(1),
        u[rows].repeat_interleave(count, -1), v[rows].repeat_interleave(count, -1),
        radius[rows], geom[rows], max(iterations, _SECTOR_STEPS)))
    best, index = others.min(-1)
    nearer = best < home[rows] - 1e-9
    home[rows] = torch.where(nearer, best, home[rows])
    t[rows] = torch.where(nearer, ends.gather(-1, index[..., None])[..., 0], t[rows])
    return home, t


def rim_distances(pose: Tensor, points: Tensor, radius: Tensor, geometry: Geometry,
                  iterations: int = 2, compiled: bool = False,
                  weights: Tensor | None = None) -> Tensor:
    """Distance of each landmark to the projected rim (its closest rim point), pixels.

    Args:
        pose: ``(B, 5)`` rad / mm; points: ``(B, N, 2)`` px; radius: ``(B,)`` mm.
        iterations: Newton steps on each landmark's rim parameter, from its exact value for
            a landmark on the rim (the error left falls with the cube of the distance); on
            a nearly edge-on rim, whose far side can trap that start, from a sample on each
            side too, the nearest end kept.
        compiled: through ``torch.compile`` (see :func:`refine_pose`).
        weights: ``(B, N)``, where given, landmarks of weight 0 (padding) do not decide
            whether a rim is thin.
    Returns:
        ``(B, N)`` px, not differentiable.
    """
    with torch.no_grad():
        geom = _batch_geometry(geometry, pose.shape[0], pose.dtype, pose.device)
        active = None if weights is None else weights > 0
        return _closest_rim(pose, points, radius, geom, iterations, compiled, active)[0]


def rim_residual(pose: Tensor, points: Tensor, weights: Tensor, radius: Tensor,
                 geometry: Geometry, compiled: bool = False) -> Tensor:
    """Weighted RMS distance of landmarks to the projected rim of ``pose``, pixels: the
    :attr:`PoseSolution.residual_px` of a solved pose, and of any other (a refined one).

    Args:
        pose: ``(B, 5)`` rad / mm; points: ``(B, N, 2)`` px; weights: ``(B, N)``
            non-negative (0: padding, whose coordinates must be finite); radius: ``(B,)`` mm.
        compiled: through ``torch.compile`` (see :func:`refine_pose`).
    Returns:
        ``(B,)`` px, not differentiable.
    """
    weights = weights.detach()
    dist = rim_distances(pose.detach(), points.detach(), radius.detach(), geometry,
                         compiled=compiled, weights=weights)
    return torch.sqrt((weights * dist**2).sum(-1) / weights.sum(-1).clamp_min(1e-300))


def solve_pose(
    points: Tensor,
    geometry: Geometry,
    cup_diameter: Tensor | float,
    weights: Tensor | None = None,
    *,
    refine: bool = True,
    on_error: Literal["raise", "flag"] = "raise",
    ambiguity_tol_deg: float = 1.0,
    max_iter: int = 10,
    tol: float = 1e-4,
    corrected: bool = True,
    compiled: bool = False,
) -> PoseSolution:
    """Cup pose from rim landmarks: ellipse fit, closed form, ML refinement, range choice.

    Args:
        points: ``(B, N, 2)`` or ``(N, 2)`` landmark pixels (u, v), solved in float64
            (CONVENTIONS.md).
        geometry: batch fields ``(B,)`` or scalars.
        cup_diameter: outer diameter, mm, scalar or ``(B,)``.
        weights: ``(B, N)`` or ``(N,)`` non-negative landmark weights (0 drops a landmark,
            whose coordinates may then be NaN: ragged sets padded).
        refine: run the Levenberg-Marquardt ML refinement (else the closed form alone, which
            is differentiable through ``eigh``).
        on_error: ``"raise"`` raises :class:`PoseError` naming the first bad item; ``"flag"``
            returns its status and NaN pose and goes on.
        ambiguity_tol_deg: the other candidate counts as in range within this margin.
        max_iter, tol: LM iterations at most, and its stopping test (:func:`refine_pose`:
            tighten ``tol``, e.g. to 1e-20, where the gradient must be exact to many digits).
        corrected, compiled: see :func:`refine_pose`.
    Returns:
        :class:`PoseSolution` in the points' floating dtype (float64 for integer points),
        differentiable in ``pose`` w.r.t. points, weights, ``cup_diameter`` and the
        geometry's fields.
    """
    points, weights, out_dtype = landmark_batch(points, weights, on_error, PoseError)
    batch, dtype, device = points.shape[0], points.dtype, points.device
    radius = _per_item(cup_diameter, "cup_diameter", batch, dtype, device) / 2
    check_geometry_batch(geometry, batch)
    fit = fit_ellipse(points, weights, on_error="flag")
    status = [s if s == "ok" else f"error: {s}" for s in fit.status]
    for i, problem in enumerate(geometry_problems(geometry, radius.detach())):
        if problem is not None and status[i] == "ok":
            status[i] = f"error: {problem}"
    small = (fit.params[:, 2] < MIN_AXIS_PX).tolist()
    major = fit.params[:, 2].tolist()
    for i in range(batch):
        if status[i] == "ok" and small[i]:
            status[i] = (f"error: ellipse too small to solve (semi-major axis "
                         f"{major[i]:.3g} px < {MIN_AXIS_PX} px)")
    _raise_first(status, on_error)

    ok = torch.tensor([s == "ok" for s in status], dtype=torch.bool, device=device)
    # Unusable items are solved on a stand-in so the batch stays finite; masked at the end.
    safe_geometry = _safe_geometry(geometry, ok, batch, dtype, device)
    safe_radius = torch.where(ok, radius, torch.full_like(radius, _STAND_IN_RADIUS_MM))
    safe_conic = torch.where(ok[:, None, None], fit.conic, _stand_in_conic(safe_geometry, dtype,
                                                                         device))
    solutions = _circle_poses(safe_conic.detach() if refine else safe_conic, safe_geometry,
                              safe_radius)
    converged = torch.ones(batch, 2, dtype=torch.bool, device=device)
    if refine:
        solutions, converged = _refine_candidates(
            solutions, points, weights, ok, safe_geometry, safe_radius,
            math.radians(ambiguity_tol_deg),
            dict(max_iter=max_iter, tol=tol, corrected=corrected, compiled=compiled))
    pose, alt, ambiguous, converged = _select(solutions, converged,
                                              math.radians(ambiguity_tol_deg))

    residual = rim_residual(pose, torch.where(ok[:, None, None], points, 0.0), weights,
                            safe_radius, safe_geometry, compiled)

    h = pose[:, 4].detach()
    sdd = _batch_geometry(safe_geometry, batch, dtype, device)[:, 0]
    finite = torch.isfinite(pose).all(-1).tolist()
    for i, (h_i, sdd_i) in enumerate(zip(h.tolist(), sdd.tolist(), strict=True)):
        if status[i] == "ok" and not finite[i]:
            status[i] = "error: pose solver did not converge"
        elif status[i] == "ok" and not (0 < h_i < sdd_i):
            status[i] = (f"error: solved h = {h_i:.1f} mm lies outside (0, SDD = "
                         f"{sdd_i:.0f} mm): check cup diameter, SDD and pixel spacing")
    _raise_first(status, on_error)
    valid = torch.tensor([s == "ok" for s in status], dtype=torch.bool, device=device)
    ambiguous = ambiguous & valid
    status = ["ambiguous" if a else s for s, a in zip(status, ambiguous.tolist(), strict=True)]
    nan = torch.full_like(pose, math.nan)
    return PoseSolution(
        pose=torch.where(valid[:, None], pose_to_degrees(pose), nan).to(out_dtype),
        alt_pose=torch.where(ambiguous[:, None], pose_to_degrees(alt), nan).to(out_dtype),
        ambiguous=ambiguous,
        ellipse=fit.params.to(out_dtype),
        residual_px=torch.where(valid, residual, torch.full_like(residual, math.nan)
                                ).to(out_dtype),
        valid=valid,
        status=status,
        converged=converged & valid,
    )


def _refine_candidates(solutions: Tensor, points: Tensor, weights: Tensor | None, ok: Tensor,
                       geometry: Geometry, radius: Tensor, ambiguity_tol: float,
                       options: dict[str, Any]) -> tuple[Tensor, Tensor]:
    """Refine the in-range candidate of each item, and the other one where it may be too.

    Args:
        solutions: ``(B, 2, 5)`` closed-form candidates; points ``(B, N, 2)``; weights
        ``(B, N)`` or None; ok ``(B,)`` items with usable input (others get stand-in points);
        options: keywords of :func:`refine_pose`.
    Returns:
        ``(B, 2, 5)`` with refined candidates (differentiable w.r.t. points and weights), and
        ``(B, 2)`` whether each candidate's refinement converged (True where not refined).
    """
    batch, n = points.shape[:2]
    dtype, device = points.dtype, points.device
    weights = torch.ones(batch, n, dtype=dtype, device=device) if weights is None else weights
    points = torch.where(ok[:, None, None], points, _stand_in_points(geometry, n, dtype, device))
    weights = torch.where(ok[:, None], weights, torch.ones_like(weights))
    violation = range_violation(solutions)
    chosen = _preferred(solutions)
    # Refinement moves a candidate's range violation by a fraction of a degree at most.
    maybe_both = violation.max(-1).values <= ambiguity_tol + math.radians(2.0)
    items = torch.cat([torch.arange(batch, device=device), maybe_both.nonzero()[:, 0]])
    which = torch.cat([chosen, 1 - chosen[maybe_both]])
    rows = _batch_geometry(geometry, batch, dtype, device)[items]
    refined, _, converged = _refined(solutions[items, which], points[items],
                                     Geometry.from_rows(rows), radius[items], weights[items],
                                     **options)
    out = solutions.detach().clone()
    out[items, which] = refined
    settled = torch.ones(batch, 2, dtype=torch.bool, device=device)
    settled[items, which] = converged
    return out, settled


def _raise_first(status: list[str], on_error: str) -> None:
    """With ``on_error`` "raise", a PoseError naming the first item whose status is an
    error."""
    if on_error == "raise":
        _raise_first_problem(s[len("error: "):] if s.startswith("error") else None
                             for s in status)


def _raise_first_problem(problems: Iterable[str | None]) -> None:
    """A PoseError naming the first item with a problem (None: the item is fine)."""
    for i, problem in enumerate(problems):
        if problem is not None:
            raise PoseError(f"item {i}: {problem}")


def _safe_geometry(geometry: Geometry, ok: Tensor, batch: int, dtype: torch.dtype,
                   device: torch.device) -> Geometry:
    rows = _batch_geometry(geometry, batch, dtype, device)
    stand_in = torch.tensor([1000.0, 1.0, 0.0, 0.0], dtype=dtype, device=device)
    return Geometry.from_rows(torch.where(ok[:, None], rows, stand_in))


def _stand_in_pose(batch: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor([0.5, 0.3, 0.0, 0.0, 300.0], dtype=dtype, device=device).expand(batch, 5)


def _stand_in_conic(geometry: Geometry, dtype: torch.dtype, device: torch.device) -> Tensor:
    batch = _batch_geometry(geometry, 1, dtype, device).shape[0]
    return rim_conic(_stand_in_pose(batch, dtype, device), _STAND_IN_RADIUS_MM, geometry)


def _stand_in_points(geometry: Geometry, n: int, dtype: torch.dtype,
                     device: torch.device) -> Tensor:
    batch = _batch_geometry(geometry, 1, dtype, device).shape[0]
    t = torch.linspace(0, 2 * math.pi, n + 1, dtype=dtype, device=device)[:-1]
    return project_rim(_stand_in_pose(batch, dtype, device), _STAND_IN_RADIUS_MM, geometry, t)


def orthographic_pose(ellipse: Tensor) -> Tensor:
    """Lewinnek / Liaw orthographic baseline: anteversion ``asin(b/a)``, inclination ``alpha``.

    Under parallel projection the rim's minor axis lies along the projected cup axis, so the
    CONVENTIONS inclination is the major-axis angle wrapped into (-90, 90].

    Args:
        ellipse: ``(..., 5)`` (cx, cy, a, b, alpha_deg).
    Returns:
        ``(..., 2)`` (theta_deg, phi_deg).
    """
    theta = torch.rad2deg(torch.asin((ellipse[..., 3] / ellipse[..., 2]).clamp(max=1.0)))
    alpha = ellipse[..., 4]
    phi = torch.where(alpha > 90.0, alpha - 180.0, alpha)
    return torch.stack([theta, phi], -1)


def cramer_rao_bound(pose: Tensor, radius: Tensor | float, geometry: Geometry, t: Tensor,
                     sigma_px: float) -> Tensor:
    """Cramer-Rao bound (standard deviations) of the pose from ``N`` noisy rim landmarks.

    Landmark positions along the rim are unknown, so only each landmark's component normal
    to the projected rim carries information: ``a_i = n_i^T J_i`` with ``J_i`` the Jacobian of
    landmark ``i`` w.r.t. the pose, and ``cov >= sigma^2 (sum_i a_i^T a_i)^-1``.

    Args:
        pose: ``(B, 5)`` rad / mm.
        radius: mm, scalar or ``(B,)``.
        geometry: batch fields ``(B,)`` or scalars.
        t: ``(N,)`` rim parameters of the landmarks (rad).
        sigma_px: isotropic landmark noise, pixels (per coordinate), >= 0.
    Returns:
        ``(B, 5)`` bound on the standard deviation, public units (deg, deg, mm, mm, mm).
    Raises:
        PoseError: fewer than 5 landmarks (the pose has 5 parameters), a negative or
        non-finite ``sigma_px``, or an item whose geometry or radius is unusable or whose
        rim centre does not lie between the detector and the source (0 < h < SDD).
    """
    if pose.ndim != 2 or pose.shape[-1] != 5:
        raise PoseError(f"pose must have shape (B, 5), got {tuple(pose.shape)}")
    if t.ndim != 1 or t.shape[0] < 5:
        raise PoseError(f"t must hold 5 or more rim parameters (N,), one per landmark (the "
                        f"pose has 5 parameters), got shape {tuple(t.shape)}")
    if not (math.isfinite(sigma_px) and sigma_px >= 0):
        raise PoseError(f"sigma_px must be a noise level >= 0 px, got {sigma_px}")
    batch = pose.shape[0]
    radius = _per_item(radius, "radius", batch, pose.dtype, pose.device)
    check_geometry_batch(geometry, batch)
    geom = _batch_geometry(geometry, batch, pose.dtype, pose.device)
    reasons = zip(geometry_problems(geometry, radius.detach()), pose[:, 4].detach().tolist(),
                  geom[:, 0].tolist(), strict=True)
    _raise_first_problem(problem if problem is not None or 0 < h < sdd
                         else f"h = {h} mm lies outside (0, SDD = {sdd} mm)"
                         for problem, h, sdd in reasons)

    def landmarks(p: Tensor, tt: Tensor, g: Tensor, r: Tensor) -> Tensor:
        return project_rim(p[None], r, Geometry.from_rows(g), tt)[0]  # (N, 2)

    jac = vmap(jacfwd(landmarks), in_dims=(0, None, 0, 0))(pose, t, geom, radius)  # (B,N,2,5)
    tangent = vmap(jacfwd(landmarks, argnums=1), in_dims=(0, None, 0, 0))(pose, t, geom, radius)
    tangent = tangent.diagonal(dim1=-3, dim2=-1).transpose(-1, -2)  # (B, N, 2) d x_i / d t_i
    normal = torch.stack([-tangent[..., 1], tangent[..., 0]], -1)
    normal = normal / torch.linalg.vector_norm(normal, dim=-1, keepdim=True)
    rows = (normal[..., None] * jac).sum(-2)
    # The bound scales with sigma: computed at unit noise, so noise-free landmarks give 0.
    fisher = matmul(rows.transpose(-1, -2), rows)
    return sigma_px * pose_to_degrees(torch.linalg.inv(fisher).diagonal(dim1=-2, dim2=-1).sqrt())


def pose_standard_errors(pose_deg: Tensor, points: Tensor, geometry: Geometry,
                         cup_diameter: Tensor | float, weights: Tensor | None = None,
                         iterations: int = 3) -> Tensor:
    """Standard errors of a pose solved from rim landmarks, with their noise measured from
    the landmarks themselves: the Cramer-Rao bound :func:`cramer_rao_bound` at the solved
    pose, with the unknown noise level estimated from the residuals.

    At the ML pose the estimate's covariance is ``s^2 (J^T W J)^-1``, with ``J`` the rows of
    the pose Jacobian of the rim along its normals at the landmarks' closest rim points
    (tangential motion is absorbed by the landmarks' rim parameters), ``W`` the weights and
    ``s^2 = sum w d^2 / (N - 5)`` the unit-weight noise variance from the normal distances
    ``d`` (``N`` landmarks with a weight; the pose takes 5 degrees of freedom), so weights
    ``1 / sigma_i^2`` of any common scale give the same errors. Random landmark noise
    only: a bias the landmarks share (a rim network placing every landmark a little outside
    the rim) moves the pose without widening these.

    Args:
        pose_deg: ``(B, 5)`` solved poses, public units (:attr:`PoseSolution.pose`).
        points: ``(B, N, 2)`` or ``(N, 2)`` the landmarks they were solved from, px.
        geometry: batch fields ``(B,)`` or scalars; cup_diameter: mm, scalar or ``(B,)``.
        weights: ``(B, N)`` or ``(N,)`` the solve's landmark weights (None: equal).
        iterations: Newton steps of each landmark's rim parameter to its closest rim point.
    Returns:
        ``(B, 5)`` standard deviations (deg, deg, mm, mm, mm) in the points' floating dtype
        (float64 for integer points); NaN where the pose is NaN, fewer than 6 landmarks have
        a weight, or the geometry or diameter is unusable. Not differentiable.
    Raises:
        PoseError: shapes that do not match (a pose per landmark set).
    """
    points, weights, out_dtype = landmark_batch(points, weights, "raise", PoseError)
    batch, dtype, device = points.shape[0], points.dtype, points.device
    if pose_deg.shape != (batch, 5):
        raise PoseError(f"pose_deg must have shape ({batch}, 5), a pose per landmark set, "
                        f"got {tuple(pose_deg.shape)}")
    radius = _per_item(cup_diameter, "cup_diameter", batch, dtype, device) / 2
    check_geometry_batch(geometry, batch)
    with torch.no_grad():
        active = weights > 0
        used = active.sum(-1, keepdim=True)
        fine = torch.tensor([p is None for p in geometry_problems(geometry, radius)],
                            dtype=torch.bool, device=device)
        usable = torch.isfinite(pose_deg).all(-1) & (used[:, 0] > 5) & fine
        # Stand-ins keep the batch finite (a NaN pose makes a singular system); masked below.
        pose = torch.where(usable[:, None], pose_to_radians(pose_deg.to(dtype)),
                           _stand_in_pose(batch, dtype, device))
        geom = _batch_geometry(_safe_geometry(geometry, fine, batch, dtype, device), batch,
                               dtype, device)
        radius = torch.where(fine, radius, torch.full_like(radius, _STAND_IN_RADIUS_MM))
        # A landmark without weight may be padding (NaN, as a ragged batch has it): zeroed.
        points = torch.where(usable[:, None, None] & active[..., None], points, 0.0)
        t = _closest_rim(pose, points, radius, geom, iterations, active=active)[1]
        dist, jac, *_ = _signed_distances(pose, t, points.unbind(-1), weights, radius, geom,
                                          False)
        information = matmul(jac.transpose(-1, -2), weights[..., None] * jac)
        inverse, info = torch.linalg.inv_ex(information)
        # The unit-weight variance (not _noise_variance's, which is per mean weight): the
        # covariance then stays the same whatever scale the weights come in.
        variance = (weights * dist**2).sum(-1, keepdim=True) / (used - 5).clamp_min(1)
        std = pose_to_degrees((variance * inverse.diagonal(dim1=-2, dim2=-1)).sqrt())
        usable = usable & (info == 0) & torch.isfinite(std).all(-1)
        return torch.where(usable[:, None], std, torch.full_like(std, math.nan)).to(out_dtype)


def ellipse_of_pose(pose_deg: Tensor, cup_diameter: Tensor | float, geometry: Geometry) -> Tensor:
    """Projected rim ellipse ``(B, 5)`` px of public-unit poses ``(B, 5)``."""
    return conic_to_params(rim_conic(pose_to_radians(pose_deg), torch.as_tensor(cup_diameter) / 2,
                                     geometry))


def paper_start(ellipse: Tensor, geometry: Geometry, radius: Tensor | float) -> Tensor:
    """The paper's "first best guess" ``(25 deg, 40 deg, beta E_x, beta E_y, (1 - beta) H)``.

    ``E`` is the observed ellipse in detector millimetres (centre relative to the principal
    point) and ``beta = r / E_a``.

    Args:
        ellipse: ``(B, 5)`` px; radius: mm.
    Returns:
        ``(B, 5)`` public units (deg, mm).
    """
    sdd, spacing, u0, v0 = geometry.tensors(ellipse.dtype, ellipse.device)
    beta = torch.as_tensor(radius, dtype=ellipse.dtype) / (ellipse[:, 2] * spacing)
    ex, ey = (ellipse[:, 0] - u0) * spacing, (ellipse[:, 1] - v0) * spacing
    return torch.stack([torch.full_like(ex, 25.0), torch.full_like(ex, 40.0), beta * ex,
                        beta * ey, (1 - beta) * sdd], -1)


def ellipse_parameter_loss(predicted: Tensor, observed: Tensor) -> Tensor:
    """The paper's loss: mean squared ``(x, y, a, b, alpha)`` difference, alpha wrapped.

    Args:
        predicted, observed: ``(B, 5)`` px / deg.
    Returns:
        ``(B,)``.
    """
    diff = predicted - observed
    d_alpha = diff[:, 4].abs()
    wrapped = torch.minimum(d_alpha, 180.0 - d_alpha)
    return torch.cat([diff[:, :4] ** 2, wrapped[:, None] ** 2], -1).mean(-1)


def solve_pose_paper(points: Tensor, geometry: Geometry, cup_diameter: Tensor | float,
                     steps: int = 3000, lr: float = 0.5) -> tuple[Tensor, Tensor]:
    """Paper-faithful solver (Suh et al. 2025): first best guess + gradient descent (Adam) on
    the ellipse-parameter MSE between the observed and the projected rim ellipse.

    Kept to reproduce and compare with the paper; :func:`solve_pose` is exact and ~1000x
    faster. The observed ellipse here is the constrained direct fit, not the paper code's
    unconstrained algebraic fit.

    Args:
        points: ``(B, N, 2)`` px; geometry: batch fields or scalars; cup_diameter: mm.
        steps: gradient steps at most; lr: Adam learning rate (deg / mm per step).
    Returns:
        ``(B, 5)`` poses in public units, mapped into the CONVENTIONS ranges, and ``(B,)``
        the number of steps each item took until its loss stopped improving.
    """
    radius = torch.as_tensor(cup_diameter, dtype=points.dtype, device=points.device) / 2
    observed = fit_ellipse(points).params
    sdd = geometry.tensors(points.dtype, points.device)[0]
    pose = paper_start(observed, geometry, radius).requires_grad_(True)
    optimiser = torch.optim.Adam([pose], lr=lr)
    best = torch.full(points.shape[:1], math.inf, dtype=points.dtype, device=points.device)
    used = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
    for step in range(steps):
        optimiser.zero_grad()
        loss = ellipse_parameter_loss(ellipse_of_pose(pose, 2 * radius, geometry), observed)
        loss.sum().backward()
        optimiser.step()
        with torch.no_grad():
            # Keep the pose in its ranges: phi wraps (the ellipse's orientation repeats every
            # 180 deg, and from the fixed 40 deg start a negative inclination is nearer
            # across +90 deg); theta and h are clamped (h between detector and source).
            pose[:, 1] = torch.remainder(pose[:, 1] + 90.0, 180.0) - 90.0
            pose[:, 0].clamp_(0.0, 90.0)
            pose[:, 4] = torch.minimum(pose[:, 4].clamp_min(1.0), sdd - 1.0)
            improved = loss < best * (1 - 1e-6)
            used = torch.where(improved, torch.full_like(used, step + 1), used)
            best = torch.minimum(best, loss.detach())
            if step - int(used.max()) > 100:  # nobody improved for 100 steps
                break
    return pose_to_degrees(canonical_pose(pose_to_radians(pose.detach()))), used
