"""Per-image geometry from ``meta.csv`` and the command line (CONVENTIONS "File formats").

``meta.csv``: ``image,sdd_mm,pixel_spacing_mm,cup_diameter_mm`` and optionally
``principal_u_px,principal_v_px``. Shared by ``cupnet predict`` and ``cupnet solve``, which
resolve each image's geometry the same way (:func:`resolve_geometry`).
"""

from __future__ import annotations

import argparse
import csv
import math
import re
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from cupnet.geometry import Geometry
from cupnet.io.csvfile import csv_text

T = TypeVar("T")

# Geometry values an image needs, with what they are called in messages and which flag sets
# them; the principal point defaults to the image centre (CONVENTIONS) where the size is known.
REQUIRED = {
    "sdd_mm": ("source-to-detector distance", "--sdd"),
    "pixel_spacing_mm": ("pixel spacing", "--pixel-spacing"),
    "cup_diameter_mm": ("cup diameter", "--cup-diameter"),
}
GEOMETRY_KEYS = (*REQUIRED, "principal_u_px", "principal_v_px")
PRINCIPAL_KEYS = GEOMETRY_KEYS[len(REQUIRED):]
# --assume-defaults: the paper's SDD, a common cup size, and a mid-size detector whose width
# spans the image (so the spacing scales with the image size).
ASSUMED_SDD_MM = 1040.0
ASSUMED_CUP_DIAMETER_MM = 52.0
ASSUMED_DETECTOR_WIDTH_MM = 300.0
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


def assumptions_once(sources: dict[str, str], noted: dict[str, str], width: int
                     ) -> list[str]:
    """The values ``--assume-defaults`` filled for an image ``width`` px wide (``sources``
    ``"assumed"``; a pixel spacing is assumed only where the width is known) not in
    ``noted`` (key -> what was assumed) yet, each as a line to print; added to ``noted`` (in
    place), so a run says each once."""
    new = []
    for key, source in sources.items():
        if source != "assumed" or key in noted:
            continue
        noted[key] = (f"{ASSUMED_DETECTOR_WIDTH_MM:g} mm / image width (e.g. "
                      f"{ASSUMED_DETECTOR_WIDTH_MM / width:.4g} mm/px at {width} px)"
                      if key == "pixel_spacing_mm" else
                      f"{ASSUMED_SDD_MM if key == 'sdd_mm' else ASSUMED_CUP_DIAMETER_MM:g} mm")
        new.append(f"assuming {REQUIRED[key][0]} = {noted[key]} where not given "
                   "(--assume-defaults)")
    return new


@dataclass
class ResolvedGeometry:
    """The geometry of one image: ``values`` by key, where each came from, what is missing,
    and the values given that no geometry can have (``unusable``: key -> why)."""

    values: dict[str, float] = field(default_factory=dict)
    sources: dict[str, str] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)
    assumed_defaults: bool = False
    unusable: dict[str, str] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        """Every value given, and usable."""
        return not self.missing and not self.unusable

    def error(self, notes: dict[str, str] | None = None) -> str:
        """The error status naming the unusable values, else the missing ones, how to give
        them (``--assume-defaults`` where not used yet), and the ``notes`` (key -> text: why a
        DICOM tag could not serve) of those."""
        if self.unusable:
            return f"error: {'; '.join(self.unusable.values())}"
        parts = []
        for key in self.missing:
            if key in PRINCIPAL_KEYS:
                if key == PRINCIPAL_KEYS[0]:  # one part for the pair
                    # Only a landmark file without image sizes (cupnet solve) lacks one.
                    parts.append("principal point (--principal-point or meta.csv "
                                 f"{', '.join(PRINCIPAL_KEYS)}; no image size to take its "
                                 "centre from: give --image-size W H)")
                continue
            name, flag = REQUIRED[key]
            note = f"; {notes[key]}" if notes and key in notes else ""
            parts.append(f"{name} ({flag} or meta.csv {key}{note})")
        # --assume-defaults gives none of the principal point (the image centre does).
        hint = ("" if self.assumed_defaults or not set(self.missing) & set(REQUIRED)
                else "; or use --assume-defaults")
        return f"error: missing {', '.join(parts)}{hint}"

    def to_json(self) -> dict[str, dict[str, float | str]]:
        return {k: {"value": self.values[k], "source": self.sources[k]} for k in self.values}

    def geometry(self) -> Geometry:
        """The scalar :class:`Geometry` of the image."""
        v = self.values
        return Geometry(v["sdd_mm"], v["pixel_spacing_mm"], v["principal_u_px"],
                        v["principal_v_px"])


