"""The outline of the cup's sphere in the image, and how far landmarks lie from it.

A cup is a hemisphere whose rim is a great circle of its sphere, so the dome's outline in the
image is part of the sphere's outline: where the cone from the X-ray source tangent to the
sphere meets the detector. That outline depends on the centre ``(k, l, h)`` alone, and it is
long and sharp where the rim is not: a nearly edge-on rim is a thin ellipse whose tips, the
only evidence of its major axis and so of ``h``, are short and faint. The pose solver can fit
dome-outline landmarks beside the rim's (:func:`cupnet.pose.refine_pose_with_outline`).

Shapes: ``K`` cups, ``n`` outline points, ``M`` landmarks. Poses ``(theta, phi, k, l, h)``
in radians and mm, as inside :mod:`cupnet.pose`; geometry rows ``(sdd, spacing, u0, v0)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from cupnet.batchwise import atan2
from cupnet.geometry import Geometry, cup_axis, project


def _cone(centre: Tensor, radius: Tensor, sdd: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The vector from the source to each sphere centre ``w`` ``(K, 3)``, its length ``D``
    ``(K,)`` and the tangent cone's half-angle ``alpha`` ``(K,)`` (``sin alpha = r / D``)."""
    source = torch.zeros_like(centre)
    source[:, 2] = sdd
    w = centre - source
    distance = w.norm(dim=-1)
    return w, distance, torch.asin((radius / distance).clamp(max=1.0))


