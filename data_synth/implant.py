"""Hip implant as closed-form solids: acetabular shell, liner, femoral head, stem, screws and
the cup's inserter.

The shell is the CONVENTIONS cup: a hemisphere of outer radius ``r`` whose rim circle is
``c + R (r cos t, 0, r sin t)``; its dome lies on the side of the rim plane away from the
opening, the points ``X`` with ``(X - c) . n <= 0`` where ``n`` is the cup axis
(:func:`cupnet.geometry.cup_axis`). Every solid is a sphere or an ellipsoid, optionally cut by
the rim plane, so each ray's line integral is exact (see :mod:`data_synth.raycast`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from cupnet.geometry import rotation
from data_synth.raycast import (
    Part,
    Rays,
    clip_halfspace,
    ellipsoid_interval,
    intersect,
    length,
    sphere_interval,
)


@dataclass
class Cup:
    """One acetabular component and what sits in it. Angles in radians, lengths in mm.

    Attributes:
        pose: ``(5,)`` (theta, phi rad; k, l, h mm) of the rim circle.
        radius: outer radius ``r`` (= the rim radius of CONVENTIONS).
        wall: shell thickness.
        mu_shell: shell attenuation (1/mm).
        porous_depth: depth of the porous outer layer (0: none); it has ``porous_density`` of
            the shell's attenuation.
        screw_holes: ``(K, 4)`` hole spheres through the dome (centre xyz, radius), mm.
        liner_inner: inner radius of the polyethylene liner (0: no liner); ``mu_liner``.
        head_radius: femoral head radius (0: none), centred at the rim centre; ``mu_head``.
    """

    pose: Tensor
    radius: float
    wall: float
    mu_shell: float
    porous_depth: float = 0.0
    porous_density: float = 0.6
    screw_holes: Tensor = field(default_factory=lambda: torch.zeros(0, 4))
    liner_inner: float = 0.0
    mu_liner: float = 0.0
    head_radius: float = 0.0
    mu_head: float = 0.0

    @property
    def centre(self) -> Tensor:
        return self.pose[2:5].float()

    @property
    def axes(self) -> Tensor:
        """``(3, 3)`` columns ``(e1, n, e2)``: the rim plane's basis and the cup axis."""
        return rotation(self.pose[0], self.pose[1]).float()


def cup_line_integral(cup: Cup, rays: Rays) -> Tensor:
    """Attenuation line integral ``(N,)`` of the shell, liner and head along ``rays``."""
    centre, axis = cup.centre, cup.axes[:, 1]
    # All spheres of a cup share its centre: one closest-approach computation for all, and
    # only the spheres the cup has.
    radii = {"outer": cup.radius, "inner": cup.radius - cup.wall,
             "core": cup.radius - cup.porous_depth, "liner": cup.liner_inner,
             "head": cup.head_radius}
    present = {"core": cup.porous_depth > 0, "liner": cup.liner_inner > 0,
               "head": cup.head_radius > 0}
    radii = {name: r for name, r in radii.items() if present.get(name, True)}
    row = {name: i for i, name in enumerate(radii)}
    balls = sphere_interval(rays, centre, torch.tensor(list(radii.values())))  # each (K, N)
    dome = clip_halfspace(balls, rays, centre, axis)
    outer = (dome[0][row["outer"]], dome[1][row["outer"]])
    inner = (dome[0][row["inner"]], dome[1][row["inner"]])
    lengths = length(dome)
    shell = lengths[row["outer"]] - lengths[row["inner"]]
    if "core" in row:  # the porous outer layer is less dense
        shell = shell - (1.0 - cup.porous_density) * (lengths[row["outer"]] - lengths[row["core"]])
    for hole in cup.screw_holes:
        ball = sphere_interval(rays, hole[:3], hole[3])
        shell = shell - (length(intersect(outer, ball)) - length(intersect(inner, ball)))
    total = cup.mu_shell * shell
    if "liner" in row:
        total = total + cup.mu_liner * (lengths[row["inner"]] - lengths[row["liner"]])
    if "head" in row:  # the head is a whole sphere, not cut by the rim plane
        total = total + cup.mu_head * (balls[1][row["head"]] - balls[0][row["head"]])
    return total


def cup_part(cup: Cup, supersample: int) -> Part:
    """The cup as a :class:`Part` (bounded by its sphere's box)."""
    centre = cup.centre
    bounds = torch.stack([centre - cup.radius, centre + cup.radius])
    return Part(lambda rays: cup_line_integral(cup, rays), bounds, supersample)


def frame_along(direction: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rotation whose first column is the unit ``direction (3,)``."""
    first = direction / np.linalg.norm(direction)
    helper = np.array([0.0, 0.0, 1.0]) if abs(first[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    second = np.cross(first, helper)
    second = second / np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)], -1)


@dataclass
class Ellipsoid:
    """A solid ellipsoid ``centre + axes @ diag(semi_axes) @ unit ball`` of attenuation ``mu``.

    ``hollow`` in ``[0, 1)``: the inner ellipsoid scaled by ``hollow`` has ``mu_inner``
    instead (a bone's cortex around its marrow). ``cut (3,)``: only the half
    ``(X - centre) . cut <= 0`` is kept (None: the whole), so a long half-ellipsoid is a rod
    of nearly constant section near its flat end. ``centre (3,)`` mm, ``axes (3, 3)``
    (columns the principal directions), ``semi_axes (3,)`` mm and ``cut`` may be given as
    arrays or tensors.
    """

    centre: Tensor
    axes: Tensor
    semi_axes: Tensor
    mu: float
    hollow: float = 0.0
    mu_inner: float = 0.0
    cut: Tensor | None = None

    def __post_init__(self) -> None:
        # Scenes are sampled in numpy (small-array maths costs ~5x less there); rays are torch.
        for name in ("centre", "axes", "semi_axes", "cut"):
            if getattr(self, name) is not None:
                setattr(self, name, torch.as_tensor(np.asarray(getattr(self, name)),
                                                    dtype=torch.float32))

    @classmethod
    def along(cls, start: np.ndarray, end: np.ndarray, radii: tuple[float, float], mu: float,
              **kwargs: float) -> Ellipsoid:
        """The ellipsoid spanning the segment ``start -> end`` (mm) with cross-section
        ``radii``."""
        axis = end - start
        semi = np.array([np.linalg.norm(axis) / 2, *radii])
        return cls((start + end) / 2, frame_along(axis), semi, mu, **kwargs)

    def line_integral(self, rays: Rays) -> Tensor:
        scales = torch.tensor([1.0, self.hollow] if self.hollow > 0 else [1.0])
        chords = ellipsoid_interval(rays, self.centre, self.axes, self.semi_axes, scales)
        if self.cut is not None:
            chords = clip_halfspace(chords, rays, self.centre, self.cut)
        if self.hollow <= 0:
            return self.mu * length(chords)[0]
        outer, inner = length(chords)
        return self.mu * (outer - inner) + self.mu_inner * inner

    def part(self, supersample: int = 1) -> Part:
        # Half-extent of an ellipsoid along world axis i: sqrt(sum_j (A_ij s_j)^2).
        extent = (self.axes * self.semi_axes).norm(dim=1)
        bounds = torch.stack([self.centre - extent, self.centre + extent])
        return Part(self.line_integral, bounds, supersample)