def resolve_geometry(size: tuple[int, int] | None, meta: dict[str, float],
                     flags: dict[str, float], assume_defaults: bool = False,
                     tags: dict[str, float | None] | None = None,
                     tag_sources: dict[str, str] | None = None,
                     file_values: dict[str, float] | None = None) -> ResolvedGeometry:
    """One image's geometry, each value from the first of: its ``meta`` row, the command
    line's ``flags``, its DICOM ``tags`` (named by ``tag_sources`` where given), the landmark
    file's own ``file_values``, an assumption (with ``assume_defaults``), the image centre
    (principal point); all by meta.csv key.

    Args:
        size: the image's ``(height, width)`` pixels, or None where unknown (a landmark file
            without it): then neither the principal point nor the spacing can be taken from
            it.
    """
    assumed: dict[str, float] = {}
    centre: dict[str, float] = {}
    if assume_defaults:
        assumed = {"sdd_mm": ASSUMED_SDD_MM, "cup_diameter_mm": ASSUMED_CUP_DIAMETER_MM}
    if size is not None:
        height, width = size
        if assume_defaults:
            assumed["pixel_spacing_mm"] = ASSUMED_DETECTOR_WIDTH_MM / width
        centre = dict(zip(PRINCIPAL_KEYS, ((width - 1) / 2, (height - 1) / 2), strict=True))
    geometry = ResolvedGeometry(assumed_defaults=assume_defaults)
    for key in GEOMETRY_KEYS:
        for source, values in (("meta.csv", meta), ("command line", flags),
                               ("DICOM tags", tags or {}), ("landmark file", file_values or {}),
                               ("assumed", assumed), ("image centre", centre)):
            if values.get(key) is not None:
                value = geometry.values[key] = float(values[key])  # type: ignore[arg-type]
                geometry.sources[key] = ((tag_sources or {}).get(key, source)
                                         if source == "DICOM tags" else source)
                if not math.isfinite(value) or (key in REQUIRED and value <= 0):
                    # Said here, not by the solver after the networks ran on the image.
                    need = "a number" if key in PRINCIPAL_KEYS else "a positive number"
                    geometry.unusable[key] = (f"{key} from {geometry.sources[key]} must be "
                                              f"{need}, got {value}")
                break
        else:
            geometry.missing.append(key)
    return geometry


@dataclass(frozen=True)
class GeometryInputs:
    """What a command was given to resolve each image's geometry from: its ``meta.csv`` rows
    (:func:`read_meta`), the command line's values (:func:`geometry_flags`) and
    ``--assume-defaults``."""

    meta: ImageTable[dict[str, float]]
    flags: dict[str, float]
    assume_defaults: bool

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> GeometryInputs:
        """From :func:`add_geometry_arguments`' arguments, ``--meta`` read now.

        Raises:
            OSError, ValueError: ``--meta`` cannot be read (:func:`read_meta`), or a flag's
                value is not positive (:func:`geometry_flags`).
        """
        return cls(ImageTable(read_meta(args.meta) if args.meta is not None else {}),
                   geometry_flags(args), args.assume_defaults)

    def resolve(self, name: str, size: tuple[int, int] | None,
                tags: dict[str, float | None] | None = None,
                tag_sources: dict[str, str] | None = None,
                file_values: dict[str, float] | None = None,
                path: str | None = None) -> ResolvedGeometry:
        """:func:`resolve_geometry` of image ``name`` (its :func:`meta_row`, its file's
        absolute ``path`` helping) and ``size``."""
        return resolve_geometry(size, meta_row(self.meta, name, path), self.flags,
                                self.assume_defaults, tags, tag_sources, file_values)


