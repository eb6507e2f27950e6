"""DICOM test files written with pydicom, re-encoded by GDCM or given JPEG codestreams (imported by
the image and predict tests)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.uid import (
    ExplicitVRLittleEndian,
    JPEGExtended12Bit,
    SecondaryCaptureImageStorage,
    generate_uid,
)


def write_dicom(path: Path, pixels: np.ndarray, photometric: str = "MONOCHROME2",
                **tags: object) -> Path:
    """A minimal secondary-capture DICOM file; ``pixels`` uint16 ``(H, W)`` or ``(F, H, W)``."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = SecondaryCaptureImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = SecondaryCaptureImageStorage
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.set_pixel_data(pixels, photometric_interpretation=photometric, bits_stored=16)
    for key, value in tags.items():
        setattr(ds, key, value)
    ds.save_as(path, enforce_file_format=True)
    return path


def transcoded(source: Path, path: Path, transfer_syntax: str) -> Path:
    """``source`` (a DICOM file) re-encoded by GDCM, an independent encoder, in
    ``transfer_syntax`` (a UID), written to ``path``."""
    import gdcm

    reader = gdcm.ImageReader()
    reader.SetFileName(str(source))
    assert reader.Read(), source
    change = gdcm.ImageChangeTransferSyntax()
    change.SetTransferSyntax(gdcm.TransferSyntax(gdcm.TransferSyntax.GetTSType(transfer_syntax)))
    change.SetInput(reader.GetImage())
    assert change.Change(), transfer_syntax
    writer = gdcm.ImageWriter()
    writer.SetFileName(str(path))
    writer.SetFile(reader.GetFile())
    writer.SetImage(change.GetOutput())
    assert writer.Write(), path
    return path


def with_jpeg_streams(source: Path, path: Path, streams: list[bytes]) -> Path:
    """``source`` (a DICOM file) with its pixel data replaced by the JPEG codestreams
    ``streams``, one a frame, as JPEG Extended (process 2 and 4), written to ``path``."""
    ds = pydicom.dcmread(source)
    ds.PixelData = encapsulate(streams)
    ds["PixelData"].VR = "OB"
    ds.file_meta.TransferSyntaxUID = JPEGExtended12Bit
    ds.save_as(path, enforce_file_format=True)
    return path
