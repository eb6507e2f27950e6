"""Closed-form line integrals against hand-derived chords and solid volumes."""

from __future__ import annotations

import math

import torch

from cupnet.geometry import Geometry
from data_synth.implant import Cup, Ellipsoid, cup_line_integral, cup_part
from data_synth.raycast import (
    clip_halfspace,
    detector_rays,
    length,
    render_parts,
    sphere_interval,
)

SDD = 1040.0


def central_ray() -> torch.Tensor:
    return detector_rays(Geometry(SDD, 1.0, 0.0, 0.0), torch.zeros(1), torch.zeros(1))


def test_sphere_chords_match_pythagoras():
    geometry = Geometry(SDD, 0.5, 0.0, 0.0)
    u = torch.tensor([0.0, 10.0, 30.0, 80.0])
    rays = detector_rays(geometry, u, torch.zeros(4))
    centre, radius = torch.tensor([0.0, 0.0, 300.0]), 25.0
    chord = length(sphere_interval(rays, centre, radius))
    # Distance of the sphere centre from each ray (float64), then 2 sqrt(r^2 - d^2).
    exact = detector_rays(geometry, u.double(), torch.zeros(4, dtype=torch.float64))
    offset = centre.double() - exact.source
    along = offset @ exact.dirs
    distance = torch.sqrt((offset * offset).sum() - along**2)
    expected = 2 * torch.sqrt((radius**2 - distance**2).clamp_min(0))
    torch.testing.assert_close(chord.double(), expected, atol=2e-3, rtol=0)
    assert chord[-1] == 0  # 80 px * 0.5 mm at z = 300 passes far outside


def test_dome_clip_keeps_the_side_away_from_the_opening():
    rays = central_ray()
    centre = torch.tensor([0.0, 0.0, 300.0])
    ball = sphere_interval(rays, centre, 20.0)
    towards_source = torch.tensor([0.0, 0.0, 1.0])
    # Opening towards the source: the ray crosses the dome from the rim plane down, 20 mm.
    torch.testing.assert_close(length(clip_halfspace(ball, rays, centre, towards_source)),
                               torch.tensor([20.0]), atol=1e-3, rtol=0)
    shifted = centre + torch.tensor([0.0, 0.0, 5.0])
    torch.testing.assert_close(length(clip_halfspace(ball, rays, shifted, -towards_source)),
                               torch.tensor([15.0]), atol=1e-3, rtol=0)


def test_cup_shell_projects_its_volume():
    """Nearly parallel rays: sum of line integrals x pixel area = the shell's volume."""
    sdd = 1e6  # source far away: magnification 1 within 1e-4
    spacing, size = 0.5, 160
    geometry = Geometry.for_image(size, size, sdd, spacing)
    radius, wall = 30.0, 4.0
    pose = torch.tensor([math.radians(35.0), math.radians(20.0), 3.0, -2.0, 50.0],
                        dtype=torch.float64)
    cup = Cup(pose=pose, radius=radius, wall=wall, mu_shell=1.0)
    image = render_parts([cup_part(cup, supersample=3)], geometry, size, size)
    volume = float(image.double().sum()) * spacing**2 / (sdd / (sdd - 50.0)) ** 2
    expected = 2 / 3 * math.pi * (radius**3 - (radius - wall) ** 3)
    assert abs(volume - expected) / expected < 2e-3


def test_hollow_ellipsoid_volume():
    sdd, spacing, size = 1e6, 0.5, 120
    geometry = Geometry.for_image(size, size, sdd, spacing)
    semi = torch.tensor([25.0, 12.0, 9.0])
    axes = torch.linalg.qr(torch.tensor([[1.0, 0.3, 0.2], [0.1, 1.0, -0.4], [0.2, 0.5, 1.0]]))[0]
    body = Ellipsoid(torch.tensor([1.0, 2.0, 40.0]), axes, semi, mu=1.0, hollow=0.5,
                     mu_inner=0.25)
    image = render_parts([body.part(supersample=2)], geometry, size, size)
    volume = float(image.double().sum()) * spacing**2
    full = 4 / 3 * math.pi * float(semi.prod())
    expected = full * (1 - 0.5**3) + 0.25 * full * 0.5**3
    assert abs(volume - expected) / expected < 3e-3


def test_a_cut_ball_keeps_the_half_behind_its_cut_with_its_centroid_there():
    """Hand-derived: any plane through a ball's centre halves it, and a half ball's centroid
    lies 3 R / 8 from its flat face. Near-parallel rays (a far source) make the image a
    projection along z, so the image's volume and centroid are the solid's."""
    sdd, spacing, size = 1e6, 0.25, 160
    geometry = Geometry.for_image(size, size, sdd, spacing)
    radius, cut = 15.0, torch.tensor([0.6, -0.8, 0.0])
    ball = Ellipsoid(torch.tensor([0.0, 0.0, 60.0]), torch.eye(3), torch.full((3,), radius),
                     mu=1.0, cut=cut)
    image = render_parts([ball.part(supersample=2)], geometry, size, size).double()
    volume = float(image.sum()) * spacing**2
    assert abs(volume - 2 / 3 * math.pi * radius**3) / volume < 3e-3
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64),
                          torch.arange(size, dtype=torch.float64), indexing="ij")
    centroid_mm = (torch.stack([(image * u).sum(), (image * v).sum()]) / image.sum()
                   - (size - 1) / 2) * spacing
    # the kept half is (X - centre) . cut <= 0: its centroid 3 R / 8 along -cut
    assert torch.allclose(centroid_mm, -3 * radius / 8 * cut[:2].double(), atol=0.02)


def test_edge_refinement_matches_full_supersampling():
    """Supersampling only edge pixels gives the image that supersampling every pixel gives."""
    from data_synth.raycast import detector_rays, subpixel_grid

    geometry = Geometry(1040.0, 0.8, 40.3, 35.6)
    pose = torch.tensor([math.radians(30.0), math.radians(50.0), 4.0, -3.0, 250.0],
                        dtype=torch.float64)
    holes = torch.tensor([[4.0, -3.0 - 20.0, 250.0 - 12.0, 3.0]])
    cup = Cup(pose=pose, radius=26.0, wall=3.5, mu_shell=0.2, porous_depth=1.0,
              screw_holes=holes, liner_inner=15.0, mu_liner=0.003, head_radius=14.0,
              mu_head=0.4)
    refined = render_parts([cup_part(cup, supersample=3)], geometry, 96, 80)
    u, v = subpixel_grid((0, 96, 0, 80), 3)
    full = cup_line_integral(cup, detector_rays(geometry, u.reshape(-1), v.reshape(-1)))
    full = torch.nn.functional.avg_pool2d(full.reshape(u.shape)[None, None], 3)[0, 0]
    assert (refined - full).abs().max() < 1e-3
    assert (refined - full).abs().mean() < 1e-5
