"""Image input of ``cupnet predict``: discovery, reading and the geometry found in DICOM tags.

Every supported file becomes one or more :class:`Frame` s: an ``(H, W)`` float32 image in
``[0, 1]`` (bright = high pixel value, MONOCHROME1 inverted) and, for DICOM, the
source-to-detector distance and detector pixel spacing from its tags. Multi-frame DICOM and
multi-page TIFF give one frame each. A file that cannot be read gives a frame whose
``error`` says why, so a batch goes on past it.

:func:`iter_frames` streams: headers are probed one file at a time and pixel data is decoded
in a small thread pool a few frames ahead of the consumer, so memory stays bounded on folders
of thousands of images and on long fluoroscopy runs.
"""

from __future__ import annotations

import glob
from collections import deque
from collections.abc import Container, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from time import perf_counter

import cv2
import numpy as np
import pydicom
from PIL import Image, UnidentifiedImageError
from pydicom.dataset import FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.pixels import apply_modality_lut, apply_voi_lut, pixel_array
from pydicom.uid import (
    DeflatedExplicitVRLittleEndian,
    ExplicitVRBigEndian,
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
)

from cupnet.errors import named_error, whole_reason
from cupnet.io import jpeg12

jpeg12.register()  # 12-bit JPEG Extended, which pydicom's own plugins refuse

MAX_SIDE = 4096
RASTER_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
DICOM_SUFFIXES = (".dcm", ".dicom")
SUPPORTED_SUFFIXES = RASTER_SUFFIXES + DICOM_SUFFIXES
_DICOM_MAGIC_OFFSET = 128
# The bytes a whole file of each kind ends with: JPEG's end-of-image marker, PNG's IEND chunk
# (its empty length, type and CRC).
# Keyed by the format PIL finds in the file, not by its suffix (a JPEG renamed .png is a JPEG).
_END_MARKERS = {"JPEG": (b"\xff\xd9", "JPEG data (no end-of-image marker)"),
                "PNG": (b"\x00\x00\x00\x00IEND\xaeB`\x82", "PNG data (no IEND end chunk)")}
# Relative difference between row and column spacing below which pixels count as square.
_SQUARE_TOL = 1e-3


class ImageReadError(ValueError):
    """A file that cannot be read as an image; the message names the cause."""


@dataclass(frozen=True)
class ImageSource:
    """One input file: ``path`` on disk and ``name``, its path relative to the input root."""

    path: Path
    name: str


@dataclass
class Frame:
    """One image to process.

    Attributes:
        name: result name: the source name, plus ``#<frame>`` (from 1) for multi-frame files.
        source: the file it came from.
        last_of_source: the source's last frame (progress counts files).
        image: ``(H, W)`` float32 in ``[0, 1]``, or None where ``error`` is set.
        sdd_mm: DistanceSourceToDetector from DICOM tags, else None.
        pixel_spacing_mm: detector pixel spacing from DICOM tags, else None.
        tag_notes: why a tag value present in the file was not usable (value name -> reason).
        tag_sources: the tags each value read from them came from (value name -> text).
        error: why the file or frame could not be read, else None.
        seconds: time spent reading and decoding.
        skipped: not decoded because its name was in ``iter_frames``' ``skip``.
    """

    name: str
    source: ImageSource
    last_of_source: bool = True
    image: np.ndarray | None = None
    sdd_mm: float | None = None
    pixel_spacing_mm: float | None = None
    tag_notes: dict[str, str] | None = None
    tag_sources: dict[str, str] | None = None
    error: str | None = None
    seconds: float = 0.0
    skipped: bool = False


# -- discovery ----------------------------------------------------------------------------------
def display_name(name: str) -> str:
    """``name`` as results, overlays and titles show it: bytes of a file name that are no
    UTF-8 (a latin-1 name from an old share, which Python keeps as lone surrogates that no
    UTF-8 writer, and not OpenCV, can take) written as ``\\xe9`` escapes."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def _is_dicom_by_content(path: Path) -> bool:
    """DICOM files often have no suffix, or one of their own (``.IMA``, the last part of a
    UID name): recognise them by the ``DICM`` preamble magic."""
    try:
        with path.open("rb") as f:
            f.seek(_DICOM_MAGIC_OFFSET)
            return f.read(4) == b"DICM"
    except OSError:
        return False


def _is_raster_by_content(path: Path) -> bool:
    """Whether PIL recognises the file's content as an image (its header alone is read)."""
    try:
        with Image.open(path):
            return True
    except Exception:  # noqa: BLE001 - anything PIL cannot open is no raster to it
        return False


