"""Murray's operative and anatomic angles against hand cases, his conversion formulas and the
definitions measured on the rim circle itself."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cupnet.geometry import pose_to_radians, rim_points
from cupnet.orientation import anatomic_angles, operative_angles


def poses(angles: list[tuple[float, float]]) -> torch.Tensor:
    """Poses ``(N, 5)`` of the given (theta, phi) deg, somewhere in front of the detector."""
    rows = [[theta, phi, 10.0, -20.0, 300.0] for theta, phi in angles]
    return torch.tensor(rows, dtype=torch.float64)


@pytest.mark.parametrize(
    ("theta", "phi", "operative", "anatomic"),
    [
        # an edge-on rim: no anteversion in any definition, the inclinations all phi
        (0.0, 40.0, (0.0, 40.0), (0.0, 40.0)),
        # the axis in the sagittal plane: no operative inclination; the anatomic anteversion
        # is the whole turn from the transverse axis
        (20.0, 0.0, (20.0, 0.0), (90.0, 20.0)),
        # the projected axis horizontal: the sagittal projection is purely anterior
        (20.0, 90.0, (90.0, 70.0), (20.0, 90.0)),
        # a left hip mirrors a right one: inclinations change sign, anteversions do not
        (20.0, -90.0, (90.0, -70.0), (20.0, -90.0)),
    ],
)
def test_hand_derived_cases(theta: float, phi: float, operative: tuple[float, float],
                            anatomic: tuple[float, float]) -> None:
    pose = poses([(theta, phi)])
    np.testing.assert_allclose(operative_angles(pose)[0].numpy(), operative, atol=1e-9)
    np.testing.assert_allclose(anatomic_angles(pose)[0].numpy(), anatomic, atol=1e-9)


def test_murrays_conversion_formulas() -> None:
    rng = np.random.default_rng(0)
    theta, phi = rng.uniform(1, 60, 200), rng.uniform(1, 89, 200)
    ra, ri = np.radians(theta), np.radians(phi)
    expected_operative = np.degrees([np.arctan(np.tan(ra) / np.cos(ri)),
                                     np.arcsin(np.sin(ri) * np.cos(ra))]).T
    expected_anatomic = np.degrees([np.arctan(np.tan(ra) / np.sin(ri)),
                                    np.arccos(np.cos(ri) * np.cos(ra))]).T
    pose = poses(list(zip(theta, phi, strict=True)))
    np.testing.assert_allclose(operative_angles(pose).numpy(), expected_operative, atol=1e-9)
    np.testing.assert_allclose(anatomic_angles(pose).numpy(), expected_anatomic, atol=1e-9)
    # A worked case: radiographic 15 deg anteversion at 45 deg inclination.
    (oa, oi), (aa, ai) = (operative_angles(poses([(15.0, 45.0)]))[0].tolist(),
                          anatomic_angles(poses([(15.0, 45.0)]))[0].tolist())
    assert (round(oa, 2), round(oi, 2), round(aa, 2), round(ai, 2)) == (20.75, 43.08, 20.75,
                                                                        46.92)


def angle_to_plane(vector: np.ndarray, normal: np.ndarray) -> float:
    return math.degrees(math.asin(abs(vector @ normal)))


def angle_in_plane(vector: np.ndarray, normal: np.ndarray, reference: np.ndarray) -> float:
    """The angle between ``reference`` (in the plane) and ``vector`` projected on the plane."""
    projected = vector - (vector @ normal) * normal
    return math.degrees(math.acos(projected @ reference / np.linalg.norm(projected)))


def test_the_definitions_measured_on_the_rim_circle() -> None:
    # The axis as the rim plane's normal (the rim's own points, not cup_axis), pointing to
    # the patient's feet (+v); the planes of the detector frame: coronal = detector (normal
    # z, anterior), sagittal (normal x), transverse (normal y); a right hip (phi > 0) faces
    # the image's left, -x.
    x, y, z = np.eye(3)
    rng = np.random.default_rng(1)
    for theta, phi in zip(rng.uniform(2, 55, 40), rng.uniform(2, 88, 40), strict=True):
        pose = poses([(theta, phi)])
        t = torch.tensor([0.0, 2.0, 4.0], dtype=torch.float64)
        a, b, c = rim_points(pose_to_radians(pose), 26.0, t)[0].numpy()
        axis = np.cross(b - a, c - a)
        axis = axis / np.linalg.norm(axis) * np.sign(axis @ y)
        assert angle_to_plane(axis, z) == pytest.approx(theta, abs=1e-9)  # radiographic
        operative = [angle_in_plane(axis, x, y), angle_to_plane(axis, x)]
        anatomic = [angle_in_plane(axis, y, -x), math.degrees(math.acos(axis @ y))]
        np.testing.assert_allclose(operative_angles(pose)[0].numpy(), operative, atol=1e-8)
        np.testing.assert_allclose(anatomic_angles(pose)[0].numpy(), anatomic, atol=1e-8)


def test_gradients_match_finite_differences() -> None:
    pose = poses([(25.0, 40.0), (10.0, -70.0)]).requires_grad_()
    assert torch.autograd.gradcheck(operative_angles, (pose,))
    assert torch.autograd.gradcheck(anatomic_angles, (pose,))


def test_anatomic_angles_have_a_finite_gradient_on_the_longitudinal_axis() -> None:
    """At theta = phi = 0 (where a zero-initialised head starts) the gradient had been NaN
    for the whole batch; it is 0 there (a subgradient of the inclination's cone), and the
    other poses' gradients are those they have alone."""
    pose = torch.tensor([[0.0, 0.0, 0.0, 0.0, 300.0], [20.0, 30.0, 0.0, 0.0, 300.0]],
                        dtype=torch.float64, requires_grad=True)
    (anatomic_angles(pose)[:, 1] - 40).pow(2).sum().backward()
    assert torch.isfinite(pose.grad).all() and pose.grad[0].abs().sum() == 0
    alone = pose.detach()[1:].clone().requires_grad_()
    (anatomic_angles(alone)[:, 1] - 40).pow(2).sum().backward()
    torch.testing.assert_close(pose.grad[1:], alone.grad)