def add_geometry_arguments(parser: argparse.ArgumentParser) -> None:
    """``--meta``, ``--sdd``, ``--pixel-spacing``, ``--cup-diameter``, ``--principal-point``,
    ``--assume-defaults``."""
    parser.add_argument("--meta", type=Path,
                        help="meta.csv: image,sdd_mm,pixel_spacing_mm,cup_diameter_mm"
                             "[,principal_u_px,principal_v_px]")
    parser.add_argument("--sdd", type=float, metavar="MM", help="source-to-detector distance")
    parser.add_argument("--pixel-spacing", type=float, metavar="MM",
                        help="detector pixel spacing, mm/px (at the detector)")
    parser.add_argument("--cup-diameter", type=float, metavar="MM", help="cup outer diameter")
    parser.add_argument("--principal-point", type=float, nargs=2, metavar=("U", "V"),
                        help="principal point in pixels (default: the image centre)")
    parser.add_argument("--assume-defaults", action="store_true",
                        help=f"fill missing values (SDD {ASSUMED_SDD_MM:g} mm, cup "
                             f"{ASSUMED_CUP_DIAMETER_MM:g} mm, pixel spacing = "
                             f"{ASSUMED_DETECTOR_WIDTH_MM:g} mm / image width) instead of an "
                             "error row")


def geometry_flags(args: argparse.Namespace) -> dict[str, float]:
    """The geometry values given on the command line, by meta.csv key (absent ones left out).

    Raises:
        ValueError: a distance or size that is not a positive number, or a principal point
            that is not finite (naming its flag): it would hold for every image, so the
            command stops before the first.
    """
    flags = {"sdd_mm": args.sdd, "pixel_spacing_mm": args.pixel_spacing,
             "cup_diameter_mm": args.cup_diameter}
    for key, value in flags.items():
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{REQUIRED[key][1]} must be a positive number of mm, got {value}")
    if args.principal_point is not None:
        if not all(map(math.isfinite, args.principal_point)):
            raise ValueError("--principal-point must be two finite pixel positions, got "
                             f"{' '.join(map(str, args.principal_point))}")
        flags["principal_u_px"], flags["principal_v_px"] = args.principal_point
    return {k: v for k, v in flags.items() if v is not None}


def read_meta(path: Path) -> dict[str, dict[str, float]]:
    """meta.csv rows by image name: ``{image: {column: value}}`` (blank cells left out).

    Raises:
        ValueError: a file that is not UTF-8, no ``image`` column, an unknown column, a
            non-numeric cell, a row with more cells than the header (blank ones, a trailing
            comma, are left out), or an image given twice with other values (with its line:
            the later row had silently won).
    """
    with csv_text(path) as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or "image" not in reader.fieldnames:
            raise ValueError(f"{path}: meta.csv needs an 'image' column")
        unknown = set(reader.fieldnames) - {"image", *GEOMETRY_KEYS}
        if unknown:
            raise ValueError(f"{path}: unknown meta.csv column(s) {sorted(unknown)}")
        rows: dict[str, dict[str, float]] = {}
        for line, row in enumerate(reader, 2):
            extra = row.pop(None, [])  # cells past the header's columns
            if any(cell.strip() for cell in extra):
                raise ValueError(f"{path}, line {line}: {len(extra)} cell(s) more than the "
                                 f"header's columns ({', '.join(reader.fieldnames)})")
            try:
                values = {k: float(v) for k, v in row.items()
                          if k != "image" and v not in (None, "")}
            except ValueError as exc:
                raise ValueError(f"{path}, line {line}: {exc}") from exc
            if rows.get(row["image"], values) != values:
                raise ValueError(f"{path}, line {line}: {row['image']} is given again, with "
                                 f"other values ({rows[row['image']]} before, {values} here); "
                                 "give each image once")
            rows[row["image"]] = values
    return rows


def frame_file(name: str) -> tuple[str, int | None]:
    """An image name's file and frame: ``run.dcm#2`` -> ``("run.dcm", 2)``; a name with no
    trailing ``#N`` is its file's, frame None (a ``#`` elsewhere is the file's own)."""
    frame = re.search(r"#(\d+)$", name)
    return (name, None) if frame is None else (name[:frame.start()], int(frame.group(1)))


