"""Forward model against an independent numpy implementation of CONVENTIONS.md."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from cup_cases import paper_poses

from cupnet.ellipse import algebraic_residual, conic_to_params
from cupnet.geometry import (
    Geometry,
    cup_axis,
    mm_to_pixels,
    pixels_to_mm,
    pose_to_radians,
    project,
    project_rim,
    rim_conic,
    rotation,
)
from cupnet.pose import geometry_problems


def numpy_rim_pixels(theta_deg, phi_deg, k, l_, h, r, sdd, spacing, u0, v0, t):
    """CONVENTIONS written out by hand: Rz(phi) @ Rx(theta), c + R (r cos t, 0, r sin t)."""
    a, p = math.radians(theta_deg), math.radians(phi_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rz = np.array([[math.cos(p), -math.sin(p), 0], [math.sin(p), math.cos(p), 0], [0, 0, 1]])
    local = np.stack([r * np.cos(t), np.zeros_like(t), r * np.sin(t)], 1)
    world = np.array([k, l_, h]) + local @ (rz @ rx).T
    scale = sdd / (sdd - world[:, 2])
    return np.stack([u0 + scale * world[:, 0] / spacing, v0 + scale * world[:, 1] / spacing], 1)


def test_projection_matches_numpy_reference(generator):
    poses = paper_poses(20, generator)
    geometry = Geometry(1100.0, 0.3, 511.5, 480.0)
    t = torch.linspace(0, 2 * math.pi, 37, dtype=torch.float64)
    ours = project_rim(pose_to_radians(poses), 27.0, geometry, t).numpy()
    for pose, got in zip(poses.tolist(), ours, strict=True):
        want = numpy_rim_pixels(*pose, 27.0, 1100.0, 0.3, 511.5, 480.0, t.numpy())
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_cup_axis_is_the_conventions_formula(generator):
    poses = pose_to_radians(paper_poses(50, generator))
    th, ph = poses[:, 0], poses[:, 1]
    want = torch.stack([-torch.sin(ph) * torch.cos(th), torch.cos(ph) * torch.cos(th),
                        torch.sin(th)], -1)
    torch.testing.assert_close(cup_axis(poses), want)
    rot = rotation(th, ph)
    torch.testing.assert_close(rot @ rot.transpose(-1, -2), torch.eye(3, dtype=torch.float64)
                               .expand_as(rot))


def test_inclination_sign_follows_conventions():
    """phi > 0 tilts the projected axis towards -u (the image's left)."""
    pose = pose_to_radians(torch.tensor([[20.0, 40.0, 0.0, 0.0, 300.0]], dtype=torch.float64))
    assert cup_axis(pose)[0, 0] < 0 and cup_axis(pose)[0, 1] > 0


def test_rim_conic_contains_projected_rim_and_matches_a_fitted_ellipse(generator):
    import cv2

    poses = paper_poses(30, generator)
    poses[:, 0] = poses[:, 0].clamp(min=5.0)  # well-defined ellipses for OpenCV
    geometry = Geometry(1040.0, 0.2, 600.0, 500.0)
    t = torch.linspace(0, 2 * math.pi, 721, dtype=torch.float64)[:-1]
    points = project_rim(pose_to_radians(poses), 25.0, geometry, t)
    conic = rim_conic(pose_to_radians(poses), 25.0, geometry)
    params = conic_to_params(conic)
    # Every projected rim point lies on the conic (residual relative to the conic's scale).
    scale = (points**2).sum(-1).max() + 1
    assert algebraic_residual(conic, points).abs().max() / scale < 1e-12
    for pts, p in zip(points.numpy(), params.numpy(), strict=True):
        (cx, cy), (w, h), ang = cv2.fitEllipseDirect(pts.astype(np.float32))
        assert abs(cx - p[0]) < 1e-2 and abs(cy - p[1]) < 1e-2
        assert abs(max(w, h) / 2 - p[2]) < 1e-2 and abs(min(w, h) / 2 - p[3]) < 1e-2


def test_pixels_mm_round_trip():
    geometry = Geometry(1000.0, 0.25, 100.0, 50.0)
    uv = torch.tensor([[[0.0, 0.0], [100.0, 50.0], [399.5, -20.0]]], dtype=torch.float64)
    xy = pixels_to_mm(uv, geometry)
    torch.testing.assert_close(xy[0, 1], torch.zeros(2, dtype=torch.float64))
    torch.testing.assert_close(mm_to_pixels(xy, geometry), uv)


def test_default_principal_point_is_image_centre():
    g = Geometry.for_image(1024, 768, 1000.0, 0.2)
    assert (g.principal_u, g.principal_v) == (511.5, 383.5)


def test_one_row_gives_the_fields_of_its_batch_as_floats() -> None:
    """A synthetic sample's row (sdd, spacing, u0, v0): one image's geometry, as its batch's
    row gives it."""
    rows = torch.tensor([[1000.0, 0.2, 255.5, 250.0], [980.0, 0.15, 300.25, 260.0]],
                        dtype=torch.float64)
    one, batch = Geometry.from_row(rows[1]), Geometry.from_rows(rows)
    assert all(type(value) is float for value in vars(one).values())
    assert vars(one) == {name: float(value[1]) for name, value in vars(batch).items()}
    assert one == Geometry(sdd=980.0, pixel_spacing=0.15, principal_u=300.25, principal_v=260.0)


@pytest.mark.parametrize("field, value, word", [("sdd", -1.0, "source-to-detector"),
                                                ("sdd", 0.0, "source-to-detector"),
                                                ("pixel_spacing", 0.0, "pixel spacing"),
                                                ("pixel_spacing", math.inf, "pixel spacing"),
                                                ("principal_u", math.nan, "principal point"),
                                                ("principal_v", math.nan, "principal point")])
def test_geometry_problems_name_the_bad_value_of_its_item(field, value, word):
    """Each item's reason, None where it is usable, whatever shares its batch."""
    fields = dict(sdd=[1000.0] * 3, pixel_spacing=[0.2] * 3, principal_u=[0.0] * 3,
                  principal_v=[0.0] * 3)
    fields[field][1] = value
    problems = geometry_problems(Geometry(**{k: torch.tensor(v) for k, v in fields.items()}),
                                 torch.full((3,), 25.0, dtype=torch.float64))
    assert problems[0] is None and problems[2] is None and word in problems[1]


def test_a_geometry_field_that_is_no_number_is_named():
    with pytest.raises(TypeError, match="geometry sdd must be a number"):
        Geometry("1040", 0.2, 0.0, 0.0).tensors()


def test_rim_conic_of_a_float32_pose_is_the_float64_ellipse() -> None:
    """A pixel conic is ill-conditioned: built in float32 (a network's dtype) it was no
    ellipse for 38 % of the paper's poses on a 2048 px detector at 0.2 mm (this one among
    them); built in float64 and given back in float32 it is the ellipse."""
    geometry = Geometry.for_image(2048, 1536, 1040.0, 0.2)
    pose = pose_to_radians(torch.tensor([[10.0, -60.0, -80.0, 60.0, 200.0]], dtype=torch.float64))
    exact = conic_to_params(rim_conic(pose, 25.0, geometry))
    single = rim_conic(pose.float(), 25.0, geometry)
    assert single.dtype == torch.float32
    got = conic_to_params(single.double())
    assert torch.isfinite(got).all()
    np.testing.assert_allclose(got.numpy(), exact.numpy(), atol=0.05)


def test_integer_pixels_and_points_are_taken_as_numbers() -> None:
    """Integer inputs (a heatmap's argmax) had cast the geometry to integers: a spacing of
    0.2 became 0, so pixels_to_mm gave 0 mm and mm_to_pixels and project inf."""
    geometry = Geometry.for_image(2048, 1536, 1040.0, 0.2)
    pixels = torch.tensor([[1100, 800]])
    np.testing.assert_allclose(pixels_to_mm(pixels, geometry).numpy(),
                               pixels_to_mm(pixels.double(), geometry).numpy())
    mm = torch.tensor([[15, 6]])
    np.testing.assert_allclose(mm_to_pixels(mm, geometry).numpy(),
                               mm_to_pixels(mm.double(), geometry).numpy())
    points = torch.tensor([[10, 20, 300]])
    np.testing.assert_allclose(project(points, geometry).numpy(),
                               project(points.double(), geometry).numpy())
