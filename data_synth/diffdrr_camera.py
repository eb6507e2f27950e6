"""The one conversion between CONVENTIONS geometry and a DiffDRR 0.6.1 camera.

DiffDRR's camera frame has the source at the origin and the detector plane at ``z = sdd``;
with ``reverse_x_axis=False`` the pixel in row ``i``, column ``j`` sits at
``(delx (j - (W-1)/2) + x0, dely ((H-1)/2 - i) + y0, sdd)`` (``Detector._initialize_carm``).
CONVENTIONS' detector frame has the source at ``(0, 0, sdd)`` and pixel ``(u, v)`` at
``((u - u0) s, (v - v0) s, 0)``. So a detector-frame point ``(x, y, z)`` is the camera point
``(x, -y, sdd - z)`` (a proper rotation by pi about x, plus a shift), and pixels match when
``x0 = s ((W-1)/2 - u0)`` and ``y0 = s (v0 - (H-1)/2)``.

Traps handled here: ``reverse_x_axis=True`` (DiffDRR's default) would mirror the columns;
``DRR.perspective_projection`` puts the origin at the top-left pixel's corner, half a pixel
off CONVENTIONS; the subject's ``reorient`` matrix is composed before the pose.
"""

from __future__ import annotations

from typing import Any

import torch
from diffdrr.drr import DRR
from diffdrr.pose import RigidTransform
from torch import Tensor
from torchio import Subject

from cupnet.geometry import Geometry


def camera_from_detector(sdd: float) -> Tensor:
    """``(4, 4)`` float64 map of detector-frame points to DiffDRR camera points (an involution)."""
    return torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, sdd], [0, 0, 0, 1]],
                        dtype=torch.float64)


def make_drr(subject: Subject, geometry: Geometry, width: int, height: int,
             **kwargs: Any) -> DRR:
    """A DiffDRR renderer whose image pixel ``[i, j]`` is the CONVENTIONS pixel ``(u=j, v=i)``.

    ``geometry`` must be one image's (scalar fields); the pixels are square. ``kwargs`` go to
    :class:`diffdrr.drr.DRR` (e.g. ``renderer``, ``patch_size``).
    """
    sdd, spacing, u0, v0 = (float(t) for t in geometry.tensors())
    return DRR(subject, sdd=sdd, height=height, width=width, delx=spacing,
               x0=spacing * ((width - 1) / 2 - u0), y0=spacing * (v0 - (height - 1) / 2),
               reverse_x_axis=False, **kwargs)


def diffdrr_pose(drr: DRR, world_from_detector: Tensor) -> RigidTransform:
    """DiffDRR pose that renders the world seen from CONVENTIONS' detector frame.

    Args:
        drr: from :func:`make_drr` (gives the SDD and the subject's ``reorient``).
        world_from_detector: ``(4, 4)`` or ``(B, 4, 4)`` rigid map of detector-frame points to
            the subject's world coordinates (mm).
    Returns:
        the extrinsic ``E`` with ``E @ reorient = world_from_detector @ detector_from_camera``,
        as DiffDRR composes ``reorient`` first.
    """
    world_from_detector = torch.as_tensor(world_from_detector, dtype=torch.float64)
    detector_from_camera = camera_from_detector(drr.detector.sdd)
    reorient = drr.detector.reorient.matrix[0].double()
    extrinsic = world_from_detector @ detector_from_camera @ torch.linalg.inv(reorient)
    return RigidTransform(extrinsic.reshape(-1, 4, 4).to(drr.density.dtype))


def diffdrr_project(drr: DRR, pose: RigidTransform, points: Tensor) -> Tensor:
    """Project world points ``(B, N, 3)`` mm with DiffDRR; CONVENTIONS pixels ``(B, N, 2)``."""
    uv = drr.perspective_projection(pose, points.to(drr.density.dtype))
    return uv - 0.5  # DiffDRR's origin is the top-left pixel's corner, ours its centre