class ImageTable(Mapping[str, T]):
    """A side file's rows by image name (meta.csv's, a landmark file's sets, truth.csv's
    names), with the index by which an image finds its row (:meth:`key_for`): the rows by
    their file name, so that a lookup reads the rows of the image's file name alone. Each
    lookup had read every row, so a run on n images named otherwise than their rows (by
    folder, or with none) took n^2 steps: 7 ms an image at 2,000 rows."""

    def __init__(self, rows: Mapping[str, T]) -> None:
        self._rows = dict(rows)
        # Each key's parts, by its file name casefolded: a key ends a path only where its file
        # name is the path's, in either case.
        self._by_file: dict[str, list[tuple[str, list[str]]]] = {}
        for key in self._rows:
            if parts := _parts(key):
                self._by_file.setdefault(parts[-1].casefold(), []).append((key, parts))

    def __getitem__(self, key: str) -> T:
        return self._rows[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._rows)

    def __len__(self) -> int:
        return len(self._rows)

    def key_for(self, name: str, path: str | None = None) -> str | None:
        """An image's key: its name, else its file's name (frames ``name#2``), else the
        longest key that ends that file's name (``a.png`` for ``sub/a.png``), else the
        longest that ends its file's absolute ``path`` where given (``d1/a.png`` for an image
        ``a.png`` of a run on ``in/d1``, or ``../in/d1/a.png`` named by its path); keys given
        with other folders match too where their file name is theirs alone (``images/a.png``
        for an image ``a.png`` of a run on ``images/``); and then each rule again with names
        of other case (``A.PNG``: names typed on Windows). Where two keys match alike,
        neither is taken."""
        file_name = frame_file(name)[0]
        for key in (name, file_name):
            if key in self._rows:
                return key
        wanted = [_parts(file_name), *([_parts(path)] if path else [])]
        if not wanted[0]:
            return None
        for fold in (str, str.casefold):
            for parts_wanted in wanted:
                found = self._longest_tail(parts_wanted, fold)
                if found is not _NONE:
                    return found
            file_key = fold(wanted[0][-1])
            keys = [key for key, _ in self._by_file.get(wanted[0][-1].casefold(), [])
                    if fold(_base_name(key)) == file_key]
            if keys:
                return keys[0] if len(keys) == 1 else None
        return None

    def _longest_tail(self, path: list[str], fold: Callable[[str], str]) -> str | None | object:
        """The longest key whose parts end ``path`` (both folded by ``fold``), None where two
        end it alike, else :data:`_NONE`."""
        path = [fold(part) for part in path]
        tails = {key: len(parts) for key, parts in self._by_file.get(path[-1].casefold(), [])
                 if [fold(part) for part in parts] == path[len(path) - len(parts):]}
        if not tails:
            return _NONE
        most = max(tails.values())
        longest = [key for key, length in tails.items() if length == most]
        return longest[0] if len(longest) == 1 else None


_NONE = object()  # no key ends the path (None: two end it alike)


def image_table(table: Collection[str]) -> ImageTable:
    """``table`` as an :class:`ImageTable` (its keys alone where it is no mapping); indexed
    once, for the lookups of a whole run."""
    if isinstance(table, ImageTable):
        return table
    return ImageTable(table if isinstance(table, Mapping) else dict.fromkeys(table))


def key_for_image(table: Collection[str], name: str, path: str | None = None) -> str | None:
    """An image's key among ``table``'s image names (:meth:`ImageTable.key_for`; give an
    :class:`ImageTable` where many images look up one table)."""
    return image_table(table).key_for(name, path)


def row_for_image(table: Mapping[str, T], name: str, path: str | None = None) -> T | None:
    """An image's entry in ``table`` (:func:`key_for_image`), else None."""
    key = key_for_image(table, name, path)
    return None if key is None else table[key]


def unmatched_keys(table: Collection[str], names: Iterable[str],
                   paths: Mapping[str, str] | None = None) -> list[str]:
    """The keys of ``table`` that none of the images ``names`` finds (:func:`key_for_image`,
    each with its file's path in ``paths`` by name, frames by their file's): rows of a side
    file a run silently went without (a typo, another folder's images)."""
    paths, index = paths or {}, image_table(table)
    found = {index.key_for(name, paths.get(frame_file(name)[0])) for name in names}
    return [key for key in table if key not in found]


def _base_name(name: str) -> str:
    """A path's last part, with either separator (a meta.csv written on Windows)."""
    return name.replace("\\", "/").rsplit("/", 1)[-1]


def _parts(name: str) -> list[str]:
    """A path's parts, with either separator, less empty and ``.`` parts."""
    return [part for part in name.replace("\\", "/").split("/") if part not in ("", ".")]


def meta_row(meta: Mapping[str, dict[str, float]], name: str, path: str | None = None
             ) -> dict[str, float]:
    """The meta.csv row of an image (:func:`row_for_image`), else no values."""
    return row_for_image(meta, name, path) or {}
