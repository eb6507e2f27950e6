"""Per-image geometry from ``meta.csv`` and the command line (CONVENTIONS "File formats").

``meta.csv``: ``image,sdd_mm,pixel_spacing_mm,cup_diameter_mm`` and optionally
``principal_u_px,principal_v_px``. Shared by ``cupnet predict`` and ``cupnet solve``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

# Geometry values an image needs, with what they are called in messages and which flag sets
# them; the principal point defaults to the image centre (CONVENTIONS) where the size is known.
REQUIRED = {
    "sdd_mm": ("source-to-detector distance", "--sdd"),
    "pixel_spacing_mm": ("pixel spacing", "--pixel-spacing"),
    "cup_diameter_mm": ("cup diameter", "--cup-diameter"),
}
GEOMETRY_KEYS = (*REQUIRED, "principal_u_px", "principal_v_px")
# Geometry values (mm) outside these are most likely a slip: a cup's radius for its diameter,
# centimetres, a spacing of the downsampled image's original. Warned of, not refused: the
# solver takes any geometry, and h, the distance, scales with the cup diameter and spacing.
PLAUSIBLE_MM = {"sdd_mm": (500.0, 2000.0), "pixel_spacing_mm": (0.03, 2.0),
                "cup_diameter_mm": (36.0, 80.0)}


def implausible(values: dict[str, float]) -> dict[str, str]:
    """Each of ``values`` (geometry key -> mm) outside :data:`PLAUSIBLE_MM`, as key -> what
    is wrong with it."""
    out = {}
    for key, (low, high) in PLAUSIBLE_MM.items():
        value = values.get(key)
        if value is not None and not low <= value <= high:
            hint = (" (its radius?)" if key == "cup_diameter_mm" and low <= 2 * value <= high
                    else " (in cm?)" if low <= 10 * value <= high else "")
            out[key] = f"{REQUIRED[key][0]} {value:g} mm{hint} lies outside {low:g}-{high:g} mm"
    return out


def implausible_once(values: dict[str, float], warned: dict[str, str], image: str,
                     sources: dict[str, str] | None = None) -> list[str]:
    """The warnings of :func:`implausible` ``values`` not in ``warned`` (key -> text) yet,
    each naming ``image`` and, where given, the value's source; added to ``warned`` (in
    place), so a run warns once a value."""
    new = []
    for key, problem in implausible(values).items():
        if key not in warned:
            source = f", from {sources[key]}" if sources else ""
            warned[key] = (f"{problem}: first in {image}{source}; check it, the poses' "
                           "distances scale with it")
            new.append(warned[key])
    return new


def add_geometry_arguments(parser: argparse.ArgumentParser) -> None:
    """``--meta``, ``--sdd``, ``--pixel-spacing``, ``--cup-diameter``, ``--principal-point``."""
    parser.add_argument("--meta", type=Path,
                        help="meta.csv: image,sdd_mm,pixel_spacing_mm,cup_diameter_mm"
                             "[,principal_u_px,principal_v_px]")
    parser.add_argument("--sdd", type=float, metavar="MM", help="source-to-detector distance")
    parser.add_argument("--pixel-spacing", type=float, metavar="MM",
                        help="detector pixel spacing, mm/px (at the detector)")
    parser.add_argument("--cup-diameter", type=float, metavar="MM", help="cup outer diameter")
    parser.add_argument("--principal-point", type=float, nargs=2, metavar=("U", "V"),
                        help="principal point in pixels (default: the image centre)")


def geometry_flags(args: argparse.Namespace) -> dict[str, float]:
    """The geometry values given on the command line, by meta.csv key (absent ones left out)."""
    flags = {"sdd_mm": args.sdd, "pixel_spacing_mm": args.pixel_spacing,
             "cup_diameter_mm": args.cup_diameter}
    if args.principal_point is not None:
        flags["principal_u_px"], flags["principal_v_px"] = args.principal_point
    return {k: v for k, v in flags.items() if v is not None}


def read_meta(path: Path) -> dict[str, dict[str, float]]:
    """meta.csv rows by image name: ``{image: {column: value}}`` (blank cells left out).

    Raises:
        ValueError: no ``image`` column, an unknown column, or a non-numeric cell (with its line).
    """
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or "image" not in reader.fieldnames:
            raise ValueError(f"{path}: meta.csv needs an 'image' column")
        unknown = set(reader.fieldnames) - {"image", *GEOMETRY_KEYS}
        if unknown:
            raise ValueError(f"{path}: unknown meta.csv column(s) {sorted(unknown)}")
        rows: dict[str, dict[str, float]] = {}
        for line, row in enumerate(reader, 2):
            try:
                rows[row["image"]] = {k: float(v) for k, v in row.items()
                                      if k != "image" and v not in (None, "")}
            except ValueError as exc:
                raise ValueError(f"{path}, line {line}: {exc}") from exc
    return rows


def meta_row(meta: dict[str, dict[str, float]], name: str) -> dict[str, float]:
    """The meta.csv row of an image: by its name, else its file name (frames: their file's)."""
    file_name = name.split("#", 1)[0]
    for key in (name, file_name, Path(file_name).name):
        if key in meta:
            return meta[key]
    return {}
