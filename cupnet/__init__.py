"""cupnet: hip cup 3D pose from one X-ray under cone-beam geometry.

The main entry points are re-exported lazily (importing ``cupnet`` stays cheap):
``cupnet.solve_pose``, ``cupnet.fit_ellipse``, ``cupnet.Geometry``, ``cupnet.load_model``.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "Geometry": "cupnet.geometry",
    "fit_ellipse": "cupnet.ellipse",
    "solve_pose": "cupnet.pose",
    "PoseSolution": "cupnet.pose",
    "load_model": "cupnet.model",
    "CupDetection": "cupnet.detection",
}
__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'cupnet' has no attribute {name!r}")
