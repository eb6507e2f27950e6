"""Landmark files of CONVENTIONS.md: the project's long format and the paper code's format.

- Long format: a header with ``image,u,v`` (optionally ``cup``), one landmark per row, pixels.
- The paper's public code: ``image_name,image_width,image_height,source_to_detection_distance,
  radius,n_landmarks,landmark_1_x,landmark_1_y,...`` one image per row; its code treats pixels
  as millimetres, so its SDD and radius are read as millimetres and the pixel spacing is
  1 mm/px unless the user gives one.

The format is detected from the header. A malformed row becomes an error for its image
(``LandmarkSet.error``), so one bad row never stops a run.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cupnet.io.csvfile import csv_text

LONG_COLUMNS = ("image", "u", "v")
PAPER_COLUMNS = ("image_name", "image_width", "image_height", "source_to_detection_distance",
                 "radius", "n_landmarks")


@dataclass
class LandmarkSet:
    """The landmarks of one cup of one image.

    Attributes:
        image: image name as in the file.
        cup: cup index within the image (0 for single cups).
        points: ``(N, 2)`` pixels (u, v).
        width, height: image size in pixels, where the file gives it.
        sdd_mm, cup_diameter_mm, pixel_spacing_mm: geometry the file carries (paper format).
        error: why the row(s) could not be read; ``points`` is empty then.
    """

    image: str
    cup: int = 0
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    width: int | None = None
    height: int | None = None
    sdd_mm: float | None = None
    cup_diameter_mm: float | None = None
    pixel_spacing_mm: float | None = None
    error: str | None = None

    def size(self) -> tuple[int, int] | None:
        """The image's ``(height, width)`` pixels where the file gives it, else None."""
        return None if self.width is None or self.height is None else (self.height,
                                                                        self.width)

    def geometry_values(self) -> dict[str, float]:
        """The geometry the file carries, by meta.csv key (those it lacks left out)."""
        values = {"sdd_mm": self.sdd_mm, "pixel_spacing_mm": self.pixel_spacing_mm,
                  "cup_diameter_mm": self.cup_diameter_mm}
        return {key: value for key, value in values.items() if value is not None}


def read_landmarks(path: str | Path) -> dict[str, list[LandmarkSet]]:
    """Landmark sets by image name (one per cup), from either CONVENTIONS format.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not UTF-8, the header matches neither format, or the file
            holds no rows.
    """
    path = Path(path)
    with csv_text(path) as f:
        rows = list(csv.reader(f))
    rows = [r for r in rows if any(cell.strip() for cell in r)]
    if not rows:
        raise ValueError(f"{path}: empty landmark file")
    header = [c.strip() for c in rows[0]]
    if set(LONG_COLUMNS) <= set(header):
        sets = _read_long(header, rows[1:])
    elif tuple(header[:len(PAPER_COLUMNS)]) == PAPER_COLUMNS:
        sets = _read_paper(rows[1:])
    else:
        raise ValueError(
            f"{path}: unknown landmark format; expected a header with {','.join(LONG_COLUMNS)} "
            f"(long format) or starting {','.join(PAPER_COLUMNS)},landmark_1_x,... "
            f"(the paper's label.csv), got {','.join(header[:8])}")
    if not sets:
        raise ValueError(f"{path}: no landmark rows")
    return sets


def _read_long(header: list[str], rows: list[list[str]]) -> dict[str, list[LandmarkSet]]:
    col = {name: header.index(name) for name in header}
    points: dict[tuple[str, int], list[tuple[float, float]]] = {}
    errors: dict[tuple[str, int], str] = {}
    for line, row in enumerate(rows, 2):
        image = row[col["image"]].strip() if len(row) > col["image"] else ""
        if not image:
            continue
        cup = 0
        try:
            cell = row[col["cup"]].strip() if "cup" in col else ""
            # "1.0": a cup column with a blank somewhere, as pandas writes it.
            cup = int(float(cell)) if cell else 0
            if cell and not float(cell).is_integer() or cup < 0:
                raise ValueError(f"cup must be a whole number >= 0, got {cell!r}")
            u, v = float(row[col["u"]]), float(row[col["v"]])
            if not (math.isfinite(u) and math.isfinite(v)):
                raise ValueError("non-finite landmark coordinate")
        except (ValueError, IndexError, OverflowError) as exc:  # int(inf): OverflowError
            # The set of the row's cup (cup 0 where the cup itself is unreadable) is an error.
            errors.setdefault((image, cup), f"landmark file line {line}: {exc}")
            continue
        points.setdefault((image, cup), []).append((u, v))
    out: dict[str, list[LandmarkSet]] = {}
    for key in sorted(set(points) | set(errors), key=lambda k: (k[0], k[1])):
        image, cup = key
        if key in errors:
            out.setdefault(image, []).append(LandmarkSet(image=image, cup=cup, error=errors[key]))
        else:
            out.setdefault(image, []).append(
                LandmarkSet(image=image, cup=cup, points=np.asarray(points[key], np.float64)))
    return out


def _count(name: str, cell: str) -> int:
    """A label.csv cell that counts (pixels, landmarks): a whole number >= 1, or a
    ValueError naming its column (inf had stopped the run, 0 given a principal point off
    the image)."""
    value = float(cell)
    if not (math.isfinite(value) and value >= 1 and value.is_integer()):
        raise ValueError(f"{name} must be a whole number >= 1, got {cell.strip()!r}")
    return int(value)


def _read_paper(rows: list[list[str]]) -> dict[str, list[LandmarkSet]]:
    out: dict[str, list[LandmarkSet]] = {}
    for line, row in enumerate(rows, 2):
        image = row[0].strip()
        if not image:
            continue
        try:
            width, height, n = (_count(PAPER_COLUMNS[i], row[i]) for i in (1, 2, 5))
            sdd, radius = float(row[3]), float(row[4])
            values = [float(x) for x in row[6:6 + 2 * n]]
            if len(values) != 2 * n:
                raise ValueError(f"n_landmarks = {n} but {len(values) // 2} landmarks given")
            pts = np.asarray(values, np.float64).reshape(n, 2)
            if not np.isfinite(pts).all():
                raise ValueError("non-finite landmark coordinate")
            entry = LandmarkSet(image=image, cup=len(out.get(image, [])), points=pts,
                                width=width, height=height, sdd_mm=sdd,
                                cup_diameter_mm=2 * radius, pixel_spacing_mm=1.0)
        except (ValueError, IndexError) as exc:
            entry = LandmarkSet(image=image, error=f"landmark file line {line}: {exc}")
        out.setdefault(image, []).append(entry)
    return out
