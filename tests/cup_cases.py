"""Cup pose cases shared by the tests (imported as `cup_cases`; `tests` is shadowed by a
site-packages package of that name)."""

from __future__ import annotations

import math

import numpy as np
import torch

from cupnet.detection import CupDetection
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


def detection(ellipse: list[float], status: str = "ok", doubt: float | None = 0.5,
              check: bool = False) -> CupDetection:
    """A detected cup with ``ellipse`` ``(5,)`` px, its pose (20, 40, 0, 0, 900) or NaN for
    an ``error`` status: for the rules that pick among detections."""
    pose = np.full(5, np.nan) if status.startswith("error") else np.array([20, 40, 0, 0, 900.0])
    return CupDetection(pose=pose, alt_pose=None, ambiguous=False,
                        ellipse=np.asarray(ellipse, np.float64), landmarks=np.zeros((0, 2)),
                        weights=np.zeros(0), residual_px=0.1, status=status, doubt=doubt,
                        check=check)


def networks_not_reached(*args, **kwargs):
    """Stands in for a model's first network where a check must come before any."""
    raise AssertionError("the networks ran")
