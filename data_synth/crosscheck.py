"""Closed-form implant vs DiffDRR's render of the same implant voxelised (tests, benchmark).

The cup shell is voxelised with partial volumes (``oversample^3`` points per voxel) and
rendered by DiffDRR's Siddon ray tracer through the tested camera conversion; the closed form
is evaluated at the same pixel centres (one ray per pixel, as DiffDRR). Compared: the outer
edge of the shadow along rays from the rim ellipse's centre, and the integrated line integral.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from diffdrr.data import read
from torch import Tensor
from torchio import ScalarImage

from cupnet.ellipse import conic_to_params
from cupnet.geometry import Geometry, pose_to_radians, project_rim, rim_conic, rim_points
from data_synth.diffdrr_camera import diffdrr_pose, diffdrr_project, make_drr
from data_synth.implant import Cup, cup_part
from data_synth.raycast import render_parts


def voxelise_cup(cup: Cup, voxels: int, oversample: int = 2) -> tuple[Tensor, Tensor]:
    """Shell occupancy ``(voxels,) * 3`` in [0, 1] and its ``(4, 4)`` voxel-to-mm affine.

    The grid is a cube around the rim centre; voxel ``(i, j, k)`` is centred at
    ``corner + (i, j, k) * size`` in the detector frame.
    """
    centre, axis = cup.centre.double(), cup.axes[:, 1].double()
    size = (2 * cup.radius + 4) / voxels
    corner = centre - (voxels - 1) / 2 * size
    sub = (torch.arange(oversample, dtype=torch.float64) + 0.5) / oversample - 0.5
    line = (torch.arange(voxels, dtype=torch.float64)[:, None] + sub).reshape(-1) * size
    grid = torch.stack(torch.meshgrid(line, line, line, indexing="ij"), -1) + corner - centre
    distance = grid.norm(dim=-1)
    inside = ((distance <= cup.radius) & (distance >= cup.radius - cup.wall)
              & (grid @ axis <= 0)).double()
    n = voxels
    occupancy = inside.reshape(n, oversample, n, oversample, n, oversample).mean((1, 3, 5))
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= size
    affine[:3, 3] = corner
    return occupancy, affine


def render_voxelised(occupancy: Tensor, affine: Tensor, geometry: Geometry, width: int,
                     height: int) -> Tensor:
    """DiffDRR (Siddon) line integrals ``(H, W)`` of the occupancy volume (detector frame)."""
    subject = read(ScalarImage(tensor=occupancy[None].float(), affine=affine.numpy()),
                   orientation=None, center_volume=False)
    drr = make_drr(subject, geometry, width, height)
    with torch.no_grad():
        image = drr(diffdrr_pose(drr, torch.eye(4, dtype=torch.float64)))[0, 0]
    # DiffDRR rescales densities to [0, 1]; undo it to get occupancy x mm.
    return image.double() * float(occupancy.max())


def edge_radii(image: Tensor, centre: tuple[float, float], angles: Tensor, reach: float,
               level: float, step: float = 0.02) -> Tensor:
    """Outermost radius (px) along each angle where bilinear ``image`` reaches ``level``."""
    radii = torch.arange(0, reach, step, dtype=torch.float64)
    u = centre[0] + radii[None] * torch.cos(angles)[:, None]
    v = centre[1] + radii[None] * torch.sin(angles)[:, None]
    height, width = image.shape
    grid = torch.stack([(u + 0.5) / width * 2 - 1, (v + 0.5) / height * 2 - 1], -1)
    profile = torch.nn.functional.grid_sample(image[None, None].double(), grid[None],
                                              align_corners=False)[0, 0]
    above = profile >= level
    last = radii.numel() - 1 - torch.flip(above, [-1]).float().argmax(-1)
    # Interpolate the crossing between the last sample above and the next one below.
    lo = profile.gather(1, last[:, None])[:, 0]
    hi = profile.gather(1, (last + 1).clamp(max=radii.numel() - 1)[:, None])[:, 0]
    fraction = ((lo - level) / (lo - hi).clamp_min(1e-12)).clamp(0, 1)
    return radii[last] + fraction * step


@dataclass
class CrossCheck:
    """Agreement of the closed form with DiffDRR for one cup."""

    edge_mean_px: float  # mean signed edge offset, closed form - DiffDRR
    edge_median_abs_px: float  # median absolute edge offset over the angles
    edge_max_px: float  # largest absolute edge offset (voxel staircase of the reference)
    integral_rel: float  # |sum closed form - sum DiffDRR| / sum DiffDRR
    projection_px: float  # largest rim landmark difference, DiffDRR's projection vs cupnet's


def cross_check(pose_deg: tuple[float, ...], diameter: float, wall: float,
                geometry: Geometry, width: int, height: int, voxels: int = 64,
                angles: int = 180) -> CrossCheck:
    """Render one shell both ways and compare (``pose_deg``: public units)."""
    pose = pose_to_radians(torch.tensor(pose_deg, dtype=torch.float64))
    cup = Cup(pose=pose, radius=diameter / 2, wall=wall, mu_shell=1.0)
    closed = render_parts([cup_part(cup, supersample=1)], geometry, width, height).double()
    occupancy, affine = voxelise_cup(cup, voxels)
    reference = render_voxelised(occupancy, affine, geometry, width, height)

    cx, cy, a, _, _ = conic_to_params(rim_conic(pose[None], diameter / 2, geometry))[0].tolist()
    theta = torch.linspace(0, 2 * math.pi, angles + 1, dtype=torch.float64)[:-1]
    reach = 2 * a + 10
    offsets = (edge_radii(closed, (cx, cy), theta, reach, level=wall)
               - edge_radii(reference, (cx, cy), theta, reach, level=wall))

    t = torch.linspace(0, 2 * math.pi, 65, dtype=torch.float64)[:-1]
    subject = read(ScalarImage(tensor=occupancy[None].float(), affine=affine.numpy()),
                   orientation=None, center_volume=False)
    drr = make_drr(subject, geometry, width, height)
    projected = diffdrr_project(drr, diffdrr_pose(drr, torch.eye(4, dtype=torch.float64)),
                                rim_points(pose[None], diameter / 2, t))
    ours = project_rim(pose[None], diameter / 2, geometry, t)
    return CrossCheck(
        edge_mean_px=float(offsets.mean()),
        edge_median_abs_px=float(offsets.abs().median()),
        edge_max_px=float(offsets.abs().max()),
        integral_rel=float(abs(closed.sum() - reference.sum()) / reference.sum()),
        projection_px=float((projected.double() - ours).norm(dim=-1).max()),
    )
