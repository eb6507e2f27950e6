"""``results.csv`` of CONVENTIONS: columns, rows, atomic writing and reading back.

One row per detected cup; an image without a cup result gets one status row
(``no_cup`` or ``error: <reason>``). Shared by ``cupnet predict`` and ``cupnet solve``.
"""

from __future__ import annotations

import csv
import math
import os
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import torch

from cupnet.io.csvfile import csv_text
from cupnet.orientation import anatomic_angles, operative_angles

POSE_COLUMNS = ("anteversion_deg", "inclination_deg", "k_mm", "l_mm", "h_mm")
ELLIPSE_COLUMNS = ("ellipse_cx_px", "ellipse_cy_px", "ellipse_a_px", "ellipse_b_px",
                   "ellipse_angle_deg")
ALT_COLUMNS = tuple("alt_" + c for c in POSE_COLUMNS)
# CONVENTIONS' columns, then the model's doubt of the pose and whether to check the cup by
# eye (blank where not measured: both for a model without its dome-outline stage, the doubt
# for given landmarks, whose check is their distance to the rim), and how the
# model took the image to show metal (dark or bright; blank where not judged).
CHECK_COLUMNS = ("doubt", "check")
# Last, the pose's angles in Murray's operative and anatomic definitions (cupnet.orientation;
# CONVENTIONS' are his radiographic ones).
MURRAY_COLUMNS = ("operative_anteversion_deg", "operative_inclination_deg",
                  "anatomic_anteversion_deg", "anatomic_inclination_deg")
# Then the pose's standard errors where measured (given landmarks: their scatter about the
# solved rim, cupnet.pose.pose_standard_errors; blank for the network's).
SD_COLUMNS = ("anteversion_sd_deg", "inclination_sd_deg", "k_sd_mm", "l_sd_mm", "h_sd_mm")
# Then the image's noise (display units) where the model denoised it first, and whether it
# did (blank where not judged: the model's denoise_above is None or infinite, or landmarks
# given; the noise blank too under the bar).
NOISE_COLUMNS = ("noise", "denoised")
# Last, the factor the model enlarged a small image by first, or reduced a large one by
# (blank where it did not).
RESULT_COLUMNS = ("image", "cup", "status", *POSE_COLUMNS, *ELLIPSE_COLUMNS, "residual_px",
                  "seconds", *ALT_COLUMNS, *CHECK_COLUMNS, "metal", *MURRAY_COLUMNS,
                  *SD_COLUMNS, *NOISE_COLUMNS, "enlarged", "reduced")


# A row's status: one of these, or "error: <reason>" (as the files' readers say it).
STATUSES = ("ok", "ambiguous", "no_cup")
STATUS_RULE = f"{', '.join(STATUSES)} or error: <reason>"


def is_status(status: str | None) -> bool:
    """Whether ``status`` (a results.csv cell; None where blank) is one a row takes."""
    return status in STATUSES or (status or "").startswith("error")


def _finite(values: Iterable[Any]) -> list[float | None]:
    return [float(v) if v is not None and math.isfinite(float(v)) else None for v in values]


def cup_row(name: str, index: int, cup: Any, seconds: float) -> dict:
    """One row of a detected cup (a :class:`cupnet.model.CupDetection`; public units, None for
    blank cells)."""
    row = {"image": name, "cup": index, "status": cup.status}
    row.update(zip(POSE_COLUMNS, _finite(cup.pose), strict=True))
    row.update(zip(ELLIPSE_COLUMNS, _finite(cup.ellipse), strict=True))
    row["residual_px"] = _finite([cup.residual_px])[0]
    row["seconds"] = seconds
    alt = cup.alt_pose if cup.alt_pose is not None else [None] * 5
    row.update(zip(ALT_COLUMNS, _finite(alt), strict=True))
    if cup.doubt is not None:
        row["doubt"] = _finite([cup.doubt])[0]
    if cup.check is not None:
        row["check"] = int(cup.check)
    if cup.metal_bright is not None:
        row["metal"] = "bright" if cup.metal_bright else "dark"
    pose = torch.as_tensor(cup.pose, dtype=torch.float64)
    if torch.isfinite(pose).all():
        angles = torch.cat([operative_angles(pose), anatomic_angles(pose)])
        row.update(zip(MURRAY_COLUMNS, angles.tolist(), strict=True))
    if cup.pose_sd is not None:
        row.update(zip(SD_COLUMNS, _finite(cup.pose_sd), strict=True))
    if cup.noise is not None:
        row["noise"] = _finite([cup.noise])[0]
    if cup.denoised is not None:
        row["denoised"] = int(cup.denoised)
    if cup.enlarged is not None:
        row["enlarged"] = float(cup.enlarged)
    if cup.reduced is not None:
        row["reduced"] = float(cup.reduced)
    return row


def status_row(name: str, status: str, seconds: float, cup: int | None = None) -> dict:
    """The row of an image without a cup result, ``no_cup`` or ``error: <reason>``, or of
    a known ``cup`` (a landmark file's) that could not be solved."""
    return {"image": name, "cup": cup, "status": status, "seconds": seconds}


def atomic_write(path: Path, write: Callable[[Any], None], binary: bool = False) -> None:
    """Write a file through ``write(f)`` (text, UTF-8, or ``binary``) so a reader never sees
    it half-written; where it cannot be written (a name too long for the file system, a full
    disk, no permission) the temporary file is removed, not left beside the results, and the
    error raised."""
    options: dict[str, Any] = {} if binary else {"newline": "", "encoding": "utf-8"}
    name = path.parent / f"tmp{uuid.uuid4().hex}.tmp"
    # Created as open() creates a file (0666 less the umask): tempfile's own are 0600, and
    # results a colleague or a web server is to read were the owner's alone.
    descriptor = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    with os.fdopen(descriptor, "wb" if binary else "w", **options) as tmp:
        try:
            write(tmp)
        except BaseException:
            tmp.close()
            os.unlink(name)
            raise
    try:
        os.replace(name, path)
    except OSError:
        os.unlink(name)
        raise


def _cell(value: object) -> object:
    if value is None:
        return ""
    return f"{value:.6g}" if isinstance(value, float) else value


def write_results_csv(path: Path, records: Iterable[dict]) -> None:
    """All rows (``record["rows"]``) of the records, atomically."""

    def write(f: Any) -> None:
        writer = csv.DictWriter(f, RESULT_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for record in records:
            for row in record["rows"]:
                writer.writerow({k: _cell(row.get(k)) for k in RESULT_COLUMNS})

    atomic_write(path, write)


def read_results_csv(path: Path) -> dict[str, list[dict]]:
    """Rows of an existing results.csv by image (values as strings; blank cells None).

    Raises:
        ValueError: a row whose status is none a row takes (:func:`is_status`), with its
            line: a file cut short mid-row had been resumed from, its half row kept.
    """
    by_image: dict[str, list[dict]] = {}
    with csv_text(path) as f:
        reader = csv.DictReader(f)
        for row in reader:
            if not is_status(row.get("status")):
                raise ValueError(f"{path}, line {reader.line_num}: status "
                                 f"{row.get('status')!r} is none of {STATUS_RULE} (a row cut "
                                 "short?)")
            by_image.setdefault(row["image"], []).append(
                {k: (v if v != "" else None) for k, v in row.items()})
    return by_image
