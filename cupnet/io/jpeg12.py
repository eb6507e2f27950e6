"""A pydicom decoding plugin for 12-bit JPEG Extended (process 4) DICOM pixel data.

Some C-arms and archives export fluoroscopy as lossy JPEG Extended (transfer syntax
1.2.840.10008.1.2.4.51) with 12-bit samples. pydicom's plugins for it are Pillow and GDCM,
which refuse 12-bit samples, and pylibjpeg, whose libjpeg is GPL. imagecodecs (BSD-3-Clause)
wraps libjpeg-turbo 3, which decodes 12-bit DCT streams. :func:`register` adds it as the
last plugin of pydicom's JPEG Extended decoder, so the others keep what they decode (8-bit
streams) and it takes what they refuse. Grayscale only: a colour stream's colour transform
is a guess without an Adobe marker, and pydicom's other plugins own those.

The module follows pydicom's plugin contract (``DECODER_DEPENDENCIES``, ``is_available``
and the decoding function); it is not meant to be called directly.
"""

from __future__ import annotations

import importlib.util

from pydicom import uid
from pydicom.pixels.decoders import JPEGExtended12BitDecoder
from pydicom.pixels.decoders.base import DecodeRunner

PLUGIN = "imagecodecs"
DECODER_DEPENDENCIES = {uid.JPEGExtended12Bit: ("imagecodecs>=2024.1",)}


def is_available(syntax: str) -> bool:
    """True where ``syntax`` is JPEG Extended and imagecodecs is installed."""
    return syntax == uid.JPEGExtended12Bit and importlib.util.find_spec("imagecodecs") is not None


def decode_frame(src: bytes, runner: DecodeRunner) -> bytes:
    """One grayscale JPEG Extended frame ``src`` (a codestream) -> its samples as bytes, in
    little-endian words of ``runner.bits_allocated`` bits (8 or 16), as pydicom lays out a
    frame.

    Raises:
        NotImplementedError: colour data (pydicom then reports every plugin's refusal).
        ValueError: a codestream whose shape is not the header's ``Rows x Columns``.
        imagecodecs.JpegError (from libjpeg-turbo): a damaged codestream.
    """
    import imagecodecs  # 0.05 s: only once a 12-bit JPEG file is read

    if runner.samples_per_pixel != 1:
        raise NotImplementedError(f"the {PLUGIN} plugin decodes grayscale JPEG Extended only")
    frame = imagecodecs.jpeg8_decode(src)
    if frame.shape != (runner.rows, runner.columns):
        raise ValueError(f"JPEG codestream of {frame.shape} samples for a "
                         f"{runner.rows} x {runner.columns} frame")
    return frame.astype(f"<u{runner.bits_allocated // 8}", copy=False).tobytes()


def register() -> None:
    """Add :func:`decode_frame` as the last plugin of pydicom's JPEG Extended decoder (once
    a process; pydicom keeps it in its module-level decoder)."""
    if PLUGIN not in JPEGExtended12BitDecoder.available_plugins:
        try:
            JPEGExtended12BitDecoder.add_plugin(PLUGIN, (__name__, "decode_frame"))
        except ValueError:  # added before, as unavailable (imagecodecs is not installed)
            pass
