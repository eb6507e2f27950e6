"""``cupnet solve``: cup poses from landmark files, no images and no network.

Geometry per image, first found wins, as in ``cupnet predict``
(:func:`cupnet.io.meta.resolve_geometry`): the ``--meta`` row, the command-line flags, the
landmark file's own columns (the paper's format carries SDD and radius, in its pixel =
millimetre units), with ``--assume-defaults`` the assumed values; the principal point
defaults to the image centre where the image size is known. A missing value is an error row
naming it; the run goes on.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import torch

from cupnet.detection import CupDetection
from cupnet.geometry import Geometry
from cupnet.io.landmarks import LandmarkSet, read_landmarks
from cupnet.io.meta import (
    GeometryInputs,
    add_geometry_arguments,
    assumptions_once,
    implausible_once,
)
from cupnet.io.results import cup_row, status_row, write_results_csv
from cupnet.pose import ellipse_of_pose, pose_standard_errors, solve_pose


def results_file(text: str) -> Path:
    """``--out``'s value as a path. A name ending in a separator names a folder: refused
    here, since ``Path`` drops the separator and the folder's name would become a file's."""
    if text.endswith(("/", os.sep)):
        raise argparse.ArgumentTypeError(f"{text} names a folder; give the results file, such "
                                         f"as {Path(text) / 'results.csv'}")
    return Path(text)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("landmarks", type=Path,
                        help="landmark file: image,u,v (long format) or the paper's label.csv")
    parser.add_argument("--out", type=results_file, required=True, help="results.csv to write")
    add_geometry_arguments(parser)
    parser.add_argument("--image-size", type=int, nargs=2, metavar=("W", "H"),
                        help="the images' size in pixels, for a landmark file that does not "
                             "give it (the long format): the principal point defaults to its "
                             "centre and --assume-defaults' spacing to 300 mm over W")
    parser.add_argument("--closed-form", action="store_true",
                        help="skip the maximum-likelihood refinement")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


# Given landmarks whose RMS distance to the solved rim exceeds this fraction of the
# semi-major axis of their own ellipse fit are flagged ``check``: clicked or detected rims
# lie within a few pixels of it (2 px of noise is 0.02 of a 100 px axis), points from
# anywhere else (another cup's rim mixed in, a mislabelled file, random clicks) lie a
# quarter of it off or more, and the solver still returns a pose for them, far from the
# truth but with an ``ok`` status.
OFF_RIM_CHECK = 0.1
# Two cups' whole rims in one set fit one wide ellipse that passes between them (about 0.06
# of its axis off), whose pose puts the cup near the source: a hip lies nearer the detector
# (the synthetic and the paper's sets: h under 0.55 SDD, a magnification under 2.2), so a
# pose past this fraction of SDD (a magnification over 4) is flagged too.
NEAR_SOURCE_CHECK = 0.75


def solve_cup(cup: LandmarkSet, geometry: Geometry, diameter: float, refine: bool
              ) -> CupDetection:
    """The pose of one cup's given landmarks and its rim's ellipse, flagged ``check`` where
    they lie off the solved rim by more than :data:`OFF_RIM_CHECK` of their own fit's
    semi-major axis or the pose lies past :data:`NEAR_SOURCE_CHECK` of SDD or within the
    cup's radius of the detector, with its standard errors from their scatter about that
    rim."""
    points = torch.as_tensor(cup.points, dtype=torch.float64)
    sol = solve_pose(points, geometry, diameter, refine=refine, on_error="flag")
    ambiguous = bool(sol.ambiguous[0])
    # Against the landmarks' own fit, their extent: points from elsewhere can give a pose
    # whose rim is far larger (two cups' rims: 551 px against the points' 179).
    off_rim = float(sol.residual_px[0] / sol.ellipse[0, 2])  # NaN where no pose, never raises
    # The row's ellipse is its pose's rim, as the network's rows and every overlay draw it
    # (the fit differs from it where the refinement moved the pose); the fit where no pose.
    ellipse = sol.ellipse
    if sol.valid[0]:
        ellipse = ellipse_of_pose(sol.pose, diameter, geometry)
    h = float(sol.pose[0, 4])
    # Past NEAR_SOURCE_CHECK of SDD, or so near the detector that the dome passes through it.
    implausible = h > NEAR_SOURCE_CHECK * float(geometry.sdd) or h < diameter / 2
    return CupDetection(
        pose=sol.pose[0].numpy(), alt_pose=sol.alt_pose[0].numpy() if ambiguous else None,
        ambiguous=ambiguous, ellipse=ellipse[0].numpy(), landmarks=cup.points,
        weights=torch.ones(len(cup.points)).numpy(), residual_px=float(sol.residual_px[0]),
        status=sol.status[0],
        check=None if math.isnan(off_rim) else off_rim > OFF_RIM_CHECK or implausible,
        pose_sd=pose_standard_errors(sol.pose, points, geometry, diameter)[0].numpy())


def run(args: argparse.Namespace) -> int:
    if args.out.is_dir():
        print(f"cupnet solve: --out {args.out} is a folder; give the results file, such as "
              f"{args.out / 'results.csv'}", file=sys.stderr)
        return 2
    if args.out.exists() and not args.overwrite:
        print(f"cupnet solve: {args.out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    try:
        if args.image_size is not None and min(args.image_size) < 1:
            raise ValueError(f"--image-size must be positive, got {args.image_size}")
        landmark_sets = read_landmarks(args.landmarks)
        geometry_inputs = GeometryInputs.from_args(args)
    except (OSError, ValueError) as exc:
        print(f"cupnet solve: {exc}", file=sys.stderr)
        return 2
    records, failures, solved, flagged = [], 0, 0, 0
    warned: dict[str, str] = {}
    assumed: dict[str, str] = {}  # what --assume-defaults filled, said once, as predict says
    for image, cups in landmark_sets.items():
        rows = []
        start = time.perf_counter()
        for cup in cups:
            # An error row keeps its cup's label: a bilateral image's two had read as one
            # row written twice, which cupnet evaluate refuses.
            if cup.error is not None:  # a bad row: no geometry to resolve for it
                rows.append(status_row(image, f"error: {cup.error}", 0.0, cup.cup))
                continue
            size = cup.size() or (None if args.image_size is None
                                  else (args.image_size[1], args.image_size[0]))
            resolved = geometry_inputs.resolve(image, size, file_values=cup.geometry_values())
            if not resolved.complete:
                rows.append(status_row(image, resolved.error(), 0.0, cup.cup))
            else:
                for text in assumptions_once(resolved.sources, assumed, size[1] if size else 0):
                    print(f"cupnet solve: {text}", file=sys.stderr)
                for text in implausible_once(resolved.values, warned, image, resolved.sources):
                    print(f"cupnet solve: warning: {text}", file=sys.stderr)
                detection = solve_cup(cup, resolved.geometry(),
                                      resolved.values["cup_diameter_mm"],
                                      refine=not args.closed_form)
                rows.append(cup_row(image, cup.cup, detection, 0.0))
        # Each row carries its image's time, as cupnet predict writes it: cupnet evaluate
        # reads an image's seconds from its first row (a cup's own had left the others out).
        seconds = time.perf_counter() - start
        for row in rows:
            row["seconds"] = seconds
        failures += sum(str(r["status"]).startswith("error") for r in rows)
        solved += sum(not str(r["status"]).startswith("error") for r in rows)
        flagged += sum(r.get("check") == 1 for r in rows)
        records.append({"rows": rows})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_results_csv(args.out, records)
    print(f"{len(records)} images, {solved} cups solved, {failures} errors -> {args.out}")
    if flagged:
        print(f"  {flagged} cup(s) flagged check=1: their landmarks lie off the solved rim "
              f"(RMS distance over {OFF_RIM_CHECK:g} of its semi-major axis), or put the cup "
              f"past {NEAR_SOURCE_CHECK:g} of the way to the source; look before trusting "
              "them")
    return 1 if records and solved == 0 else 0  # as cupnet predict: nothing came of it
