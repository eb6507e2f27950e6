"""Cup pose cases shared by the tests (imported as `cup_cases`; `tests` is shadowed by a
site-packages package of that name)."""

from __future__ import annotations

import math

import torch

from cupnet.geometry import Geometry, pose_to_radians, project_rim


def paper_poses(n: int, generator: torch.Generator) -> torch.Tensor:
    """``(n, 5)`` poses of the paper's protocol in public units (deg, mm)."""
    lo = torch.tensor([0.0, -90.0, -100.0, -100.0, 100.0], dtype=torch.float64)
    hi = torch.tensor([50.0, 90.0, 100.0, 100.0, 520.0], dtype=torch.float64)
    return lo + (hi - lo) * torch.rand(n, 5, generator=generator, dtype=torch.float64)


def rim_landmarks(pose_deg: torch.Tensor, geometry: Geometry, diameter: float = 50.0,
                  n: int = 100) -> torch.Tensor:
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    return project_rim(pose_to_radians(pose_deg), diameter / 2, geometry, t)
