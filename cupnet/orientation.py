"""The cup's orientation in Murray's three definitions (J Bone Joint Surg Br 1993;75:228).

A pose's ``theta`` and ``phi`` are Murray's *radiographic* anteversion and inclination, with
the detector plane taken for the patient's coronal plane and the image's vertical for the
longitudinal axis (CONVENTIONS.md). Surgeons and navigation systems mostly state the
*operative* angles and CT studies the *anatomic* ones, so a cup measured here is compared
with theirs through these functions. Each takes the cup's axis ``n`` (CONVENTIONS:
``(-sin phi cos theta, cos phi cos theta, sin theta)``: lateral, inferior and anterior parts
for a right hip in the usual AP display) and measures:

- operative anteversion: the longitudinal axis against ``n`` projected on the sagittal plane;
  operative inclination: ``n`` against the sagittal plane;
- anatomic anteversion: the transverse axis against ``n`` projected on the transverse plane;
  anatomic inclination: ``n`` against the longitudinal axis.

Inclinations carry ``phi``'s sign (the side, as in ``results.csv``); anteversions lie in
``[0, 90]`` as ``theta`` does. Pure, batched and differentiable; degrees in and out.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cupnet.batchwise import atan2, hypot
from cupnet.geometry import cup_axis, pose_to_radians


def _axis_parts(pose: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(lateral, inferior, anterior, phi)`` of the axes of poses ``(..., 5)`` deg / mm."""
    radians = pose_to_radians(pose)
    x, y, z = cup_axis(radians).unbind(-1)
    return x.abs(), y, z, radians[..., 1]


def operative_angles(pose: Tensor) -> Tensor:
    """Murray's operative anteversion and inclination of poses ``(..., 5)`` (theta, phi deg;
    k, l, h mm) -> ``(..., 2)`` deg: ``tan(OA) = tan(theta) / cos(phi)``, ``sin(OI) =
    sin(phi) cos(theta)``."""
    lateral, inferior, anterior, phi = _axis_parts(pose)
    anteversion = atan2(anterior, inferior)
    inclination = atan2(lateral, hypot(inferior, anterior))
    return torch.rad2deg(torch.stack([anteversion, torch.copysign(inclination, phi)], -1))


def anatomic_angles(pose: Tensor) -> Tensor:
    """Murray's anatomic anteversion and inclination of poses ``(..., 5)`` (theta, phi deg;
    k, l, h mm) -> ``(..., 2)`` deg: ``tan(AA) = tan(theta) / sin(phi)``, ``cos(AI) =
    cos(phi) cos(theta)``. Where the axis is the longitudinal axis (``theta = phi = 0``) the
    anatomic anteversion is undefined and given as 0."""
    lateral, inferior, anterior, phi = _axis_parts(pose)
    # Along the longitudinal axis both parts are 0, where atan2's and hypot's gradients are
    # 0 / 0: they are taken at a stand-in (1, 0), whose anteversion is 0 and whose radial
    # part is dropped, so the gradient there is 0 (a subgradient of the inclination's cone),
    # not NaN for the whole batch's step.
    axial = (lateral == 0) & (anterior == 0)
    lateral_, anterior_ = torch.where(axial, 1.0, lateral), torch.where(axial, 0.0, anterior)
    anteversion = atan2(anterior_, lateral_)
    radial = torch.where(axial, 0.0, hypot(lateral_, anterior_))
    inclination = atan2(radial, inferior)
    return torch.rad2deg(torch.stack([anteversion, torch.copysign(inclination, phi)], -1))
