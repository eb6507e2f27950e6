"""``cupnet solve``: cup poses from landmark files, no images and no network.

Geometry per image, first found wins: the ``--meta`` row, the command-line flags, the
landmark file's own columns (the paper's format carries SDD and radius, in its pixel =
millimetre units); the principal point defaults to the image centre where the image size is
known. A missing value is an error row naming it; the run goes on.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from cupnet.geometry import Geometry
from cupnet.io.landmarks import LandmarkSet, read_landmarks
from cupnet.model import CupDetection
from cupnet.pose import solve_pose
from cupnet.predict import cup_row, meta_row, read_meta, status_row, write_results_csv

# value key -> (name in messages, flag, LandmarkSet attribute)
GEOMETRY_VALUES = {
    "sdd_mm": ("source-to-detector distance", "--sdd", "sdd_mm"),
    "pixel_spacing_mm": ("pixel spacing", "--pixel-spacing", "pixel_spacing_mm"),
    "cup_diameter_mm": ("cup diameter", "--cup-diameter", "cup_diameter_mm"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("landmarks", type=Path,
                        help="landmark file: image,u,v (long format) or the paper's label.csv")
    parser.add_argument("--out", type=Path, required=True, help="results.csv to write")
    parser.add_argument("--meta", type=Path, help="meta.csv with per-image geometry")
    parser.add_argument("--sdd", type=float, metavar="MM", help="source-to-detector distance")
    parser.add_argument("--pixel-spacing", type=float, metavar="MM",
                        help="detector pixel spacing, mm/px (the paper's format: 1)")
    parser.add_argument("--cup-diameter", type=float, metavar="MM", help="cup outer diameter")
    parser.add_argument("--principal-point", type=float, nargs=2, metavar=("U", "V"),
                        help="principal point in pixels (default: the image centre)")
    parser.add_argument("--closed-form", action="store_true",
                        help="skip the maximum-likelihood refinement")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def geometry_of(cup: LandmarkSet, meta: dict[str, float], flags: dict[str, float | None]
                ) -> tuple[Geometry, float] | str:
    """The cup's geometry and diameter, or an error status naming what is missing."""
    values: dict[str, float] = {}
    missing = []
    for key, (name, flag, attribute) in GEOMETRY_VALUES.items():
        for source in (meta.get(key), flags.get(key), getattr(cup, attribute)):
            if source is not None:
                values[key] = float(source)
                break
        else:
            missing.append(f"{name} ({flag} or meta.csv {key})")
    principal = [meta.get("principal_u_px"), meta.get("principal_v_px")]
    if None in principal:
        principal = flags.get("principal_point") or [None, None]
    if None in principal and cup.width is not None and cup.height is not None:
        principal = [(cup.width - 1) / 2, (cup.height - 1) / 2]
    if None in principal:
        missing.append("principal point (--principal-point or meta.csv principal_u_px, "
                       "principal_v_px; no image size to take its centre from)")
    if missing:
        return f"error: missing {', '.join(missing)}"
    geometry = Geometry(values["sdd_mm"], values["pixel_spacing_mm"], *principal)
    return geometry, values["cup_diameter_mm"]


def solve_cup(cup: LandmarkSet, geometry: Geometry, diameter: float, refine: bool
              ) -> CupDetection:
    sol = solve_pose(torch.as_tensor(cup.points, dtype=torch.float64), geometry, diameter,
                     refine=refine, on_error="flag")
    ambiguous = bool(sol.ambiguous[0])
    return CupDetection(
        pose=sol.pose[0].numpy(), alt_pose=sol.alt_pose[0].numpy() if ambiguous else None,
        ambiguous=ambiguous, ellipse=sol.ellipse[0].numpy(), landmarks=cup.points,
        weights=torch.ones(len(cup.points)).numpy(), residual_px=float(sol.residual_px[0]),
        status=sol.status[0])


def run(args: argparse.Namespace) -> int:
    if args.out.exists() and not args.overwrite:
        print(f"cupnet solve: {args.out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    try:
        landmark_sets = read_landmarks(args.landmarks)
        meta = read_meta(args.meta) if args.meta else {}
    except (OSError, ValueError) as exc:
        print(f"cupnet solve: {exc}", file=sys.stderr)
        return 2
    flags = {"sdd_mm": args.sdd, "pixel_spacing_mm": args.pixel_spacing,
             "cup_diameter_mm": args.cup_diameter, "principal_point": args.principal_point}
    records, failures, solved = [], 0, 0
    for image, cups in landmark_sets.items():
        rows = []
        for cup in cups:
            start = time.perf_counter()
            resolved = geometry_of(cup, meta_row(meta, image), flags)
            if cup.error is not None:
                rows.append(status_row(image, f"error: {cup.error}", 0.0))
            elif isinstance(resolved, str):
                rows.append(status_row(image, resolved, 0.0))
            else:
                detection = solve_cup(cup, *resolved, refine=not args.closed_form)
                rows.append(cup_row(image, cup.cup, detection, time.perf_counter() - start))
        failures += sum(str(r["status"]).startswith("error") for r in rows)
        solved += sum(not str(r["status"]).startswith("error") for r in rows)
        records.append({"rows": rows})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_results_csv(args.out, records)
    print(f"{len(records)} images, {solved} cups solved, {failures} errors -> {args.out}")
    return 0