def sphere_outline(pose: Tensor, radius: Tensor, geometry: Geometry, n: int,
                   dome_only: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Points on the projected outline of each cup's sphere, their outward normals, and on
    which side of the rim plane each lies.

    Args:
        pose: ``(K, 5)`` rad / mm (only the rim plane's side needs the angles).
        radius: ``(K,)`` mm; geometry: fields ``(K,)`` or scalars.
        n: points per outline, equally spaced around the tangent circle on the sphere ...
        dome_only: ... or along its half on the dome's side of the rim plane (centred where
            the tangent circle lies farthest towards the dome), for twice the density where
            the dome is.
    Returns:
        points ``(K, n, 2)`` px; normals ``(K, n, 2)`` unit, pointing away from the sphere;
        side ``(K, n)``: the tangent point's height above the rim plane in radii, towards
        the dome (``> 0``: the outline of the dome, the cup's own; ``< 0``: the opening's
        side, where the sphere is not there to see).
    """
    sdd = geometry.tensors(pose.dtype, pose.device)[0].expand(pose.shape[0])
    centre = pose[:, 2:5]
    w, distance, alpha = _cone(centre, radius, sdd)
    axis = w / distance[:, None]
    # The tangent circle: centre c - (r^2 / D) axis, radius r cos alpha, normal to the axis.
    middle = centre - (radius**2 / distance)[:, None] * axis
    helper = torch.zeros_like(axis)
    helper[:, 0] = 1.0  # the axis points mostly along -z, never along x for a real cup
    e1 = torch.linalg.cross(axis, helper)
    e1 = e1 / e1.norm(dim=-1, keepdim=True)
    e2 = torch.linalg.cross(axis, e1)
    dome = -cup_axis(pose)
    if dome_only:  # half a turn about the direction of the dome in the circle's plane
        apex = atan2((e2 * dome).sum(-1), (e1 * dome).sum(-1))[:, None]
        t = apex + torch.linspace(-math.pi / 2, math.pi / 2, n, dtype=pose.dtype,
                                  device=pose.device)
    else:
        t = torch.arange(n, dtype=pose.dtype, device=pose.device).expand(len(pose), -1) * (
            2 * math.pi / n)
    rho = (radius * torch.cos(alpha))[:, None, None]

    def tangent_points(t: Tensor) -> Tensor:
        return middle[:, None] + rho * (torch.cos(t)[..., None] * e1[:, None]
                                        + torch.sin(t)[..., None] * e2[:, None])

    touching = tangent_points(t)
    points = project(touching, geometry)
    # Outward normals: the outline's tangent turned away from the projected sphere centre
    # (inside the convex outline).
    step = 1e-4
    tangent = project(tangent_points(t + step), geometry) - project(tangent_points(t - step),
                                                                  geometry)
    normals = torch.stack([tangent[..., 1], -tangent[..., 0]], -1)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    inside = project(centre[:, None], geometry)
    outwards = ((points - inside) * normals).sum(-1, keepdim=True)
    normals = torch.where(outwards < 0, -normals, normals)
    side = ((touching - centre[:, None]) * dome[:, None]).sum(-1) / radius[:, None]
    return points, normals, side


def outline_distances(centre: Tensor, points: Tensor, radius: Tensor, geom: Tensor
                      ) -> tuple[Tensor, Tensor]:
    """Signed distance of landmarks to the projected sphere outline, and its Jacobian.

    The distance is the angle between a landmark's ray and the tangent cone, times the
    detector distance one radian of ray angle spans there (``|d|^2 / (sdd s)`` px for the
    ray ``d`` from the source): the distance along the outline's normal to first order
    where the outline's normal is radial about the principal point. Elsewhere the scale is
    off by a little (a review's exact form, ``(psi - alpha) / |grad_p psi|``: up to 2.5 % for
    k, l within 100 mm, 18 % at 250 mm, far more for a sphere near the source). Zero stays
    zero, so landmarks on the outline give the same pose; off it, the residuals are weighted
    by that much.

    Args:
        centre: ``(B, 3)`` sphere centres (k, l, h) mm.
        points: ``(B, M, 2)`` landmarks px; radius: ``(B,)`` mm; geom: ``(B, 4)`` rows.
    Returns:
        distances ``(B, M)`` px, positive outside the outline, and their Jacobian
        ``(B, M, 3)`` w.r.t. ``(k, l, h)`` (px / mm).
    """
    sdd, spacing, u0, v0 = (g[:, None] for g in geom.unbind(-1))
    ray = torch.stack([(points[..., 0] - u0) * spacing, (points[..., 1] - v0) * spacing,
                       -sdd.expand_as(points[..., 0])], -1)  # (B, M, 3) source -> landmark
    w, distance, alpha = _cone(centre, radius, sdd[:, 0])
    axis = (w / distance[:, None])[:, None]  # (B, 1, 3)
    length = ray.norm(dim=-1, keepdim=True)
    direction = ray / length
    cos_psi = (direction * axis).sum(-1, keepdim=True)
    across = direction - cos_psi * axis  # the ray's direction away from the axis
    sin_psi = across.norm(dim=-1, keepdim=True)
    psi = atan2(sin_psi, cos_psi)[..., 0]
    px_per_rad = length[..., 0] ** 2 / (sdd * spacing)
    # d psi / d w = -(direction - cos psi axis) / (D sin psi); d alpha / d w = -tan(alpha) axis / D
    d_psi = -across / (distance[:, None, None] * sin_psi.clamp_min(1e-12))
    d_alpha = -(torch.tan(alpha) / distance)[:, None, None] * axis
    return (psi - alpha[:, None]) * px_per_rad, (d_psi - d_alpha) * px_per_rad[..., None]


def over_dome(points: Tensor, pose: Tensor, geometry: Geometry) -> Tensor:
    """Whether image points lie on the dome's side of the projected rim centre (split by the
    line through it across the projected cup axis, a straight stand-in for the perspective
    boundary through the rim's tips): the half of the rim over the dome's own shadow, whose
    visible edge is the shell's inner surface (the outer rim's edge is hidden in the metal
    there), not the rim the pose is of.

    Args:
        points: ``(K, N, 2)`` px; pose: ``(K, 5)`` rad / mm; geometry: fields ``(K,)`` or
            scalars.
    Returns:
        ``(K, N)`` bool.
    """
    centre = pose[:, 2:5]
    ends = project(torch.stack([centre, centre - cup_axis(pose)], 1), geometry)  # (K, 2, 2)
    towards_dome = ends[:, 1] - ends[:, 0]
    return ((points - ends[:, :1]) * towards_dome[:, None]).sum(-1) > 0
