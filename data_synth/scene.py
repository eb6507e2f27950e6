"""Random scenes: imaging geometry, cup poses placed in the field of view, implants and bones.

Everything random comes from one ``numpy.random.Generator``, so a scene is a pure function of
the config and the generator's state. Anatomical directions in the detector frame follow the
usual AP display of CONVENTIONS: image left (-x) is the patient's right, +y is inferior, +z
(towards the source) anterior; a right hip (projected cup axis to the image's left,
``phi > 0``) has its lateral side at -x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from cupnet.geometry import Geometry, pose_to_radians, project_rim
from data_synth.config import SynthConfig
from data_synth.implant import Cup, Ellipsoid, cup_part, frame_along
from data_synth.raycast import Part

MAX_CUPS = 2
RIM_CHECK_POINTS = 32


@dataclass
class Scene:
    """One image's ground truth and solids (lengths mm, pose angles degrees).

    Attributes:
        geometry: scalar-field CONVENTIONS geometry.
        width, height: image size (px).
        field_radius: radius of the image intensifier's circular field (px, inf: none).
        poses: ``(n, 5)`` float64 public units, ``n`` in ``0..MAX_CUPS``.
        diameters: ``(n,)`` float64 cup outer diameters.
        nominal_diameter: the image's cup diameter as a user would give it (mm), also for an
            image without a cup.
        metal: implant parts (shells, liners, heads, stems, screws, inserters).
        bones: procedural pelvis and femur parts.
    """

    geometry: Geometry
    width: int
    height: int
    field_radius: float
    poses: Tensor
    diameters: Tensor
    nominal_diameter: float
    metal: list[Part]
    bones: list[Part]


def uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


def reflect_into(values: np.ndarray | float, bounds: tuple[float, float]) -> np.ndarray:
    """``values`` folded into ``[lo, hi]`` by reflection at its ends (a triangle wave).

    A value drawn near a range's end plus noise that leaves it comes back by as much as it
    went beyond; clipping would pile such draws onto the end itself (a bilateral second
    cup at exactly 0 deg of anteversion, edge-on, or at the nearest h allowed).
    """
    lo, hi = bounds
    span = hi - lo
    if span <= 0:
        return np.full_like(np.asarray(values, dtype=float), lo)
    folded = np.mod(np.asarray(values, dtype=float) - lo, 2 * span)
    return lo + span - np.abs(folded - span)


def sample_geometry(config: SynthConfig, rng: np.random.Generator) -> Geometry:
    """SDD, pixel spacing and a principal point near the image centre."""
    width, height = config.image_size
    sdd = uniform(rng, config.sdd_mm)
    if config.pixel_spacing_mm is not None:
        spacing = uniform(rng, config.pixel_spacing_mm)
    else:
        spacing = uniform(rng, config.detector_width_mm) / width
    offset = rng.uniform(-1, 1, size=2) * config.principal_offset_frac * np.array([width, height])
    return Geometry(sdd, spacing, (width - 1) / 2 + offset[0], (height - 1) / 2 + offset[1])


def rims_inside(poses: Tensor, radii: Tensor, geometry: Geometry, width: int, height: int,
                field_radius: float, margin: float) -> Tensor:
    """Whether every cup's projected rim lies inside the field of view.

    Args:
        poses: ``(T, n, 5)`` candidates, public units. radii: ``(n,)`` mm.
    Returns:
        ``(T,)`` bool: all rims within ``margin`` px of the image border and of the circle.
    """
    t = torch.linspace(0, 2 * math.pi, RIM_CHECK_POINTS + 1, dtype=torch.float64)[:-1]
    flat = pose_to_radians(poses.reshape(-1, 5))
    rim = project_rim(flat, radii.repeat(poses.shape[0]), geometry, t)  # (T * n, N, 2)
    u, v = rim[..., 0], rim[..., 1]
    centre_u, centre_v = (width - 1) / 2, (height - 1) / 2
    inside = ((u >= margin) & (u <= width - 1 - margin) & (v >= margin)
              & (v <= height - 1 - margin)
              & ((u - centre_u) ** 2 + (v - centre_v) ** 2 <= (field_radius - margin) ** 2))
    return inside.all(-1).reshape(poses.shape[:2]).all(-1)


def sample_poses(config: SynthConfig, rng: np.random.Generator, geometry: Geometry,
                 field_radius: float, bilateral: bool) -> tuple[Tensor, Tensor]:
    """Cup poses ``(n, 5)`` public units and diameters ``(n,)`` mm placed in the field.

    ``theta, phi, h`` and the diameter follow the config; ``k, l`` are redrawn until the rim
    ellipse(s) fit, then shrunk towards the principal point, where a cup that fits at all
    fits; one that does not fit even there is kept there. A bilateral pair puts the second
    cup on the other hip (``phi`` mirrored, ``k`` shifted by the inter-hip distance); when
    no draw fits both, one cup is kept.
    """
    width, height = config.image_size
    tries = config.placement_tries
    margin = config.field_margin * min(width, height)
    theta, phi, h = (uniform(rng, config.theta_deg), uniform(rng, config.phi_deg),
                     uniform(rng, config.h_mm))
    diameters = [uniform(rng, config.cup_diameter_mm)]
    k = rng.uniform(*config.k_mm, size=tries)
    l_ = rng.uniform(*config.l_mm, size=tries)
    first = np.stack([np.full(tries, theta), np.full(tries, phi), k, l_, np.full(tries, h)], -1)
    candidates = [first]
    if bilateral:
        side = 1.0 if phi > 0 else -1.0  # the other hip lies on the image's right of a right hip
        jitter = rng.normal(0, [6.0, 6.0, 0, 6.0, 20.0])
        second = first.copy()
        second[:, 0] = reflect_into(theta + jitter[0], config.theta_deg)
        second[:, 1] = reflect_into(-phi + jitter[1], config.phi_deg)
        second[:, 2] = k + side * uniform(rng, config.bilateral_separation_mm)
        second[:, 3] = l_ + jitter[3]
        second[:, 4] = reflect_into(h + jitter[4], config.h_mm)
        candidates.append(second)
        diameters.append(diameters[0])  # one diameter per image, as meta.csv holds
    poses = torch.as_tensor(np.stack(candidates, 1))  # (T, n, 5)
    radii = torch.tensor(diameters, dtype=torch.float64) / 2
    fits = rims_inside(poses, radii, geometry, width, height, field_radius, margin)
    if fits.any():
        return poses[int(fits.nonzero()[0])], radii * 2
    if bilateral:
        return sample_poses(config, rng, geometry, field_radius, bilateral=False)
    # Shrink towards the principal point, where a cup that fits at all fits.
    for shrink in (0.5, 0.25, 0.0):
        pose = poses[:1, :1].clone()
        pose[..., 2:4] *= shrink
        if rims_inside(pose, radii[:1], geometry, width, height, field_radius, margin).any():
            break
    return pose[0], radii[:1] * 2


def dome_holes(rng: np.random.Generator, cup: Cup, pose: Tensor) -> tuple[Tensor, Tensor]:
    """1-3 holes through a cup's dome, clustered in one sector 15-60 degrees from its pole.

    Args:
        pose: ``(5,)`` the cup's pose, public units (deg, mm), float64.
    Returns:
        ``(K, 4)`` hole spheres (centre xyz in the wall's middle, radius; mm, float64) and
        ``(K, 3)`` their unit directions from the cup's centre.
    """
    count = int(rng.integers(1, 4))
    polar = np.deg2rad(rng.uniform(15, 60, count))
    azimuth = rng.uniform(0, 2 * np.pi) + rng.uniform(-0.8, 0.8, count)
    local = np.stack([np.sin(polar) * np.cos(azimuth), -np.cos(polar),
                      np.sin(polar) * np.sin(azimuth)], -1)
    dirs = torch.as_tensor(local) @ cup.axes.double().T
    centres = pose[2:5] + (cup.radius - cup.wall / 2) * dirs
    hole_radius = torch.as_tensor(rng.uniform(2.5, 3.5, count))[:, None]
    return torch.cat([centres, hole_radius], -1), dirs


def sample_cup(config: SynthConfig, rng: np.random.Generator, pose: Tensor, diameter: float
               ) -> Cup:
    """Shell, liner, head and screw holes of one cup (``pose (5,)`` public units)."""
    radius = diameter / 2
    wall = uniform(rng, config.shell_wall_mm)
    pose_rad = pose_to_radians(pose)
    cup = Cup(pose=pose_rad, radius=radius, wall=wall, mu_shell=uniform(rng, config.mu_shell))
    if rng.random() < config.p_porous_rim:
        cup.porous_depth = min(rng.uniform(0.5, 1.5), wall * 0.5)
    if rng.random() < config.p_screw_holes:
        cup.screw_holes = dome_holes(rng, cup, pose)[0].float()
    head = rng.random() < config.p_head
    inner = radius - wall
    if head:
        # Heads too big for a small shell come down to what fits with a thin liner.
        cup.head_radius = min(uniform(rng, config.head_diameter_mm) / 2,
                              inner - rng.uniform(1.5, 4.0))
        cup.mu_head = uniform(rng, config.mu_head)
    if rng.random() < config.p_liner:
        # The liner fills the shell down to the head (or a 6-10 mm thick wall without one).
        cup.liner_inner = cup.head_radius + 0.3 if head else max(inner - rng.uniform(6, 10), 5)
        cup.mu_liner = uniform(rng, config.mu_liner)
    return cup


def surgical_hardware(config: SynthConfig, rng: np.random.Generator, cup: Cup, pose: Tensor,
                      inserted: bool, sdd: float) -> tuple[list[Part], bool]:
    """Screws fixing ``cup`` (chance ``p_screws``) and, where ``inserted``, the inserter it
    is held on (chance ``p_impactor``).

    The screws' holes are added to ``cup`` (before its part is made). A cup on its inserter
    is being impacted: it has no liner or femoral head yet (they are taken out of ``cup``),
    and the caller leaves its stem out. ``rng`` is a generator of its own, so that a
    scene's other draws, and the image's noise, are those of the same scene without them.

    A screw's head sits in its hole at the cup's inner surface; its shank, a half-ellipsoid
    cut at the head, tapers to its tip in the bone. The inserter screws into the dome's pole
    from inside and leaves through the opening along the cup's axis: a steel rod, a
    half-ellipsoid cut at the pole and longer than the field (so of nearly constant section
    across it), across the opening's ellipse on the side the axis points to. It ends short
    of the source's plane, ``sdd`` mm from the detector, which no solid may reach.

    Args:
        pose: ``(5,)`` the cup's pose, public units (deg, mm). sdd: mm.
    Returns:
        the hardware's parts, and whether the cup is held on its inserter.
    """
    parts: list[Part] = []
    if rng.random() < config.p_screws:
        holes, dirs = dome_holes(rng, cup, pose)
        cup.screw_holes = torch.cat([cup.screw_holes, holes.float()])
        centre = pose[2:5].numpy()
        for direction, radius in zip(dirs.numpy(), holes[:, 3].tolist(), strict=True):
            head = centre + direction * (cup.radius - cup.wall)
            shank = cup.wall + uniform(rng, config.screw_length_mm)
            parts.append(Ellipsoid(head, frame_along(direction),
                                   np.array([shank, radius * 0.9, radius * 0.9]),
                                   cup.mu_shell, cut=-direction).part())
    held = inserted and rng.random() < config.p_impactor
    if held:
        axis = cup.axes[:, 1].double().numpy()
        pole = pose[2:5].numpy() - axis * (cup.radius - cup.wall)
        rod = uniform(rng, config.impactor_diameter_mm) / 2
        reach = uniform(rng, config.impactor_length_mm)
        if axis[2] > 0:  # towards the source: stop 10 % of the way short of its plane
            reach = min(reach, (0.9 * sdd - pole[2]) / axis[2])
        parts.append(Ellipsoid(pole, frame_along(axis), np.array([reach, rod, rod]),
                               uniform(rng, config.mu_head), cut=-axis).part())
        cup.head_radius = cup.liner_inner = 0.0
    return parts, held


def _unit(*xyz: float) -> np.ndarray:
    v = np.array(xyz)
    return v / np.linalg.norm(v)


def hip_parts(config: SynthConfig, rng: np.random.Generator, centre: Tensor, radius: float,
              lateral: float, stem: bool, mu_metal: float) -> tuple[list[Part], list[Part]]:
    """Femoral stem (metal) and procedural femur and pelvis (bone) around a hip centre.

    Args:
        centre: ``(3,)`` mm, the hip's centre of rotation (the rim centre).
        lateral: -1 or +1, the x direction of the patient's lateral side.
    Returns:
        ``(metal, bones)`` parts.
    """
    c = centre.numpy()
    neck_angle = np.deg2rad(rng.uniform(38, 55))  # from the shaft: the neck-shaft angle's rest
    neck_dir = _unit(lateral * math.sin(neck_angle), math.cos(neck_angle), rng.uniform(-0.2, 0.2))
    neck_base = c + neck_dir * rng.uniform(35, 50)
    shaft_dir = _unit(-lateral * math.sin(np.deg2rad(rng.uniform(2, 10))), 1.0,
                      rng.uniform(-0.1, 0.1))
    metal: list[Part] = []
    # The stem's outline carries no ground truth: one ray per pixel is enough.
    if stem:
        neck_r = rng.uniform(5.5, 7.5)
        metal.append(Ellipsoid.along(c, neck_base + neck_dir * 12, (neck_r, neck_r * 0.85),
                                     mu_metal).part())
        metal.append(Ellipsoid.along(neck_base - shaft_dir * 25 + neck_dir * 8,
                                     neck_base + shaft_dir * rng.uniform(110, 170),
                                     (rng.uniform(8, 11), rng.uniform(6, 8)),
                                     mu_metal).part())
    bones: list[Part] = []
    if rng.random() < config.p_bones:
        mu = uniform(rng, config.mu_bone)
        shaft_r = rng.uniform(13, 18)
        x_lat = _unit(lateral, 0, 0)
        y_inf = _unit(0, 1, 0)
        jitter = rng.uniform(0.85, 1.15)

        def offset(medial_inferior: tuple[float, float]) -> np.ndarray:
            """Medial and inferior mm from the hip centre (scaled per patient)."""
            return jitter * (-x_lat * medial_inferior[0] + y_inf * medial_inferior[1])

        shapes = [
            # Femoral shaft: a cortical tube around the marrow.
            Ellipsoid.along(neck_base - shaft_dir * 30, neck_base + shaft_dir * 320,
                            (shaft_r, shaft_r * 0.9), mu * 1.6, hollow=0.62, mu_inner=mu * 0.3),
            # Femoral neck remnant, greater and lesser trochanter.
            Ellipsoid.along(c + neck_dir * 12, neck_base, (15.0, 14.0), mu, hollow=0.8,
                            mu_inner=mu * 0.5),
            Ellipsoid(neck_base + x_lat * 14 - y_inf * 6, np.eye(3),
                      np.array([20.0, 26.0, 20.0]) * rng.uniform(0.85, 1.15), mu,
                      hollow=0.85, mu_inner=mu * 0.55),
            Ellipsoid(neck_base + shaft_dir * 45 - x_lat * 14, np.eye(3),
                      np.array([10.0, 14.0, 10.0]), mu, hollow=0.7, mu_inner=mu * 0.5),
            # Ilium: a broad plate above and medial to the cup, whose lower edge is the
            # acetabular roof over the dome.
            Ellipsoid(c - x_lat * rng.uniform(15, 35) - y_inf * rng.uniform(60, 80),
                      _rotz(lateral * rng.uniform(10, 35)),
                      np.array([rng.uniform(70, 90), rng.uniform(85, 105), 10.0]),
                      mu * 0.9, hollow=0.93, mu_inner=mu * 0.45),
            # Ischium below the cup and the pubic rami medial to it: overlapping cortical
            # tubes, a ring of bone around the obturator foramen.
            *(Ellipsoid.along(c + offset(start), c + offset(end), radii, mu * 1.2, hollow=0.6,
                              mu_inner=mu * 0.4)
              for start, end, radii in (((5, 15), (105, 35), (12.0, 10.0)),
                                        ((0, 20), (30, 110), (17.0, 15.0)),
                                        ((18, 100), (105, 45), (10.0, 9.0)))),
        ]
        bones = [shape.part() for shape in shapes]
    return metal, bones


def _rotz(degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def sample_scene(config: SynthConfig, rng: np.random.Generator) -> Scene:
    """A random scene: geometry, field, 0-2 placed cups with implants, and bones."""
    width, height = config.image_size
    geometry = sample_geometry(config, rng)
    field_radius = math.inf
    if rng.random() < config.p_circular_field:
        field_radius = uniform(rng, config.field_radius_frac) * min(width, height)
    no_cup = rng.random() < config.p_no_cup
    bilateral = rng.random() < config.p_bilateral
    poses, diameters = sample_poses(config, rng, geometry, field_radius, bilateral)
    # A child generator (spawning draws nothing from rng) for the surgical hardware, so
    # that a config with it makes the same scenes and images as without, plus the hardware.
    hardware_rng = rng.spawn(1)[0] if config.p_screws or config.p_impactor else None
    metal: list[Part] = []
    bones: list[Part] = []
    for slot, (pose, diameter) in enumerate(zip(poses, diameters, strict=True)):
        cup = sample_cup(config, rng, pose, float(diameter))
        lateral = -1.0 if float(pose[1]) > 0 else 1.0
        stem = cup.head_radius > 0 and rng.random() < config.p_stem
        stem_metal, hip_bones = hip_parts(config, rng, pose[2:5], cup.radius, lateral, stem,
                                          cup.mu_shell * rng.uniform(1.0, 1.8))
        # After the stem's draws (which depend on the head), so that they stay the same.
        hardware, held = (([], False) if hardware_rng is None
                          else surgical_hardware(config, hardware_rng, cup, pose, slot == 0,
                                                 float(geometry.sdd)))
        if held:  # the femoral side comes after the cup is impacted
            stem_metal = []
        if not no_cup:
            metal += [cup_part(cup, config.supersample), *stem_metal, *hardware]
        bones += hip_bones
    nominal = float(diameters[0])
    if no_cup:  # the hip stays (native bone), the implant goes
        poses, diameters = poses[:0], diameters[:0]
    return Scene(geometry, width, height, field_radius, poses, diameters, nominal, metal, bones)
