"""``cupnet synth``: write synthetic fluoroscopy images with meta.csv and truth.csv.

Output (CONVENTIONS file formats): ``images/synth_000000.png`` (16-bit PNG) or ``.dcm``
(DICOM with DistanceSourceToDetector and ImagerPixelSpacing), ``meta.csv``
(``image,sdd_mm,pixel_spacing_mm,cup_diameter_mm,principal_u_px,principal_v_px``) and
``truth.csv`` (one row per cup; images without a cup have none).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from data_synth.anatomy import bank_path, load_bank
from data_synth.config import SynthConfig
from data_synth.dataset import synthesize

META_COLUMNS = ["image", "sdd_mm", "pixel_spacing_mm", "cup_diameter_mm", "principal_u_px",
                "principal_v_px"]
TRUTH_COLUMNS = ["image", "cup", "theta_deg", "phi_deg", "k_mm", "l_mm", "h_mm",
                 "ellipse_cx_px", "ellipse_cy_px", "ellipse_a_px", "ellipse_b_px",
                 "ellipse_angle_deg", "cup_diameter_mm"]
OUTPUTS = ("images", "meta.csv", "truth.csv")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=int, required=True, help="number of images")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--config", help="YAML of SynthConfig fields (default: the paper's "
                        "protocol with SDD and pixel spacing varied)")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                        help="image size in pixels (overrides the config's image_size, 256 x "
                             "256 by default; the shipped networks learnt 512 px and more, so "
                             "give 512 512 or larger for images to predict on)")
    parser.add_argument("--seed", type=int, default=0, help="stream seed (default 0)")
    parser.add_argument("--format", choices=("png", "dcm"), default="png",
                        help="16-bit PNG (default) or DICOM")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace images/, meta.csv and truth.csv in --out")


def write_dicom(path: Path, pixels: np.ndarray, sdd: float, spacing: float,
                stream: tuple[int, int]) -> None:
    """Save ``pixels`` ``(H, W)`` uint16 as a DICOM X-ray image with its geometry tags; its
    UIDs follow from ``stream`` (seed, image index), so a seed gives the same files again."""
    import pydicom
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    def uid(*parts: object) -> str:
        return generate_uid(entropy_srcs=["cupnet synth", *map(str, parts)])

    sop_class = "1.2.840.10008.5.1.4.1.1.12.2"  # X-Ray Radiofluoroscopic Image Storage
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = uid(*stream, "instance")
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = pydicom.Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, meta.MediaStorageSOPInstanceUID
    # One study and series a seed: the images of one run belong together.
    ds.StudyInstanceUID, ds.SeriesInstanceUID = uid(stream[0], "study"), uid(stream[0], "series")
    ds.Modality = "RF"
    ds.PatientName, ds.PatientID = "SYNTHETIC^CUPNET", path.stem
    ds.Rows, ds.Columns = pixels.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.DistanceSourceToDetector = f"{sdd:.4f}"
    ds.ImagerPixelSpacing = [f"{spacing:.6f}", f"{spacing:.6f}"]
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<u2").tobytes()
    ds.save_as(path, enforce_file_format=True)


def _fmt(value: float) -> str:
    return f"{value:.6f}"


def _config(args: argparse.Namespace) -> SynthConfig:
    """The run's config, checked, with the anatomy it draws from read once: a bad bank or
    CT had failed mid-run, after the outputs were begun (so the rerun asked for
    --overwrite). Raises ValueError naming the problem."""
    try:
        config = (SynthConfig.from_yaml(args.config) if args.config else SynthConfig())
    except OSError as error:
        raise ValueError(f"--config {args.config}: {error.strerror or error}") from error
    if args.size is not None:
        config = dataclasses.replace(config, image_size=tuple(args.size))
    if args.n < 1:
        raise ValueError(f"--n must be >= 1, got {args.n}")
    if args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    if config.p_anatomy > 0:
        source = config.anatomy_bank or config.anatomy_ct or "the shipped anatomy bank"
        try:
            load_bank(str(bank_path(config.anatomy_bank, config.anatomy_ct)))
        except (OSError, RuntimeError, ValueError, EOFError, zipfile.BadZipFile) as error:
            raise ValueError(f"anatomy from {source} cannot be used: {error}") from error
    return config


def run(args: argparse.Namespace) -> int:
    try:
        config = _config(args)
    except ValueError as error:
        print(f"cupnet synth: {error}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        print(f"cupnet synth: --out {out} is a file; give a folder", file=sys.stderr)
        return 2
    existing = [name for name in OUTPUTS if (out / name).exists()]
    if existing and not args.overwrite:
        print(f"cupnet synth: {out} already holds {', '.join(existing)}; pass --overwrite "
              "to replace them", file=sys.stderr)
        return 2
    images = out / "images"
    try:
        if images.exists():
            for old in images.glob("synth_*.*"):
                old.unlink()
        images.mkdir(parents=True, exist_ok=True)
    except OSError as error:  # a file on the way (--out under a file), no permission
        print(f"cupnet synth: cannot make {images}: {error.strerror or error}", file=sys.stderr)
        return 2

    with open(out / "meta.csv", "w", newline="") as meta_file, \
            open(out / "truth.csv", "w", newline="") as truth_file:
        meta, truth = csv.writer(meta_file), csv.writer(truth_file)
        meta.writerow(META_COLUMNS)
        truth.writerow(TRUTH_COLUMNS)
        overhanging, cups = 0, 0
        for index in tqdm(range(args.n), desc="cupnet synth", unit="image"):
            sample = synthesize(config, args.seed, index)
            overhanging += int(rims_overhanging(sample).sum())
            cups += int(sample["cup_valid"].sum())
            name = f"synth_{index:06d}.{args.format}"
            pixels = np.round(sample["image"][0].numpy() * 65535).astype(np.uint16)
            sdd, spacing, u0, v0 = sample["geometry"].tolist()
            if args.format == "png":
                if not cv2.imwrite(str(images / name), pixels):
                    raise OSError(f"could not write {images / name}")
            else:
                write_dicom(images / name, pixels, sdd, spacing, (args.seed, index))
            valid = sample["cup_valid"]
            diameter = float(sample["cup_diameter"][0])  # the image's, with a cup or without
            meta.writerow([name, _fmt(sdd), _fmt(spacing), _fmt(diameter), _fmt(u0), _fmt(v0)])
            for cup in range(int(valid.sum())):
                truth.writerow([name, cup, *map(_fmt, sample["pose"][cup].tolist()),
                                *map(_fmt, sample["ellipse"][cup].tolist()),
                                _fmt(float(sample["cup_diameter"][cup]))])
    print(f"wrote {args.n} images, meta.csv and truth.csv to {out}")
    if overhanging:
        print(f"cupnet synth: warning: {overhanging} of {cups} cups reach past the image's "
              "edge (truth.csv gives their whole rims): the field is narrow for the config's "
              "cups; widen image_size or pixel_spacing_mm, or narrow cup_diameter_mm or h_mm",
              file=sys.stderr)
    return 0


def rims_overhanging(sample: dict) -> np.ndarray:
    """``(MAX_CUPS,)`` bool: the sample's cups whose true rim points reach past its image."""
    height, width = sample["image"].shape[-2:]
    u, v = sample["rim"][..., 0].numpy(), sample["rim"][..., 1].numpy()
    outside = (u < 0) | (u > width - 1) | (v < 0) | (v > height - 1)
    return sample["cup_valid"].numpy() & outside.any(-1)
