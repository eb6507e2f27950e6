"""Cone-beam geometry of CONVENTIONS.md: detector frame, cup pose, rim circle, projection.

World frame = detector frame: origin at the principal point on the detector, x along +u,
y along +v, z towards the source, which sits at (0, 0, sdd). Lengths in mm, pixel positions
(u, v) with pixel centres at integers. Pose tensors are ``(..., 5)`` ordered
``(theta, phi, k, l, h)`` with the angles in **radians** inside this module (public results
convert to degrees at the boundary, see :func:`pose_to_degrees`).

All functions are pure, batched over leading dimensions and differentiable; geometry and
pose maths default to float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cupnet.batchwise import matmul


@dataclass(frozen=True)
class Geometry:
    """Imaging geometry of one image, or of a batch when the fields are ``(B,)`` tensors.

    Attributes:
        sdd: source-to-detector distance ``H`` (mm).
        pixel_spacing: detector pixel spacing ``s`` (mm / pixel, at the detector).
        principal_u: principal point column ``u0`` (pixels).
        principal_v: principal point row ``v0`` (pixels).
    """

    sdd: float | Tensor
    pixel_spacing: float | Tensor
    principal_u: float | Tensor
    principal_v: float | Tensor

    @classmethod
    def for_image(
        cls,
        width: int,
        height: int,
        sdd: float,
        pixel_spacing: float,
        principal_u: float | None = None,
        principal_v: float | None = None,
    ) -> Geometry:
        """Geometry with the CONVENTIONS default principal point, the image centre."""
        return cls(
            sdd=sdd,
            pixel_spacing=pixel_spacing,
            principal_u=(width - 1) / 2 if principal_u is None else principal_u,
            principal_v=(height - 1) / 2 if principal_v is None else principal_v,
        )

    @classmethod
    def from_row(cls, row: Tensor) -> Geometry:
        """Geometry of one image, its fields Python floats, from a row ``(4,)`` (sdd, spacing,
        u0, v0), as a synthetic sample's ``"geometry"`` holds it."""
        return cls(*(float(v) for v in row))

    @classmethod
    def from_rows(cls, rows: Tensor) -> Geometry:
        """Geometry of rows ``(..., 4)`` (sdd, spacing, u0, v0), one per image (also for one
        row under ``vmap``)."""
        return cls(*rows.unbind(-1))

    def tensors(
        self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(sdd, spacing, u0, v0)`` as tensors broadcastable over a batch ``(B,)`` or ``()``."""
        out = []
        for name in ("sdd", "pixel_spacing", "principal_u", "principal_v"):
            value = getattr(self, name)
            try:
                out.append(torch.as_tensor(value, dtype=dtype, device=device))
            except (TypeError, ValueError) as err:  # torch's own names no field
                raise TypeError(f"geometry {name} must be a number or a tensor of numbers, "
                                f"got {value!r}") from err
        return tuple(out)  # type: ignore[return-value]


def rotation(theta: Tensor, phi: Tensor) -> Tensor:
    """Cup rotation ``R = Rz(phi) @ Rx(theta)``.

    Args:
        theta, phi: ``(...)`` radians.
    Returns:
        ``(..., 3, 3)``.
    """
    ct, st, cp, sp = torch.cos(theta), torch.sin(theta), torch.cos(phi), torch.sin(phi)
    zero = torch.zeros_like(ct)
    # Rz(phi) @ Rx(theta) multiplied out.
    rows = [
        torch.stack([cp, -sp * ct, sp * st], -1),
        torch.stack([sp, cp * ct, -cp * st], -1),
        torch.stack([zero, st, ct], -1),
    ]
    return torch.stack(rows, -2)


def cup_axis(pose: Tensor) -> Tensor:
    """Rim normal ``n = R @ (0, 1, 0)``. pose: ``(..., 5)`` -> ``(..., 3)`` unit vectors."""
    return rotation(pose[..., 0], pose[..., 1])[..., 1]


def rim_points(pose: Tensor, radius: Tensor | float, t: Tensor) -> Tensor:
    """3D rim points ``X(t) = c + R (r cos t, 0, r sin t)``.

    Args:
        pose: ``(..., 5)`` (theta, phi rad; k, l, h mm).
        radius: cup radius (mm), scalar or ``(...)``.
        t: ``(N,)`` or ``(..., N)`` rim parameter (rad).
    Returns:
        ``(..., N, 3)`` mm in the detector frame.
    """
    radius = torch.as_tensor(radius, dtype=pose.dtype, device=pose.device)
    rot = rotation(pose[..., 0], pose[..., 1])  # (..., 3, 3)
    local = torch.stack([torch.cos(t), torch.zeros_like(t), torch.sin(t)], -1)  # (..., N, 3)
    local = local * radius[..., None, None]
    return pose[..., None, 2:5] + matmul(local, rot.transpose(-1, -2))


def _floating(x: Tensor) -> Tensor:
    """``x`` itself when floating, else as float64 (integer pixel indices, say)."""
    return x if x.is_floating_point() else x.to(torch.float64)


def project(points: Tensor, geometry: Geometry) -> Tensor:
    """Perspective projection of detector-frame points to pixels.

    Args:
        points: ``(B, N, 3)`` or ``(N, 3)`` mm, with ``z < sdd``.
        geometry: batch fields ``(B,)`` or scalars.
    Returns:
        ``(..., N, 2)`` pixel positions ``(u, v)``.
    """
    points = _floating(points)
    sdd, spacing, u0, v0 = (g[..., None] for g in geometry.tensors(points.dtype, points.device))
    scale = sdd / (sdd - points[..., 2]) / spacing
    return torch.stack([u0 + points[..., 0] * scale, v0 + points[..., 1] * scale], -1)


def pixels_to_mm(uv: Tensor, geometry: Geometry) -> Tensor:
    """Pixels ``(..., N, 2)`` -> detector-plane mm ``(..., N, 2)`` (x, y)."""
    uv = _floating(uv)
    _, spacing, u0, v0 = (g[..., None] for g in geometry.tensors(uv.dtype, uv.device))
    return torch.stack([(uv[..., 0] - u0) * spacing, (uv[..., 1] - v0) * spacing], -1)


def mm_to_pixels(xy: Tensor, geometry: Geometry) -> Tensor:
    """Detector-plane mm ``(..., N, 2)`` -> pixels ``(..., N, 2)``."""
    xy = _floating(xy)
    _, spacing, u0, v0 = (g[..., None] for g in geometry.tensors(xy.dtype, xy.device))
    return torch.stack([u0 + xy[..., 0] / spacing, v0 + xy[..., 1] / spacing], -1)


def camera_matrix(geometry: Geometry, dtype: torch.dtype = torch.float64,
                  device: torch.device | str | None = None) -> Tensor:
    """Matrix ``A`` with ``(u, v, 1) ~ A @ (X - S)`` for a point ``X`` and the source ``S``.

    Returns ``(B, 3, 3)`` or ``(3, 3)``. Derivation: ``u = u0 + sdd x / (s (sdd - z))``, and
    ``X - S = (x, y, z - sdd)``, so ``A = [[sdd/s, 0, -u0], [0, sdd/s, -v0], [0, 0, -1]]``.
    """
    sdd, spacing, u0, v0 = geometry.tensors(dtype, device)
    sdd, spacing, u0, v0 = torch.broadcast_tensors(sdd, spacing, u0, v0)
    f = sdd / spacing
    zero, one = torch.zeros_like(f), torch.ones_like(f)
    return torch.stack(
        [torch.stack([f, zero, -u0], -1), torch.stack([zero, f, -v0], -1),
         torch.stack([zero, zero, -one], -1)], -2)


def source_position(geometry: Geometry, dtype: torch.dtype = torch.float64,
                    device: torch.device | str | None = None) -> Tensor:
    """X-ray source ``(0, 0, sdd)``: ``(B, 3)`` or ``(3,)`` mm."""
    sdd = geometry.tensors(dtype, device)[0]
    zero = torch.zeros_like(sdd)
    return torch.stack([zero, zero, sdd], -1)


def rim_conic(pose: Tensor, radius: Tensor | float, geometry: Geometry) -> Tensor:
    """Image conic of the projected rim circle, computed from the pose directly.

    The rim plane is mapped to the image by the homography ``G = A [e1, e2, c - S]`` of plane
    coordinates ``(alpha, beta, 1)``; the rim is ``alpha^2 + beta^2 = r^2`` there, so the image
    conic is ``G^-T diag(1, 1, -r^2) G^-1``. The result is scaled to unit Frobenius norm with
    ``p^T C p < 0`` inside the ellipse (as :func:`normalize_conic`).

    Args:
        pose: ``(B, 5)`` (theta, phi rad; k, l, h mm).
        radius: mm, scalar or ``(B,)``.
        geometry: batch fields ``(B,)`` or scalars.
    Returns:
        ``(B, 3, 3)`` symmetric conic in homogeneous pixels ``(u, v, 1)``.
    """
    # A pixel conic is ill-conditioned (its quadratic part ~1/a^2 beside a constant
    # ~(c/a)^2): built in float32 it is often no ellipse at all, so build it in float64.
    out_dtype, pose = pose.dtype, pose.to(torch.float64)
    radius = torch.as_tensor(radius, dtype=pose.dtype, device=pose.device)
    rot = rotation(pose[..., 0], pose[..., 1])
    cam = camera_matrix(geometry, pose.dtype, pose.device)
    centre = pose[..., 2:5] - source_position(geometry, pose.dtype, pose.device)
    basis = torch.stack([rot[..., 0], rot[..., 2], centre], -1)  # columns e1, e2, c - S
    homography = matmul(cam, basis)
    # G^-1 is adj(G) / det(G); the conic is defined up to scale, so use adj(G) and skip the
    # inverse: rows of adj(G) are cross products of G's columns. The factor det(G)^2 > 0
    # keeps the sign: points inside the rim get p^T C p < 0.
    g0, g1, g2 = homography.unbind(-1)
    adjugate = torch.stack([torch.linalg.cross(g1, g2), torch.linalg.cross(g2, g0),
                            torch.linalg.cross(g0, g1)], -2)
    r2 = (radius**2)[..., None, None]
    quad = adjugate[..., :2, :]
    conic = (matmul(quad.transpose(-1, -2), quad)
             - r2 * matmul(adjugate[..., 2:, :].transpose(-1, -2), adjugate[..., 2:, :]))
    return (conic / torch.linalg.matrix_norm(conic)[..., None, None]).to(out_dtype)


def normalize_conic(conic: Tensor) -> Tensor:
    """Scale ``(..., 3, 3)`` conics to unit Frobenius norm and negative determinant."""
    conic = 0.5 * (conic + conic.transpose(-1, -2))
    norm = torch.linalg.matrix_norm(conic)
    sign = torch.where(torch.linalg.det(conic) > 0, -1.0, 1.0).to(conic.dtype)
    return conic * (sign / norm)[..., None, None]


def project_rim(pose: Tensor, radius: Tensor | float, geometry: Geometry, t: Tensor) -> Tensor:
    """Rim landmarks in pixels: ``(B, 5)`` pose, ``(N,)`` or ``(B, N)`` t -> ``(B, N, 2)``."""
    return project(rim_points(pose, radius, t), geometry)


def pose_to_degrees(pose: Tensor) -> Tensor:
    """``(..., 5)`` pose with radians -> the public units (deg, deg, mm, mm, mm)."""
    return torch.cat([torch.rad2deg(pose[..., :2]), pose[..., 2:]], -1)


def pose_to_radians(pose: Tensor) -> Tensor:
    """``(..., 5)`` pose with degrees (public units) -> radians inside the library."""
    return torch.cat([torch.deg2rad(pose[..., :2]), pose[..., 2:]], -1)
