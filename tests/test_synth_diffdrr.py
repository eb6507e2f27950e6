"""The CONVENTIONS <-> DiffDRR conversion and the closed-form implant against DiffDRR."""

from __future__ import annotations

import math

import pytest
import torch

from cupnet.geometry import Geometry, pose_to_radians, project_rim, rim_points
from data_synth.build_bank import WORLD_FROM_DETECTOR_AP
from data_synth.crosscheck import cross_check
from data_synth.diffdrr_camera import diffdrr_pose, diffdrr_project, make_drr


@pytest.fixture(scope="module")
def example_ct():
    """A small random CT read the way DiffDRR reads its example (AP reorientation)."""
    from diffdrr.data import read
    from torchio import ScalarImage

    volume = torch.rand(1, 24, 20, 16, generator=torch.Generator().manual_seed(0)) * 1000
    affine = torch.diag(torch.tensor([-8.0, 8.0, 10.0, 1.0])).double().numpy()
    return read(ScalarImage(tensor=volume, affine=affine), orientation="AP")


def test_diffdrr_projection_matches_cupnet_in_a_ct_world(example_ct):
    """DiffDRR's own projection of the rim = cupnet's forward model, with an AP reorient."""
    geometry = Geometry(1040.0, 0.9, 70.3, 44.8)  # off-centre principal point, W != H
    drr = make_drr(example_ct, geometry, 128, 96)
    world_from_detector = torch.eye(4, dtype=torch.float64)
    world_from_detector[:3, :3] = WORLD_FROM_DETECTOR_AP
    world_from_detector[:3, 3] = torch.tensor([12.0, -30.0, 40.0])
    pose = pose_to_radians(torch.tensor([[35.0, 40.0, 20.0, -15.0, 300.0],
                                         [10.0, -70.0, -40.0, 25.0, 150.0]],
                                        dtype=torch.float64))
    t = torch.linspace(0, 2 * math.pi, 65, dtype=torch.float64)[:-1]
    points = rim_points(pose, torch.tensor([27.0, 22.0], dtype=torch.float64), t)
    world = points @ world_from_detector[:3, :3].T + world_from_detector[:3, 3]
    ours = project_rim(pose, torch.tensor([27.0, 22.0], dtype=torch.float64), geometry, t)
    for i in range(2):
        theirs = diffdrr_project(drr, diffdrr_pose(drr, world_from_detector), world[i : i + 1])
        assert (theirs[0].double() - ours[i]).norm(dim=-1).max() < 0.05


def test_rendered_pixels_follow_the_conversion(example_ct):
    """A render's column j / row i is CONVENTIONS (u=j, v=i): moving the principal point by
    whole pixels shifts the image by as many pixels (no mirroring, no half-pixel offset)."""
    base = Geometry(1040.0, 2.0, 31.5, 31.5)
    moved = Geometry(1040.0, 2.0, 34.5, 29.5)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = WORLD_FROM_DETECTOR_AP
    pose[:3, 3] = -WORLD_FROM_DETECTOR_AP @ torch.tensor([0.0, 0.0, 200.0], dtype=torch.float64)
    images = []
    for geometry in (base, moved):
        drr = make_drr(example_ct, geometry, 64, 64)
        with torch.no_grad():
            images.append(drr(diffdrr_pose(drr, pose))[0, 0])
    # Detector point (x, y) sits at u = u0 + x / s: +3 columns, -2 rows, so
    # moved[i, j] = base[i + 2, j - 3].
    torch.testing.assert_close(images[1][:-2, 3:], images[0][2:, :-3], atol=1e-3, rtol=1e-4)


@pytest.mark.parametrize(
    ("pose", "diameter", "wall"),
    [((30.0, 40.0, 8.0, -5.0, 300.0), 54.0, 4.0), ((70.0, -20.0, -10.0, 5.0, 200.0), 48.0, 3.0)],
)
def test_closed_form_cup_matches_diffdrr_render(pose, diameter, wall):
    check = cross_check(pose, diameter, wall, Geometry(1040.0, 1.2, 45.7, 41.2), 96, 88)
    assert check.projection_px < 0.05
    assert abs(check.edge_mean_px) < 0.25 and check.edge_median_abs_px < 0.25
    assert check.integral_rel < 0.02
