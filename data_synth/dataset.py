"""Synthetic fluoroscopy samples with exact ground truth, one at a time or as a stream.

Sample ``i`` of seed ``s`` draws everything from ``numpy.random.default_rng([s, i])``, so it
is the same whichever DataLoader worker makes it and however many workers there are.
"""

from __future__ import annotations

import itertools
import math
import numbers
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import IterableDataset, get_worker_info

from cupnet.ellipse import conic_to_params
from cupnet.geometry import Geometry, pose_to_radians, project_rim, rim_conic
from data_synth.anatomy import bank_path, load_bank, smooth_field, warp_anatomy
from data_synth.config import SynthConfig
from data_synth.formation import form_image
from data_synth.raycast import Part, render_parts, subpixel_grid
from data_synth.scene import MAX_CUPS, sample_scene, uniform

RIM_POINTS = 64
THIN_ELLIPSE_PX = 2.0
THIN_SUPERSAMPLE = 8
# Photoelectric absorption dominates in metal and falls faster with energy than the Compton
# scattering of tissue: metal's attenuation scales with a higher power of the energy factor.
METAL_ENERGY_POWER = 1.5
BASE_TISSUE = (3.0, 6.0)  # water-equivalent attenuation of a body without CT anatomy


def render_bones(bones: list[Part], geometry: Geometry, width: int, height: int) -> Tensor:
    """Line integrals ``(H, W)`` of the smooth bone parts, cast at half resolution.

    Half-resolution pixel ``(j, i)`` covers full-resolution pixels ``2j, 2j + 1``, so its centre
    is at ``u = 2 j + 1/2``: spacing ``2 s`` and principal point ``(u0 - 1/2) / 2``; bilinear
    upsampling (OpenCV's pixel-area alignment) puts the values back in place.
    """
    if not bones:
        return torch.zeros(height, width)
    sdd, spacing, u0, v0 = (float(t) for t in geometry.tensors())
    half = Geometry(sdd, 2 * spacing, (u0 - 0.5) / 2, (v0 - 0.5) / 2)
    small = render_parts(bones, half, (width + 1) // 2, (height + 1) // 2)
    full = cv2.resize(small.numpy(), ((width + 1) // 2 * 2, (height + 1) // 2 * 2),
                      interpolation=cv2.INTER_LINEAR)
    return torch.from_numpy(full[:height, :width])


def is_count(value: object) -> bool:
    """``value`` is a non-negative integer of any integer type (numpy's too), not a bool."""
    return (isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
            and value >= 0)


def sample_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of sample ``index`` of stream ``seed`` (both non-negative integers)."""
    return np.random.default_rng([int(seed), int(index)])


def rim_truth(poses: Tensor, diameters: Tensor, geometry: Geometry
              ) -> tuple[Tensor, Tensor, Tensor]:
    """Rim conics ``(n, 3, 3)``, ellipse parameters ``(n, 5)`` and landmarks ``(n, 64, 2)`` px.

    Args:
        poses: ``(n, 5)`` public units. diameters: ``(n,)`` mm. All float64.
    """
    radius = diameters / 2
    pose = pose_to_radians(poses)
    conic = rim_conic(pose, radius, geometry)
    t = torch.linspace(0, 2 * math.pi, RIM_POINTS + 1, dtype=torch.float64)[:-1]
    return conic, conic_to_params(conic), project_rim(pose, radius, geometry, t)


def opening_mask(conics: Tensor, ellipses: Tensor, width: int, height: int) -> Tensor:
    """Fraction ``(H, W)`` of each pixel inside the union of the rim ellipses.

    ``conics``: ``(n, 3, 3)`` rim conics (negative inside); ``ellipses``: their ``(n, 5)``
    parameters. Anti-aliased analytically: a pixel's coverage is ``clamp(1/2 - d, 0, 1)``
    with ``d`` the first-order (Sampson) signed distance in pixels of its centre from the
    conic: exact for a straight edge along a pixel axis, and off by up to about 0.05 of a
    pixel's coverage where the edge runs diagonally (the area a straight edge cuts off a
    square is no linear ramp of its distance; a review's 16 x 16 supersampling: mean 0.007
    within 9 deg of an axis, 0.023 on diagonals); ellipses thinner than ``THIN_ELLIPSE_PX``
    count inside samples on an 8 x 8 grid. The truth's rim and ellipse are exact; this
    is the training mask only.
    """
    mask = torch.zeros(height, width)
    for conic, (cx, cy, a, b, alpha) in zip(conics, ellipses.tolist(), strict=True):
        ca, sa = math.cos(math.radians(alpha)), math.sin(math.radians(alpha))
        half_u, half_v = math.hypot(a * ca, b * sa), math.hypot(a * sa, b * ca)
        box = (max(math.floor(cx - half_u) - 1, 0), min(math.ceil(cx + half_u) + 2, width),
               max(math.floor(cy - half_v) - 1, 0), min(math.ceil(cy + half_v) + 2, height))
        if box[0] >= box[1] or box[2] >= box[3]:
            continue
        # Thinner than a few pixels the first-order distance fails: count sub-pixels instead.
        n = 1 if b >= THIN_ELLIPSE_PX else THIN_SUPERSAMPLE
        u, v = subpixel_grid(box, n, torch.float64)
        (a_uu, a_uv, a_u), (_, a_vv, a_v), (_, _, a_1) = conic.tolist()
        # Half the gradient of p^T C p, then its value p^T C p = (g_u u + g_v v) + (...).
        g_u = a_uu * u + a_uv * v + a_u
        g_v = a_uv * u + a_vv * v + a_v
        value = g_u * u + g_v * v + (a_u * u + a_v * v + a_1)
        if n == 1:
            distance = value / (2 * torch.sqrt(g_u * g_u + g_v * g_v)).clamp_min(1e-12)
            coverage = (0.5 - distance).clamp(0, 1).float()
        else:
            inside = (value < 0).float()[None, None]
            coverage = torch.nn.functional.avg_pool2d(inside, n)[0, 0]
        region = mask[box[2]:box[3], box[0]:box[1]]
        torch.maximum(region, coverage, out=region)
    return mask


@contextmanager
def single_thread() -> Iterator[None]:
    """Run torch on one thread, then restore the caller's setting.

    A sample's tensors are small: two intra-op threads gain nothing, and on a busy machine
    their synchronisation made synthesis 10-20x slower (measured: 125-270 vs 10 ms of CPU
    per 256 px image). DataLoader workers already run single-threaded.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def synthesize(config: SynthConfig, seed_or_generator: int | np.random.Generator,
               index: int = 0) -> dict[str, Tensor]:
    """One synthetic image and its ground truth.

    Args:
        config: sampling ranges.
        seed_or_generator: stream seed (with ``index``: :func:`sample_rng`) or a generator.
        index: sample index within the stream (ignored with a generator).
    Returns:
        ``image (1, H, W)`` float32 in [0, 1]; ``mask (1, H, W)`` float32 rim-ellipse coverage;
        ``geometry (4,)`` (sdd mm, spacing mm/px, u0 px, v0 px); ``pose (2, 5)`` (theta deg,
        phi deg, k, l, h mm); ``ellipse (2, 5)`` (cx, cy, a, b px, alpha deg);
        ``rim (2, 64, 2)`` px; ``cup_diameter (2,)`` mm; ``cup_valid (2,)`` bool. Slots that
        hold no cup have zero pose, ellipse and rim and ``cup_valid`` False; their
        ``cup_diameter`` is the image's (the diameter a user would give, as in meta.csv), so
        it is never 0. Truth is float64. ``index ()`` int64.
    """
    if isinstance(seed_or_generator, np.random.Generator):
        rng = seed_or_generator
    elif is_count(seed_or_generator) and is_count(index):
        rng = sample_rng(seed_or_generator, index)
    else:
        raise ValueError("synthesize needs a non-negative integer seed and index or a "
                         f"numpy Generator, got {seed_or_generator!r} and index {index!r}")
    with single_thread(), torch.no_grad():
        return _synthesize(config, rng, index)


def _synthesize(config: SynthConfig, rng: np.random.Generator, index: int) -> dict[str, Tensor]:
    scene = sample_scene(config, rng)
    width, height, geometry = scene.width, scene.height, scene.geometry

    metal = render_parts(scene.metal, geometry, width, height)
    if rng.random() < config.p_anatomy:
        bank = load_bank(str(bank_path(config.anatomy_bank, config.anatomy_ct)))
        tissue = warp_anatomy(bank, rng, width, height, config.anatomy_zoom)
        tissue = tissue * uniform(rng, config.anatomy_scale)
    else:
        tissue = torch.full((height, width), uniform(rng, BASE_TISSUE))
    tissue = tissue + smooth_field(rng, width, height, uniform(rng, config.smooth_background))
    tissue = tissue + render_bones(scene.bones, geometry, width, height)
    energy = uniform(rng, config.energy_factor)
    line_integral = tissue * energy + metal * energy**METAL_ENERGY_POWER
    image = form_image(line_integral, scene.field_radius, config, rng)

    n = len(scene.poses)
    pose = torch.zeros(MAX_CUPS, 5, dtype=torch.float64)
    ellipse = torch.zeros(MAX_CUPS, 5, dtype=torch.float64)
    rim = torch.zeros(MAX_CUPS, RIM_POINTS, 2, dtype=torch.float64)
    diameter = torch.full((MAX_CUPS,), scene.nominal_diameter, dtype=torch.float64)
    valid = torch.zeros(MAX_CUPS, dtype=torch.bool)
    mask = torch.zeros(height, width)
    if n:
        pose[:n], diameter[:n], valid[:n] = scene.poses, scene.diameters, True
        conics, ellipse[:n], rim[:n] = rim_truth(scene.poses, scene.diameters, geometry)
        mask = opening_mask(conics, ellipse[:n], width, height)
    return {
        "image": image,
        "mask": mask[None],
        "geometry": torch.stack(geometry.tensors()),
        "pose": pose,
        "ellipse": ellipse,
        "rim": rim,
        "cup_diameter": diameter,
        "cup_valid": valid,
        "index": torch.tensor(index, dtype=torch.int64),
    }


def stream_share(rotate: int = 0) -> tuple[int, int]:
    """This reader's share of a sample stream, ``(share, shares)``: one per DataLoader worker
    in each process of a distributed run (DDP: ``torch.distributed``, when initialised), so
    that no two readers make the same samples. With ``rotate``, worker ``w`` takes worker
    ``(w + rotate) % workers``'s share (a resumed loader, whose first worker takes up where
    the stopped one's next worker was)."""
    rank, world = ((torch.distributed.get_rank(), torch.distributed.get_world_size())
                   if torch.distributed.is_available() and torch.distributed.is_initialized()
                   else (0, 1))
    info = get_worker_info()
    worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
    return rank * workers + (worker + rotate) % workers, world * workers


class SynthDataset(IterableDataset):
    """Endless (or ``length``-long) stream of :func:`synthesize` samples for a DataLoader.

    Reader ``r`` of ``n`` (:func:`stream_share`: DataLoader workers, times DDP processes)
    makes samples ``r, r + n, r + 2n, ...``. Sample ``i`` is the same whatever the number
    of readers (its ``index`` entry says which it is); only the order in which they are
    batched changes.
    """

    def __init__(self, config: SynthConfig, seed: int, length: int | None = None) -> None:
        super().__init__()
        if not is_count(seed):
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        if length is not None and not is_count(length):
            raise ValueError(f"length must be a non-negative integer or None, got {length!r}")
        self.config, self.seed = config, int(seed)
        self.length = None if length is None else int(length)

    def __len__(self) -> int:
        if self.length is None:
            raise TypeError("an endless SynthDataset has no length")
        return self.length

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        """Sample ``index`` of the stream (the same the iterator yields)."""
        return synthesize(self.config, self.seed, index)

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        return self.samples()

    def samples(self, skip: int = 0, rotate: int = 0) -> Iterator[dict[str, Tensor]]:
        """This reader's samples (:func:`stream_share` with ``rotate``), after its first
        ``skip`` of them (a resumed run's, which it trained on), without making those."""
        share, shares = stream_share(rotate)
        first = share + skip * shares
        indices = (itertools.count(first, shares) if self.length is None
                   else range(first, self.length, shares))
        for index in indices:
            yield synthesize(self.config, self.seed, index)
