"""Synthetic fluoroscopy: speed, closed-form vs DiffDRR agreement, and the contact sheet.

Speed: images per second of :func:`data_synth.synthesize` (default config: anatomy from the
shipped DiffDRR bank, implants in closed form, full image formation), one process, at several
image sizes. Agreement: the closed-form shell against DiffDRR's Siddon render of the same
shell voxelised (64^3 partial volumes, 96 x 88 px): mean and median absolute offset of the
shadow's outer edge along 180 rays from the rim centre, the largest offset, the relative
difference of the integrated line integral, and DiffDRR's projection of the rim landmarks vs
cupnet's forward model. The contact sheet (``docs/contact_sheet.png``) shows samples with
their truth rim drawn.

Run: ``python -m benchmarks.synth [--n 200] [--checks 6] [--sheet docs/contact_sheet.png]``
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from benchmarks.report import machine, markdown_table, write_section
from cupnet.geometry import Geometry
from data_synth import SynthConfig, synthesize
from data_synth.crosscheck import cross_check

SHEET = Path(__file__).resolve().parent.parent / "docs" / "contact_sheet.png"


def images_per_second(size: int, n: int, seed: int = 0) -> tuple[float, float]:
    """``(wall, cpu)`` images per second: per second of elapsed time and of this process's
    CPU time (the second does not count time lost to other processes on a shared machine)."""
    config = SynthConfig(image_size=(size, size))
    synthesize(config, seed, 10**6)  # load the anatomy bank outside the timing
    wall, cpu = time.perf_counter(), time.process_time()
    for index in range(n):
        synthesize(config, seed, index)
    return n / (time.perf_counter() - wall), n / (time.process_time() - cpu)


def agreement(checks: int, seed: int = 0) -> list[list[object]]:
    rng = np.random.default_rng(seed)
    geometry = Geometry(1040.0, 1.2, 45.7, 41.2)
    rows = []
    for _ in range(checks):
        pose = (rng.uniform(5, 70), rng.uniform(-90, 90), rng.uniform(-10, 10),
                rng.uniform(-10, 10), rng.uniform(150, 350))
        diameter, wall = rng.uniform(44, 60), rng.uniform(2, 6)
        check = cross_check(pose, diameter, wall, geometry, 96, 88)
        rows.append([", ".join(f"{v:.0f}" for v in pose), f"{diameter:.0f} / {wall:.1f}",
                     check.edge_mean_px, check.edge_median_abs_px, check.edge_max_px,
                     100 * check.integral_rel, check.projection_px])
    return rows


def contact_sheet(path: Path, columns: int = 4, rows: int = 4, size: int = 256,
                  seed: int = 2026) -> None:
    """Grid of samples with each cup's truth rim (64 landmarks) drawn in colour."""
    config = SynthConfig(image_size=(size, size))
    tiles = []
    for index in range(columns * rows):
        sample = synthesize(config, seed, index)
        tile = cv2.cvtColor((sample["image"][0].numpy() * 255).astype(np.uint8),
                            cv2.COLOR_GRAY2BGR)
        for rim, valid in zip(sample["rim"], sample["cup_valid"], strict=True):
            if valid:
                points = np.round(rim.numpy() * 16).astype(np.int32)  # 4 fractional bits
                cv2.polylines(tile, [points], True, (0, 200, 255), 1, cv2.LINE_AA, shift=4)
        tiles.append(tile)
    grid = np.vstack([np.hstack(tiles[r * columns:(r + 1) * columns]) for r in range(rows)])
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), grid)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200, help="images timed at 256 px")
    parser.add_argument("--checks", type=int, default=6, help="random DiffDRR cross-checks")
    parser.add_argument("--sheet", type=Path, default=SHEET)
    args = parser.parse_args(argv)

    load = os.getloadavg()[0]
    speed = [[size, n, *images_per_second(size, n)]
             for size, n in ((256, args.n), (512, max(args.n // 4, 10)),
                             (1024, max(args.n // 16, 5)))]
    speed_table = markdown_table(["size (px)", "images", "images / s (wall)",
                                  "images / s (CPU time)"], speed)
    print(speed_table)
    checks = agreement(args.checks)
    check_table = markdown_table(
        ["pose (theta, phi, k, l, h)", "diameter / wall (mm)", "edge mean (px)",
         "edge median abs (px)", "edge max (px)", "integral diff (%)",
         "rim projection diff (px)"], checks)
    print(check_table)
    contact_sheet(args.sheet)
    print(f"wrote {args.sheet}")
    body = "\n\n".join([
        f"## Synthetic fluoroscopy (`python -m benchmarks.synth --n {args.n}`)",
        f"Machine: {machine()}; load average {load:.1f} when the timing started (the 2 cores "
        "are shared: the CPU-time rate is what one otherwise idle core gives). One process, "
        "`data_synth.synthesize` (one torch thread) with the default config (DiffDRR anatomy "
        "bank, closed-form implant, full image formation). No GPU was lent to this task, so "
        "there is no GPU figure.",
        speed_table,
        "Closed-form shell vs DiffDRR's Siddon render of it voxelised (64^3 partial volumes, "
        "96 x 88 px, one ray per pixel both ways). Edge: outer edge of the shadow along 180 "
        "rays from the rim centre, closed form minus DiffDRR (the max is the voxel staircase). "
        "Rim projection: DiffDRR's `perspective_projection` through `data_synth.diffdrr_camera`"
        " vs `cupnet.geometry.project_rim`.",
        check_table,
        f"Contact sheet: `{args.sheet.relative_to(SHEET.parent.parent)}`.",
    ])
    write_section("synth", body)
    return 0


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    raise SystemExit(main())