def _is_dicom(path: Path) -> bool:
    """The content decides where it can: a ``DICM`` marker makes a DICOM whatever the name
    (a ``.png`` exported from a PACS), and a ``.dcm`` without one is a bare dataset unless
    it holds a raster."""
    if _is_dicom_by_content(path):
        return True
    return path.suffix.lower() in DICOM_SUFFIXES and not _is_raster_by_content(path)


def _wanted(path: Path) -> bool:
    suffix = path.suffix.lower()
    if path.is_symlink() and not path.exists():
        # A broken link named as an image: its row says so, where skipping it would lose it.
        return not path.name.startswith(".") and suffix in SUPPORTED_SUFFIXES
    if path.name.startswith(".") or not path.is_file():
        return False
    return suffix in SUPPORTED_SUFFIXES or _is_dicom_by_content(path)


def _glob_root(pattern: str) -> Path:
    """The longest leading part of a glob pattern without wildcards (names are relative to it)."""
    fixed: list[str] = []
    for part in Path(pattern).parts[:-1]:
        if glob.has_magic(part):
            break
        fixed.append(part)
    return Path(*fixed) if fixed else Path(".")


def find_images(spec: str | Path, recursive: bool = False,
                exclude: Path | None = None) -> list[ImageSource]:
    """Input files named by a folder, a file or a glob pattern, in sorted order.

    A folder gives its files with a supported suffix (and DICOM files of any other name, by
    content), with ``recursive`` those of its subfolders too. A file is taken as is (reading
    it says whether it is supported). A glob keeps the files it matches (``**`` spans folders
    with ``recursive``). Names are :func:`display_name` s.

    Args:
        spec: folder, file or glob.
        recursive: descend into subfolders, leaving out the output folders of earlier runs
            (those holding a results.json and a results.csv): their overlays had been taken
            for input images.
        exclude: a folder whose contents are skipped (the output folder, when inside the input).
    Raises:
        FileNotFoundError: nothing by that name, or no images in it.
    """
    spec = str(spec)
    path = Path(spec)
    if path.is_dir():
        root = path
        candidates = path.rglob("*") if recursive else path.iterdir()
    elif path.is_file():
        return [ImageSource(path, display_name(path.name))]
    elif glob.has_magic(spec):
        root = _glob_root(spec)
        candidates = (Path(p) for p in glob.glob(spec, recursive=recursive))
    else:
        raise FileNotFoundError(f"no such file, folder or glob match: {spec}")
    excluded = [] if exclude is None else [exclude.resolve()]
    if recursive:
        excluded += [run.parent.resolve() for run in root.rglob("results.json")
                     if (run.parent / "results.csv").is_file() and run.parent != root]
    found, skipped = [], 0
    for p in candidates:
        if excluded and any(map(p.resolve().is_relative_to, excluded)):
            skipped += 1
            continue
        if _wanted(p):
            found.append(ImageSource(p, display_name(p.relative_to(root).as_posix())))
    if not found and skipped:  # it had said "no images found", with the images right there
        where = "" if exclude is None else f"the output folder {exclude} or "
        raise FileNotFoundError(f"everything {spec} names lies in {where}an earlier run's "
                                "output folder (one holding results.json and results.csv), "
                                "whose contents are skipped as input")
    if not found:
        where = "matching" if glob.has_magic(spec) and not path.is_dir() else "in"
        hint = "" if recursive or not path.is_dir() else " (use --recursive for subfolders)"
        raise FileNotFoundError(
            f"no images found {where} {spec}{hint}: looked for "
            f"{', '.join(SUPPORTED_SUFFIXES)} and DICOM files of other names")
    return sorted(found, key=lambda s: s.name)


# -- conversion ---------------------------------------------------------------------------------
# Colour in an X-ray image is an annotation (a planning tool's ellipse or line, a ruler,
# text): averaged into grey it is an edge, which the rim network took for a rim (a green
# ellipse drawn on a cup gave a pose 32 deg off, unflagged). Pixels whose channels differ by
# more than this share of the value range are inpainted from their surround, unless more
# than _ANNOTATION_MAX_SHARE of the image is coloured (a tinted image, not annotations).
_ANNOTATION_CHROMA = 0.12
_ANNOTATION_MAX_SHARE = 0.1


