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

from cupnet.detection import CupDetection
from cupnet.geometry import Geometry
from cupnet.io.landmarks import LandmarkSet, read_landmarks
from cupnet.io.meta import (
    REQUIRED,
    add_geometry_arguments,
    geometry_flags,
    implausible_once,
    meta_row,
    read_meta,
)
from cupnet.io.results import cup_row, status_row, write_results_csv
from cupnet.pose import solve_pose


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("landmarks", type=Path,
                        help="landmark file: image,u,v (long format) or the paper's label.csv")
    parser.add_argument("--out", type=Path, required=True, help="results.csv to write")
    add_geometry_arguments(parser)
    parser.add_argument("--closed-form", action="store_true",
                        help="skip the maximum-likelihood refinement")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def geometry_of(cup: LandmarkSet, meta: dict[str, float], flags: dict[str, float]
                ) -> tuple[Geometry, float] | str:
    """The cup's geometry and diameter, or an error status naming what is missing.

    Each value from the first of: the meta.csv row, the command line, the landmark file;
    the principal point from meta.csv, the command line, else the image centre.
    """
    values: dict[str, float] = {}
    missing = []
    for key, (name, flag) in REQUIRED.items():
        for source in (meta.get(key), flags.get(key), getattr(cup, key)):
            if source is not None:
                values[key] = float(source)
                break
        else:
            missing.append(f"{name} ({flag} or meta.csv {key})")
    for source in (meta, flags):
        if "principal_u_px" in source and "principal_v_px" in source:
            principal = [source["principal_u_px"], source["principal_v_px"]]
            break
    else:
        principal = None
        if cup.width is not None and cup.height is not None:
            principal = [(cup.width - 1) / 2, (cup.height - 1) / 2]
    if principal is None:
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
    flags = geometry_flags(args)
    records, failures, solved = [], 0, 0
    warned: dict[str, str] = {}
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
                geometry, diameter = resolved
                values = {"sdd_mm": float(geometry.sdd),
                          "pixel_spacing_mm": float(geometry.pixel_spacing),
                          "cup_diameter_mm": diameter}
                for text in implausible_once(values, warned, image):
                    print(f"cupnet solve: warning: {text}", file=sys.stderr)
                detection = solve_cup(cup, geometry, diameter, refine=not args.closed_form)
                rows.append(cup_row(image, cup.cup, detection, time.perf_counter() - start))
        failures += sum(str(r["status"]).startswith("error") for r in rows)
        solved += sum(not str(r["status"]).startswith("error") for r in rows)
        records.append({"rows": rows})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_results_csv(args.out, records)
    print(f"{len(records)} images, {solved} cups solved, {failures} errors -> {args.out}")
    return 0