def _to_gray(pixels: np.ndarray) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` -> ``(H, W)``: colour channels averaged, alpha dropped,
    coloured annotations inpainted (:data:`_ANNOTATION_CHROMA`)."""
    if pixels.ndim == 2:
        return pixels
    if pixels.ndim == 3 and pixels.shape[2] in (1, 2, 3, 4):
        colour = pixels[..., :3] if pixels.shape[2] >= 3 else pixels[..., :1]
        if colour.shape[2] == 1:
            return colour[..., 0]
        return _annotations_inpainted(colour, colour.mean(-1, dtype=np.float32))
    raise ImageReadError(f"unsupported pixel layout {pixels.shape}")


def _annotations_inpainted(colour: np.ndarray, gray: np.ndarray) -> np.ndarray:
    """``gray`` ``(H, W)`` float32 with the pixels that ``colour`` ``(H, W, 3)`` shows in
    colour (and a pixel around them) inpainted (OpenCV's Telea), where they are few."""
    # Extremes over the channels in the image's own type, cast to float32 only then (rounding
    # is monotone, so as of a float32 copy): that copy of a 4096 px RGB image took 200 MB.
    span = (float(np.iinfo(colour.dtype).max) if colour.dtype.kind == "u"
            else float(np.float32(np.nanmax(colour))) - float(np.float32(np.nanmin(colour))))
    if not span > 0:
        return gray
    chroma = np.subtract(colour.max(-1), colour.min(-1), dtype=np.float32)
    marked = chroma > _ANNOTATION_CHROMA * span
    if not marked.any() or marked.mean() > _ANNOTATION_MAX_SHARE:
        return gray
    mask = cv2.dilate(marked.astype(np.uint8), np.ones((3, 3), np.uint8))
    return cv2.inpaint(gray, mask, 3, cv2.INPAINT_TELEA)


def _stretch(values: np.ndarray, shown: np.ndarray | None = None) -> np.ndarray:
    """Min-max scale to ``[0, 1]`` float32 (a constant image becomes all zeros); with a
    ``shown`` mask ``(H, W)`` bool, the range is that of those pixels (the others may fall
    outside ``[0, 1]``: the caller sets them)."""
    values = values.astype(np.float32, copy=False)
    if not np.isfinite(values).all():
        raise ImageReadError("image contains NaN or infinite values")
    ranged = values if shown is None else values[shown]
    if ranged.size == 0:
        return np.zeros_like(values)
    lo, hi = float(ranged.min()), float(ranged.max())
    return (values - lo) / (hi - lo) if hi > lo else np.zeros_like(values)


def to_unit_range(pixels: np.ndarray) -> np.ndarray:
    """Stored pixel values -> float32 ``(H, W)`` in ``[0, 1]``.

    Unsigned 8-bit images are divided by 255, so an image keeps its exposure; unsigned
    16-bit ones by the full scale of the fewest bits (8 to 16) that hold their largest value:
    a detector's 10- or 12-bit data in a 16-bit file fills its range as it would its own
    (divided by 65535 it reached 0.016, where the flat-surround and noise rules, set on
    the whole range, misread it). Other types (signed, float) are min-max scaled.
    """
    gray = _to_gray(pixels)
    if gray.dtype == np.uint8:
        return gray.astype(np.float32) * np.float32(1.0 / 255)
    if gray.dtype == np.uint16:
        bits = max(8, int(gray.max()).bit_length())
        return gray.astype(np.float32) * np.float32(1.0 / (2**bits - 1))
    return _stretch(gray)


# The clockwise turns turned_clockwise takes, degrees.
TURNS = (0, 90, 180, 270)


def turned_clockwise(image: np.ndarray, u: float, v: float, degrees: int
                     ) -> tuple[np.ndarray, float, float]:
    """``image`` ``(H, W)`` turned clockwise by ``degrees`` (one of :data:`TURNS`), and the
    pixel position ``(u, v)`` of the image moved with it (pixel centres at integers)."""
    if degrees not in TURNS:
        raise ValueError(f"turn by 0, 90, 180 or 270 degrees, not {degrees}")
    height, width = image.shape[:2]
    position = {0: (u, v), 90: (height - 1 - v, u), 180: (width - 1 - u, height - 1 - v),
                270: (v, width - 1 - u)}
    # np.rot90 turns counterclockwise for positive k.
    return np.ascontiguousarray(np.rot90(image, -degrees // 90)), *position[degrees]


def _check_size(width: int, height: int) -> None:
    if width <= 0 or height <= 0:
        raise ImageReadError(f"image has no pixels ({width} x {height})")
    if width > MAX_SIDE or height > MAX_SIDE:
        raise ImageReadError(f"image too large: {width} x {height} px (at most "
                             f"{MAX_SIDE} x {MAX_SIDE})")


# -- DICOM --------------------------------------------------------------------------------------
def _positive(value: object) -> float | None:
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return number if np.isfinite(number) and number > 0 else None


# The source of a detector spacing read from PixelSpacing alone: by the standard the spacing in
# the patient, smaller than the detector's by the magnification (often 1.1-1.5), so h comes out
# too small by that factor unless the file means the detector's.
PATIENT_SPACING_SOURCE = ("DICOM PixelSpacing, taken as the detector's (no ImagerPixelSpacing "
                          "or EstimatedRadiographicMagnificationFactor)")


def dicom_geometry(ds: pydicom.Dataset
                   ) -> tuple[float | None, float | None, dict[str, str], dict[str, str]]:
    """Source-to-detector distance and detector pixel spacing (mm) from DICOM tags.

    Spacing comes from ImagerPixelSpacing (at the detector), else from PixelSpacing times
    EstimatedRadiographicMagnificationFactor where present (PixelSpacing is calibrated to the
    patient, ImagerPixelSpacing / magnification). Non-square pixels are not usable.

    Returns:
        ``(sdd_mm, pixel_spacing_mm, notes, sources)``; a value is None where absent or
        unusable, ``notes`` says why for tags that were present but unusable, and
        ``sources`` which tags each value came from (:data:`PATIENT_SPACING_SOURCE` where
        PixelSpacing had no magnification factor beside it).
    """
    notes: dict[str, str] = {}
    sources: dict[str, str] = {}
    sdd = _positive(ds.get("DistanceSourceToDetector"))
    if sdd is not None:
        sources["sdd_mm"] = "DICOM DistanceSourceToDetector"
    if sdd is None and "DistanceSourceToDetector" in ds:
        notes["sdd_mm"] = f"DICOM DistanceSourceToDetector {ds.DistanceSourceToDetector!r} unusable"
    spacing = None
    unusable = []  # an unusable ImagerPixelSpacing leaves PixelSpacing to try
    for keyword in ("ImagerPixelSpacing", "PixelSpacing"):
        if keyword not in ds:
            continue
        pair = [_positive(v) for v in ds[keyword].value] if ds[keyword].VM == 2 else [None]
        if None in pair:
            unusable.append(f"DICOM {keyword} {ds[keyword].value!r} unusable")
            continue
        row, col = pair
        if abs(row - col) > _SQUARE_TOL * max(row, col):
            unusable.append(f"DICOM {keyword} is not square ({row} x {col} mm); give "
                            "--pixel-spacing")
            continue
        spacing = (row + col) / 2
        sources["pixel_spacing_mm"] = f"DICOM {keyword}"
        if keyword == "PixelSpacing":
            magnification = _positive(ds.get("EstimatedRadiographicMagnificationFactor"))
            spacing *= magnification or 1.0
            sources["pixel_spacing_mm"] = ("DICOM PixelSpacing x "
                                           "EstimatedRadiographicMagnificationFactor"
                                           if magnification else PATIENT_SPACING_SOURCE)
        break
    if spacing is None and unusable:
        notes["pixel_spacing_mm"] = "; ".join(unusable)
    return sdd, spacing, notes, sources


def _bare_dataset(path: Path, stop_before_pixels: bool) -> pydicom.Dataset | None:
    """A DICOM dataset stored bare (no preamble, no file meta: old exports and archives),
    with the transfer syntax it was read in set in its file meta; None where the file holds
    no image dataset."""
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=stop_before_pixels, force=True)
        implicit, little = ds.original_encoding
        ok = "Rows" in ds and "Columns" in ds and implicit is not None
    except Exception:  # noqa: BLE001 - read by force, anything may fail: not a DICOM file
        return None
    if not ok:
        return None
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = (ImplicitVRLittleEndian if implicit else
                                      ExplicitVRLittleEndian if little else
                                      ExplicitVRBigEndian)
    return ds


def _dicom_header(path: Path) -> pydicom.Dataset:
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except InvalidDicomError as exc:
        ds = _bare_dataset(path, stop_before_pixels=True)
        if ds is None:
            # pydicom's message ends "Use force=True to force reading.", advice for its API
            # that a predict user cannot take.
            raise ImageReadError("not a DICOM file (no 'DICM' prefix and no file meta "
                                 "information header)") from exc
    except (EOFError, OSError, ValueError, KeyError, TypeError) as exc:
        raise ImageReadError(f"corrupt or truncated DICOM header ({exc})") from exc
    for keyword in ("Rows", "Columns"):
        if keyword not in ds:
            # pydicom reads a header cut short without complaint, as far as it goes.
            raise ImageReadError(f"DICOM has no image ({keyword} missing: a dataset without "
                                 "pixel data, or a file cut short in its header)")
    _check_size(int(ds.Columns), int(ds.Rows))
    photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2"))
    if photometric not in ("MONOCHROME1", "MONOCHROME2", "RGB", "YBR_FULL", "YBR_FULL_422"):
        raise ImageReadError(f"unsupported DICOM PhotometricInterpretation {photometric}")
    return ds


def _holds_pixel_data(path: Path) -> bool:
    """Whether a DICOM file that failed to decode has a pixel data element at all (one that
    cannot be read again is taken to have one: its data is what broke)."""
    keywords = ("PixelData", "FloatPixelData", "DoubleFloatPixelData")
    try:
        ds = pydicom.dcmread(path, specific_tags=list(keywords))
    except Exception:  # noqa: BLE001 - any failure here leaves the first one to report
        return True
    return any(keyword in ds for keyword in keywords)


def _dicom_frame(path: Path, ds: pydicom.Dataset, index: int | None) -> np.ndarray:
    """One decoded frame with modality LUT / rescale and VOI LUT / window applied."""
    syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    try:
        if syntax == DeflatedExplicitVRLittleEndian or ds.preamble is None:
            # pixel_array(path) reads neither a deflated file nor a bare dataset.
            whole = (pydicom.dcmread(path) if ds.preamble is not None
                     else _bare_dataset(path, stop_before_pixels=False))
            stored = whole.pixel_array if whole is not None else None
            if stored is None:
                raise ValueError("the dataset read again has no pixel data")
            stored = stored if index is None else stored[index]
        else:
            stored = pixel_array(path, index=index)
    except Exception as exc:  # pydicom raises many types on broken pixel data
        if not _holds_pixel_data(path):  # it had been called corrupt
            raise ImageReadError("DICOM has no image (no Pixel Data element: a dataset "
                                 "without pixel data)") from exc
        # A decoder's message may run over lines (one a plugin): one line, all of them.
        reason = whole_reason(exc)
        try:
            compressed = syntax is not None and syntax.is_compressed
        except ValueError:  # a private or unknown transfer syntax: no decoder knows it
            raise ImageReadError(f"cannot decode DICOM pixel data in transfer syntax "
                                 f"{syntax} ({reason})") from exc
        if compressed:
            # Intact data no installed decoder reads (a colour JPEG Extended stream, HTJ2K
            # where GDCM is old) or a damaged stream: say which compression, and what the
            # decoders said.
            raise ImageReadError(f"cannot decode DICOM pixel data compressed as {syntax.name} "
                                 f"(unsupported or damaged: {reason})") from exc
        raise ImageReadError(f"corrupt or truncated DICOM pixel data ({reason})") from exc
    padding = None
    if stored.ndim == 3 and stored.shape[-1] == 3:
        stored = _to_gray(stored)
    elif stored.ndim == 2:
        padding = _padding(stored, ds)
    else:
        raise ImageReadError(f"unexpected DICOM frame shape {stored.shape}")
    values = apply_voi_lut(apply_modality_lut(stored, ds), ds)
    image = _stretch(values, None if padding is None else ~padding)
    if str(ds.get("PhotometricInterpretation")) == "MONOCHROME1":
        image = 1.0 - image  # MONOCHROME1: low values are bright
    if padding is not None:
        image[padding] = 0  # a flat black surround, as an intensifier's
    return image


def _padding(stored: np.ndarray, ds: pydicom.Dataset) -> np.ndarray | None:
    """The pixels a grey frame marks as padding (PixelPaddingValue, through
    PixelPaddingRangeLimit where given, in stored values), or None where it marks none.

    A CR or DX image's padding (the plate's edge, a shuttered border) is often the type's
    largest value; stretched with the rest, it squeezed the picture into a few hundredths of
    the range, and the cup went unseen."""
    value = ds.get("PixelPaddingValue")
    if not isinstance(value, int):  # absent, or unreadable (a byte string of unknown sign)
        return None
    limit = ds.get("PixelPaddingRangeLimit")
    low, high = sorted((value, limit if isinstance(limit, int) else value))
    padding = (stored >= low) & (stored <= high)
    return padding if padding.any() else None


# -- reading ------------------------------------------------------------------------------------
# TIFF modes whose stored values are what the page shows (grey levels, or colour channels).
_TIFF_GREY_OR_RGB = ("1", "L", "LA", "I", "I;16", "I;16B", "I;16L", "I;16N", "F", "RGB", "RGBA")


def _read_raster(path: Path, page: int | None, kind: str) -> np.ndarray:
    """One page of a raster file whose content PIL found to be ``kind`` ("PNG", "JPEG",
    "TIFF", ...), whatever its suffix."""
    if kind == "TIFF":
        try:
            with Image.open(path) as im:
                im.seek(page or 0)
                _check_size(*im.size)  # a page's own (the probe saw the first page's)
                # A palette's (or CMYK's, LAB's) values are no greys: what they show is.
                pixels = np.asarray(im if im.mode in _TIFF_GREY_OR_RGB else im.convert("RGB"))
        except ImageReadError:
            raise  # the page's size, named as such
        except (OSError, ValueError, EOFError) as exc:
            raise ImageReadError(f"corrupt or truncated TIFF ({exc})") from exc
        return to_unit_range(pixels)  # a decoded file's values: their own error, not "corrupt"
    # libjpeg decodes a cut-off JPEG into a partly grey image without failing, and libpng
    # fails on a cut-off PNG with "libpng error: Read Error" on stderr: require the end
    # marker (some writers pad after it, so look at the last kilobyte; a JPEG may carry a
    # longer trailer, a phone's motion photo, so its segments are walked to find its end).
    if kind in _END_MARKERS and _END_MARKERS[kind][0] not in _tail(path, 1024) and not (
            kind == "JPEG" and _jpeg_ends(path.read_bytes())):
        raise ImageReadError(f"corrupt or truncated {_END_MARKERS[kind][1]}")
    try:
        str(path).encode("utf-8")
        decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # faster than imdecode
    except UnicodeEncodeError:  # a name no UTF-8 holds, which OpenCV cannot open by name
        decoded = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise ImageReadError(f"corrupt or truncated {kind} data")
    return to_unit_range(decoded)


# EXIF Orientation -> what turns the stored pixels as every viewer shows them (a phone's
# photo of a monitor, an exporter writing rows as the sensor read them).
_EXIF_ORIENTATION = 0x0112
_UPRIGHT = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
            5: lambda a: a.T, 6: lambda a: np.rot90(a, -1), 7: lambda a: a.T[::-1, ::-1],
            8: lambda a: np.rot90(a, 1)}


def _orientation(image: Image.Image) -> int:
    """A raster's EXIF Orientation; 1 where it has none, or where reading it meets damage
    (PNG's chunks past a cut: the decoding names that)."""
    try:
        return int(image.getexif().get(_EXIF_ORIENTATION, 1) or 1)
    except (OSError, ValueError, SyntaxError, TypeError):
        return 1


def upright(image: np.ndarray, orientation: int) -> np.ndarray:
    """``(H, W)`` stored pixels as shown under EXIF ``orientation`` (1-8; 1 and unknown
    values: as stored), contiguous."""
    turn = _UPRIGHT.get(orientation)
    return image if turn is None else np.ascontiguousarray(turn(image))


def _tail(path: Path, size: int) -> bytes:
    with path.open("rb") as f:
        f.seek(max(0, path.stat().st_size - size))
        return f.read()


def _jpeg_ends(data: bytes) -> bool:
    """Whether a JPEG's own segments reach its end-of-image marker: headers are skipped by
    their lengths (an EXIF thumbnail's own marker lies inside one), entropy-coded data up to
    the next marker (0xFF followed by neither a stuffed 0x00 nor a restart marker)."""
    at = 2  # after the start-of-image marker
    while at + 1 < len(data):
        if data[at] != 0xFF:
            return False
        marker = data[at + 1]
        if marker == 0xD9:
            return True
        if marker == 0xFF or 0xD0 <= marker <= 0xD7 or marker == 0x01:  # fill, no length
            at += 1 if marker == 0xFF else 2
            continue
        at += 2 + int.from_bytes(data[at + 2:at + 4], "big")
        if marker == 0xDA:  # start of scan: its entropy-coded data runs to the next marker
            while (at := data.find(b"\xff", at)) != -1 and at + 1 < len(data) and (
                    data[at + 1] == 0x00 or 0xD0 <= data[at + 1] <= 0xD7):
                at += 2
            if at == -1:
                return False
    return False


@dataclass(frozen=True)
class _Unit:
    """One frame to decode: ``index`` None for single-frame files."""

    source: ImageSource
    index: int | None
    last: bool
    header: pydicom.Dataset | None = None
    kind: str = ""  # a raster's format, as PIL found it in the file
    orientation: int = 1  # a raster's EXIF Orientation (1: as stored)


def _probe(source: ImageSource) -> list[_Unit]:
    """Check a file cheaply (size, format, frame count) without decoding pixel data."""
    path = source.path
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise ImageReadError(f"cannot open file ({exc.strerror})") from exc
    if size == 0:
        raise ImageReadError("empty file (0 bytes)")
    suffix = path.suffix.lower()
    if _is_dicom(path):
        ds = _dicom_header(path)
        n = _frame_count(ds, size)
        return [_Unit(source, i if n > 1 else None, i == n - 1, ds) for i in range(n)]
    if suffix not in SUPPORTED_SUFFIXES:
        raise ImageReadError(f"unsupported file type {suffix or '(no suffix)'}; "
                             f"supported: {', '.join(SUPPORTED_SUFFIXES)}")
    try:
        with Image.open(path) as im:
            width, height, kind = *im.size, str(im.format)
            n = getattr(im, "n_frames", 1) if kind == "TIFF" else 1
            orientation = _orientation(im)
    except UnidentifiedImageError as exc:
        raise ImageReadError(f"not a readable {suffix.lstrip('.').upper()} image "
                             "(unknown or corrupt content)") from exc
    except Image.DecompressionBombError as exc:  # PIL refuses sizes far over MAX_SIDE
        raise ImageReadError(f"image too large: its header gives over "
                             f"{2 * Image.MAX_IMAGE_PIXELS:,} pixels (at most {MAX_SIDE} x "
                             f"{MAX_SIDE})") from exc
    except OSError as exc:
        raise ImageReadError(f"corrupt image header ({exc})") from exc
    _check_size(width, height)
    return [_Unit(source, i if n > 1 else None, i == n - 1, kind=kind,
                  orientation=orientation if orientation in _UPRIGHT else 1) for i in range(n)]


def _frame_count(ds: pydicom.Dataset, file_bytes: int) -> int:
    """A DICOM header's NumberOfFrames (absent or 0: one), checked against the file's size
    where its pixel data is stored uncompressed.

    Raises:
        ImageReadError: a count that is no whole number above 0, or more uncompressed frames
            than the file holds (a row each would repeat one error thousands of times).
    """
    value = ds.get("NumberOfFrames", 1)
    try:
        count = int(value or 1)
    except (TypeError, ValueError):
        count = 0
    if count < 1:
        raise ImageReadError(f"invalid DICOM NumberOfFrames {value}")
    syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    try:  # a deflated file's pixel data is compressed too, with the rest of the dataset
        compressed = syntax is None or syntax.is_compressed or syntax.is_deflated
    except ValueError:  # a private transfer syntax: decoding says what it can
        compressed = True
    frame_bytes = (int(ds.Rows) * int(ds.Columns) * int(ds.get("SamplesPerPixel", 1) or 1)
                   * int(ds.get("BitsAllocated", 8) or 8) // 8)
    if count > 1 and not compressed and count * frame_bytes > file_bytes:
        raise ImageReadError(
            f"DICOM NumberOfFrames {count} of {ds.Columns} x {ds.Rows} px needs "
            f"{count * frame_bytes:,} bytes of pixel data, but the file holds {file_bytes:,}")
    return count


def _frame_name(unit: _Unit) -> str:
    return unit.source.name if unit.index is None else f"{unit.source.name}#{unit.index + 1}"


def _decode(unit: _Unit) -> Frame:
    start = perf_counter()
    frame = Frame(_frame_name(unit), unit.source, unit.last)
    try:
        if unit.header is not None:
            frame.image = _dicom_frame(unit.source.path, unit.header, unit.index)
            (frame.sdd_mm, frame.pixel_spacing_mm, frame.tag_notes,
             frame.tag_sources) = dicom_geometry(unit.header)
        else:
            frame.image = upright(_read_raster(unit.source.path, unit.index, unit.kind),
                                  unit.orientation)
    except ImageReadError as exc:
        frame.error = str(exc)
    except (OSError, MemoryError) as exc:
        frame.error = f"cannot read file ({exc})"
    except Exception as exc:  # noqa: BLE001 - a decoder's own failure ends this file only
        frame.error = unreadable(exc)
    frame.seconds = perf_counter() - start
    return frame


def read_frames(source: ImageSource | str | Path) -> list[Frame]:
    """All frames of one file, decoded now (errors in ``Frame.error``)."""
    if not isinstance(source, ImageSource):
        source = ImageSource(Path(source), display_name(Path(source).name))
    return list(iter_frames([source], workers=0))


def read_image(path: str | Path) -> np.ndarray:
    """The first frame of one file as ``(H, W)`` float32 in ``[0, 1]``.

    Raises:
        ImageReadError: naming why the file cannot be read.
    """
    source = ImageSource(Path(path), display_name(Path(path).name))
    units = _probe(source)
    frame = _decode(units[0])
    if frame.error is not None:
        raise ImageReadError(f"{path}: {frame.error}")
    return frame.image  # type: ignore[return-value]


def unreadable(error: Exception) -> str:
    """The row of a file whose reader failed in a way no check foresaw: the failure named."""
    return f"unreadable file ({named_error(error)})"


def _units(sources: Iterable[ImageSource]) -> Iterator[_Unit | Frame]:
    """Frames to decode, or a finished error frame for a file that fails its probe."""
    for source in sources:
        try:
            units = _probe(source)
        except ImageReadError as exc:
            units = [Frame(source.name, source, error=str(exc))]
        except Exception as exc:  # noqa: BLE001 - a reader's own failure ends this file only
            units = [Frame(source.name, source, error=unreadable(exc))]
        yield from units


def iter_frames(sources: Iterable[ImageSource], workers: int = 2, lookahead: int = 8,
                skip: Container[str] = frozenset()) -> Iterator[Frame]:
    """Decoded frames of ``sources`` in order, read ``lookahead`` frames ahead in threads.

    OpenCV, zlib and pydicom's decoders release the GIL, so reading overlaps the network.
    At most ``lookahead`` decoded frames wait in memory. ``workers=0`` reads in the caller's
    thread. Frames named in ``skip`` (done by an earlier run) come back undecoded with
    ``skipped`` set, so the caller can still count files.
    """

    def start(unit: _Unit | Frame) -> Future[Frame] | Frame:
        if isinstance(unit, Frame):
            return unit
        if _frame_name(unit) in skip:
            return Frame(_frame_name(unit), unit.source, unit.last, skipped=True)
        return _decode(unit) if pool is None else pool.submit(_decode, unit)

    pool = ThreadPoolExecutor(workers, thread_name_prefix="cupnet-read") if workers else None
    pending: deque[Future[Frame] | Frame] = deque()
    try:
        for unit in _units(sources):
            pending.append(start(unit))
            while len(pending) > lookahead:
                yield _result(pending.popleft())
        while pending:
            yield _result(pending.popleft())
    finally:
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)


def _result(item: Future[Frame] | Frame) -> Frame:
    return item if isinstance(item, Frame) else item.result()
