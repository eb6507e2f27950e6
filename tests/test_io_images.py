"""Image reading: formats, bit depths, DICOM tags and LUTs, broken files, discovery."""

from __future__ import annotations

import os
import re
import struct
import zlib
from pathlib import Path

import cv2
import imagecodecs
import numpy as np
import pydicom
import pytest
from dicom_factory import transcoded, with_jpeg_streams, write_dicom
from PIL import Image, ImageOps
from pydicom.data import get_testdata_file
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_dataset
from pydicom.pixels import pixel_array
from pydicom.uid import (
    DeflatedExplicitVRLittleEndian,
    JPEG2000Lossless,
    JPEGLosslessSV1,
    JPEGLSLossless,
)

from cupnet.io.images import (
    MAX_SIDE,
    PATIENT_SPACING_SOURCE,
    ImageReadError,
    ImageSource,
    find_images,
    iter_frames,
    read_frames,
    read_image,
    turned_clockwise,
)


def gradient(height: int = 48, width: int = 64) -> np.ndarray:
    """A float ramp in [0, 1] with distinct values along u and v."""
    u = np.linspace(0, 1, width)[None, :]
    v = np.linspace(0, 1, height)[:, None]
    return (0.7 * u + 0.3 * v).astype(np.float64)


def test_png_8_and_16_bit_give_the_same_image(tmp_path: Path) -> None:
    ramp = gradient()
    cv2.imwrite(str(tmp_path / "a8.png"), np.round(ramp * 255).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "a16.png"), np.round(ramp * 65535).astype(np.uint16))
    img8, img16 = read_image(tmp_path / "a8.png"), read_image(tmp_path / "a16.png")
    assert img8.dtype == img16.dtype == np.float32
    assert img8.shape == img16.shape == ramp.shape
    np.testing.assert_allclose(img16, ramp, atol=1 / 65535)
    np.testing.assert_allclose(img8, ramp, atol=0.5 / 255 + 1e-6)


def test_jpeg_tiff_and_colour_png(tmp_path: Path) -> None:
    ramp = gradient()
    cv2.imwrite(str(tmp_path / "a.jpg"), np.round(ramp * 255).astype(np.uint8),
                [cv2.IMWRITE_JPEG_QUALITY, 100])
    cv2.imwrite(str(tmp_path / "a.tif"), np.round(ramp * 65535).astype(np.uint16))
    colour = np.repeat(np.round(ramp * 255).astype(np.uint8)[..., None], 3, -1)
    cv2.imwrite(str(tmp_path / "rgb.png"), colour)
    np.testing.assert_allclose(read_image(tmp_path / "a.jpg"), ramp, atol=3 / 255)
    np.testing.assert_allclose(read_image(tmp_path / "a.tif"), ramp, atol=1 / 65535)
    np.testing.assert_allclose(read_image(tmp_path / "rgb.png"), ramp, atol=0.5 / 255 + 1e-6)


def test_dicom_geometry_tags(tmp_path: Path) -> None:
    stored = np.round(gradient() * 4000).astype(np.uint16)
    imager = write_dicom(tmp_path / "imager.dcm", stored, DistanceSourceToDetector=1040.0,
                         ImagerPixelSpacing=[0.148, 0.148], PixelSpacing=[0.1, 0.1])
    patient = write_dicom(tmp_path / "patient.dcm", stored, PixelSpacing=[0.125, 0.125],
                          EstimatedRadiographicMagnificationFactor=1.2)
    bare = write_dicom(tmp_path / "bare.dcm", stored)
    skewed = write_dicom(tmp_path / "skewed.dcm", stored, ImagerPixelSpacing=[0.1, 0.2])
    plain = write_dicom(tmp_path / "plain.dcm", stored, PixelSpacing=[0.125, 0.125])
    (f_imager,), (f_patient,), (f_bare,), (f_skewed,), (f_plain,) = (
        read_frames(p) for p in (imager, patient, bare, skewed, plain))
    assert f_imager.tag_sources == {"sdd_mm": "DICOM DistanceSourceToDetector",
                                    "pixel_spacing_mm": "DICOM ImagerPixelSpacing"}
    assert f_patient.tag_sources == {
        "pixel_spacing_mm": "DICOM PixelSpacing x EstimatedRadiographicMagnificationFactor"}
    # PixelSpacing alone: used as it is, and the source says so.
    assert f_plain.pixel_spacing_mm == pytest.approx(0.125)
    assert f_plain.tag_sources == {"pixel_spacing_mm": PATIENT_SPACING_SOURCE}
    assert f_imager.error is None
    assert f_imager.sdd_mm == pytest.approx(1040.0)
    assert f_imager.pixel_spacing_mm == pytest.approx(0.148)  # ImagerPixelSpacing wins
    assert f_patient.sdd_mm is None
    assert f_patient.pixel_spacing_mm == pytest.approx(0.125 * 1.2)
    assert f_bare.sdd_mm is None and f_bare.pixel_spacing_mm is None and not f_bare.tag_notes
    assert f_skewed.pixel_spacing_mm is None
    assert "not square" in f_skewed.tag_notes["pixel_spacing_mm"]
    # An unusable ImagerPixelSpacing leaves a usable PixelSpacing to take; both unusable,
    # both are named.
    (f_zero,) = read_frames(write_dicom(tmp_path / "zero.dcm", stored,
                                        ImagerPixelSpacing=[0, 0], PixelSpacing=[0.125, 0.125]))
    assert f_zero.pixel_spacing_mm == pytest.approx(0.125)
    assert f_zero.tag_sources == {"pixel_spacing_mm": PATIENT_SPACING_SOURCE}
    (f_both,) = read_frames(write_dicom(tmp_path / "both.dcm", stored,
                                        ImagerPixelSpacing=[0, 0], PixelSpacing=[0.1, 0.2]))
    assert f_both.pixel_spacing_mm is None
    assert f_both.tag_notes["pixel_spacing_mm"].startswith("DICOM ImagerPixelSpacing [0.0, 0.0] "
                                                           "unusable; DICOM PixelSpacing is not")
    # Stored values min-max scaled: the ramp comes back.
    np.testing.assert_allclose(f_bare.image, (stored - stored.min()) / np.ptp(stored), atol=1e-6)


def test_dicom_monochrome1_is_inverted(tmp_path: Path) -> None:
    stored = np.round(gradient() * 4000).astype(np.uint16)
    mono2 = read_image(write_dicom(tmp_path / "m2.dcm", stored, "MONOCHROME2"))
    mono1 = read_image(write_dicom(tmp_path / "m1.dcm", stored, "MONOCHROME1"))
    np.testing.assert_allclose(mono1, 1.0 - mono2, atol=1e-6)


@pytest.mark.parametrize("syntax", [JPEGLosslessSV1, JPEGLSLossless, JPEG2000Lossless],
                         ids=["jpeg-lossless", "jpeg-ls", "jpeg-2000"])
def test_compressed_dicom_gives_the_uncompressed_image_and_tags(tmp_path: Path,
                                                                 syntax: str) -> None:
    # 12-bit detector values, as C-arms store them, each frame re-encoded by GDCM.
    stored = np.round(np.random.default_rng(3).random((2, 60, 70)) * 4095).astype(np.uint16)
    plain = write_dicom(tmp_path / "plain.dcm", stored, DistanceSourceToDetector=1000.0,
                        ImagerPixelSpacing=[0.2, 0.2])
    packed = transcoded(plain, tmp_path / "packed.dcm", syntax)
    assert pydicom.dcmread(packed).file_meta.TransferSyntaxUID == syntax
    for ours, reference in zip(read_frames(packed), read_frames(plain), strict=True):
        assert ours.error is None, ours.error
        np.testing.assert_array_equal(ours.image, reference.image)
        assert (ours.sdd_mm, ours.pixel_spacing_mm) == (1000.0, 0.2)


def test_pydicoms_jpeg_ls_sample_matches_its_uncompressed_twin() -> None:
    # Encoded elsewhere (pydicom's test data), so not only GDCM's round trip.
    (ours,) = read_frames(Path(get_testdata_file("MR_small_jpeg_ls_lossless.dcm",
                                                 download=False)))
    (reference,) = read_frames(Path(get_testdata_file("MR_small.dcm", download=False)))
    assert ours.error is None, ours.error
    np.testing.assert_array_equal(ours.image, reference.image)


def test_twelve_bit_jpeg_extended_gives_pydicoms_reference_values() -> None:
    # pydicom's own sample, 12-bit JPEG Extended, which neither GDCM's plugin nor Pillow
    # reads; the values are those pydicom's reference tests assert (pylibjpeg's decode).
    path = Path(get_testdata_file("JPGExtended.dcm", download=False))
    (frame,) = read_frames(path)
    assert frame.error is None, frame.error
    assert frame.image.shape == (1024, 256)
    stored = pixel_array(path)  # after cupnet.io.images registered its decoder
    assert (stored[420, 140], stored[230, 120]) == (244, 95)


def test_twelve_bit_jpeg_extended_frames_decode_to_the_uncompressed_frames(
        tmp_path: Path) -> None:
    # 12-bit detector values in two distinct frames, each its own lossy 12-bit codestream.
    v, u = np.mgrid[0:60, 0:70]
    stored = np.stack([np.round(2000 + 1500 * np.sin(u / 9 + k) * np.cos(v / 7))
                       for k in range(2)]).astype(np.uint16)
    plain = write_dicom(tmp_path / "plain.dcm", stored, BitsStored=12, HighBit=11,
                        DistanceSourceToDetector=1000.0, ImagerPixelSpacing=[0.2, 0.2])
    streams = [imagecodecs.jpeg8_encode(frame, level=95, bitspersample=12) for frame in stored]
    assert all(stream[stream.index(b"\xff\xc1") + 4] == 12 for stream in streams)  # SOF1, 12 bits
    packed = with_jpeg_streams(plain, tmp_path / "packed.dcm", streams)
    references = [frame.image for frame in read_frames(plain)]
    for k, ours in enumerate(read_frames(packed)):
        assert ours.error is None, ours.error
        assert (ours.sdd_mm, ours.pixel_spacing_mm) == (1000.0, 0.2)
        # Lossy: within a few counts of 3,000 of its own frame, far from the other.
        assert np.abs(ours.image - references[k]).max() < 0.005
        assert np.abs(ours.image - references[1 - k]).max() > 0.1


def test_a_compression_no_decoder_reads_is_named_not_called_corrupt(tmp_path: Path) -> None:
    plain = write_dicom(tmp_path / "plain.dcm", np.ones((32, 32), np.uint16))
    damaged = with_jpeg_streams(plain, tmp_path / "damaged.dcm",
                                [b"\xff\xd8\xff\xc1" + bytes(range(200)) + b"\xff\xd9"])
    (frame,) = read_frames(damaged)
    assert frame.error.startswith("cannot decode DICOM pixel data compressed as JPEG Extended")
    assert "corrupt" not in frame.error
    assert "\n" not in frame.error  # a decoder's message over lines: its first one


def test_deflated_dicom_is_inflated(tmp_path: Path) -> None:
    """Deflated Explicit VR Little Endian: pydicom's pixel_array(path) reads no deflated
    file, which had been called corrupt."""
    pixels = (gradient() * 4000).astype(np.uint16)
    path = write_dicom(tmp_path / "plain.dcm", pixels)
    ds = pydicom.dcmread(path)
    ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
    ds.save_as(tmp_path / "deflated.dcm")
    written = pydicom.dcmread(tmp_path / "deflated.dcm", stop_before_pixels=True)
    assert written.file_meta.TransferSyntaxUID == DeflatedExplicitVRLittleEndian
    (frame,) = read_frames(tmp_path / "deflated.dcm")
    assert frame.error is None
    np.testing.assert_array_equal(frame.image, read_frames(path)[0].image)


def test_a_private_transfer_syntax_is_an_error_row_not_a_crash(tmp_path: Path) -> None:
    path = write_dicom(tmp_path / "private.dcm", np.ones((32, 32), np.uint16))
    ds = pydicom.dcmread(path)
    ds.file_meta.TransferSyntaxUID = "1.2.840.113619.5.2"  # a vendor's, no decoder knows it
    ds.save_as(path)
    (frame,) = read_frames(path)
    assert frame.error.startswith("cannot decode DICOM pixel data in transfer syntax "
                                  "1.2.840.113619.5.2")


def test_dicom_rescale_and_window_are_applied(tmp_path: Path) -> None:
    stored = np.round(gradient() * 4000).astype(np.uint16)
    plain = read_image(write_dicom(tmp_path / "plain.dcm", stored))
    # A negative rescale slope turns the image over: the modality LUT must have run.
    flipped = read_image(write_dicom(tmp_path / "flip.dcm", stored, RescaleSlope=-2.0,
                                     RescaleIntercept=100.0))
    np.testing.assert_allclose(flipped, 1.0 - plain, atol=1e-6)
    # A window over the middle of the range clips both ends (DICOM linear VOI function).
    windowed = read_image(write_dicom(tmp_path / "win.dcm", stored, WindowCenter=2000,
                                      WindowWidth=1000))
    assert np.all(windowed[stored <= 1500] == 0.0)
    assert np.all(windowed[stored >= 2500] == 1.0)
    inside = (stored > 1600) & (stored < 2400)
    expected = (stored[inside] - (2000 - 0.5)) / (1000 - 1) + 0.5
    np.testing.assert_allclose(windowed[inside], expected, atol=2e-3)


def test_multiframe_dicom_gives_one_frame_each(tmp_path: Path) -> None:
    """Each frame its own pixels: frames alike after their min-max stretch (a constant and
    a 0 each) had passed with the first frame read for all."""
    ramp = np.round(gradient(32, 40) * 4000).astype(np.uint16)
    frames = np.stack([ramp, ramp[::-1], ramp[:, ::-1]])
    path = write_dicom(tmp_path / "run.dcm", frames, DistanceSourceToDetector=1000.0)
    read = read_frames(path)
    assert [f.name for f in read] == ["run.dcm#1", "run.dcm#2", "run.dcm#3"]
    assert [f.last_of_source for f in read] == [False, False, True]
    assert all(f.error is None and f.sdd_mm == 1000.0 for f in read)
    for frame, stored in zip(read, frames, strict=True):
        np.testing.assert_allclose(frame.image, (stored - stored.min()) / np.ptp(stored),
                                   atol=1e-6)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.png", b"", "empty file"),
        ("text.png", b"this is not an image\n", "not a readable PNG"),
        ("notes.bmp", b"BM\x00\x00", "unsupported file type .bmp"),
        ("fake.dcm", b"not dicom at all" * 20, "not a DICOM file (no 'DICM' prefix"),
    ],
)
def test_broken_files_name_the_problem(tmp_path: Path, name: str, content: bytes,
                                       message: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    (frame,) = read_frames(path)
    assert frame.image is None and message in frame.error
    with pytest.raises(ImageReadError, match=re.escape(message)):
        read_image(path)


def test_truncated_png_jpeg_and_dicom(tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    # Noise: a cut through its long pixel data is what makes libpng print its error.
    noise = np.random.default_rng(0).integers(0, 65535, (256, 256), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "full.png"), noise)
    assert read_frames(tmp_path / "full.png")[0].error is None
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    assert "corrupt or truncated PNG" in read_frames(tmp_path / "cut.png")[0].error
    # Found before libpng reads the file, so its "libpng error: Read Error" never shows.
    assert "libpng" not in capfd.readouterr().err
    cv2.imwrite(str(tmp_path / "full.jpg"), np.round(gradient() * 255).astype(np.uint8))
    assert read_frames(tmp_path / "full.jpg")[0].error is None
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) * 2 // 3])
    assert "truncated JPEG" in read_frames(tmp_path / "cut.jpg")[0].error
    write_dicom(tmp_path / "full.dcm", np.ones((64, 64), np.uint16))
    data = (tmp_path / "full.dcm").read_bytes()
    (tmp_path / "cut.dcm").write_bytes(data[: len(data) - 4000])
    assert "corrupt or truncated DICOM" in read_frames(tmp_path / "cut.dcm")[0].error
    (tmp_path / "head.dcm").write_bytes(data[:300])  # cut within the header: pydicom reads on
    assert "cut short in its header" in read_frames(tmp_path / "head.dcm")[0].error
    # Rows and Columns but no pixel data element: no image, not a corrupt one.
    dataset = pydicom.dcmread(tmp_path / "full.dcm")
    del dataset.PixelData
    dataset.save_as(tmp_path / "bare.dcm")
    assert read_frames(tmp_path / "bare.dcm")[0].error == (
        "DICOM has no image (no Pixel Data element: a dataset without pixel data)")


def test_a_float_tiff_with_nan_is_named_as_such_not_as_corrupt(tmp_path: Path) -> None:
    image = gradient().astype(np.float32)
    image[3, 4] = np.nan
    cv2.imwrite(str(tmp_path / "nan.tiff"), image)
    with pytest.raises(ImageReadError) as caught:
        read_image(tmp_path / "nan.tiff")
    assert str(caught.value) == f"{tmp_path / 'nan.tiff'}: image contains NaN or infinite values"


def test_size_limit(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "wide.png"), np.zeros((8, MAX_SIDE + 1), np.uint16))
    assert "too large" in read_frames(tmp_path / "wide.png")[0].error
    cv2.imwrite(str(tmp_path / "max.png"), np.zeros((MAX_SIDE, MAX_SIDE), np.uint16))
    assert read_image(tmp_path / "max.png").shape == (MAX_SIDE, MAX_SIDE)


def png_header_only(path: Path, width: int, height: int) -> Path:
    """A PNG whose header gives ``width`` x ``height`` 8-bit gray pixels and whose data is a
    few bytes: what a decompression bomb looks like before decoding."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
                     + chunk(b"IDAT", zlib.compress(bytes(100))) + chunk(b"IEND", b""))
    return path


def test_a_header_past_pils_bomb_limit_is_an_error_row_not_a_crash(tmp_path: Path) -> None:
    # 30,000 x 30,000 px: Pillow refuses to open it with its own error type.
    bomb = png_header_only(tmp_path / "bomb.png", 30_000, 30_000)
    cv2.imwrite(str(tmp_path / "fine.png"), np.zeros((16, 16), np.uint8))
    sources = [ImageSource(bomb, "bomb.png"), ImageSource(tmp_path / "fine.png", "fine.png")]
    bad, good = iter_frames(sources, workers=0)
    assert bad.error.startswith("image too large: its header gives over")
    assert good.error is None


@pytest.mark.parametrize("stage", ["_probe", "_read_raster"])
def test_a_readers_unforeseen_failure_ends_that_file_alone(tmp_path: Path, stage: str,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    import cupnet.io.images as images

    real = getattr(images, stage)

    def failing(source: ImageSource | Path, *args: object) -> object:
        if source.name == "bad.png":  # the probe takes a source, the decoder a path
            raise AttributeError("a decoder's own bug")
        return real(source, *args)

    monkeypatch.setattr(images, stage, failing)
    sources = []
    for name in ("a.png", "bad.png", "c.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((16, 16), np.uint8))
        sources.append(ImageSource(tmp_path / name, name))
    frames = list(iter_frames(sources, workers=2))
    assert [f.name for f in frames] == ["a.png", "bad.png", "c.png"]
    assert frames[1].error == "unreadable file (AttributeError: a decoder's own bug)"
    assert frames[0].error is None and frames[2].error is None


@pytest.mark.parametrize(("degrees", "shape", "moved"),
                         [(0, (3, 5), (4, 1)), (90, (5, 3), (1, 4)), (180, (3, 5), (0, 1)),
                          (270, (5, 3), (1, 0))])
def test_turning_clockwise_moves_a_pixel_position_with_the_image(
        degrees: int, shape: tuple[int, int], moved: tuple[int, int]) -> None:
    # A 5 x 3 image marked at (u, v) = (4, 1), the right end of its middle row. A quarter
    # clockwise takes rows to columns, the top row to the right column: the middle row
    # becomes the middle column, its right end the bottom (hand-derived, each turn).
    image = np.zeros((3, 5))
    image[1, 4] = 1.0
    turned, u, v = turned_clockwise(image, 4.0, 1.0, degrees)
    assert turned.shape == shape and (u, v) == moved
    assert turned[int(v), int(u)] == 1.0


def test_turning_by_another_angle_is_refused() -> None:
    with pytest.raises(ValueError, match="0, 90, 180 or 270"):
        turned_clockwise(np.zeros((3, 5)), 0.0, 0.0, 45)


def test_discovery_folder_recursive_glob_and_empty(tmp_path: Path) -> None:
    image = np.zeros((8, 8), np.uint8)
    (tmp_path / "sub").mkdir()
    (tmp_path / "out").mkdir()
    for rel in ("b.png", "a.jpg", "sub/c.tif", "out/overlay.png"):
        cv2.imwrite(str(tmp_path / rel), image)
    write_dicom(tmp_path / "sub" / "IM0001", np.zeros((8, 8), np.uint16))  # no suffix
    # DICOM by its content, whatever its suffix: a UID name's last part, Siemens' .IMA.
    write_dicom(tmp_path / "sub" / "1.2.840.113619.2.55.3.1234", np.zeros((8, 8), np.uint16))
    write_dicom(tmp_path / "sub" / "IM-0001-0001.IMA", np.zeros((8, 8), np.uint16))
    (tmp_path / "readme.txt").write_text("not an image")
    (tmp_path / "moved.png").symlink_to(tmp_path / "gone.png")  # a broken link: a row
    (tmp_path / "folder.png").mkdir()  # a folder named as an image: not one
    names = [s.name for s in find_images(tmp_path, exclude=tmp_path / "out")]
    assert names == ["a.jpg", "b.png", "moved.png"]
    (moved,) = read_frames(tmp_path / "moved.png")
    assert moved.error.startswith("cannot open file (No such file")
    names = [s.name for s in find_images(tmp_path, recursive=True, exclude=tmp_path / "out")]
    assert names == ["a.jpg", "b.png", "moved.png", "sub/1.2.840.113619.2.55.3.1234",
                     "sub/IM-0001-0001.IMA", "sub/IM0001", "sub/c.tif"]
    assert read_frames(tmp_path / "sub" / "IM-0001-0001.IMA")[0].error is None
    assert [s.name for s in find_images(f"{tmp_path}/*.png")] == ["b.png", "moved.png"]
    assert [s.name for s in find_images(f"{tmp_path}/**/*.tif", recursive=True)] == ["sub/c.tif"]
    assert [s.name for s in find_images(tmp_path / "b.png")] == ["b.png"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no images found in"):
        find_images(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="no such file"):
        find_images(tmp_path / "missing")


def test_stream_keeps_order_and_goes_past_bad_files(tmp_path: Path) -> None:
    sources = []
    for i in range(12):
        path = tmp_path / f"{i:02d}.png"
        if i % 5 == 3:
            path.write_text("broken")
        else:
            cv2.imwrite(str(path), np.full((16, 16), i * 10, np.uint8))
        sources.append(ImageSource(path, path.name))
    frames = list(iter_frames(sources, workers=2, lookahead=3))
    assert [f.name for f in frames] == [s.name for s in sources]
    for i, frame in enumerate(frames):
        if i % 5 == 3:
            assert frame.error is not None and frame.image is None
        else:
            assert frame.error is None and frame.image[0, 0] == pytest.approx(i * 10 / 255)


def test_stream_reads_a_bounded_number_of_frames_ahead(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import cupnet.io.images as images

    cv2.imwrite(str(tmp_path / "one.png"), np.zeros((16, 16), np.uint8))
    sources = [ImageSource(tmp_path / "one.png", f"copy{i}.png") for i in range(100)]
    decoded = []
    real = images._decode
    monkeypatch.setattr(images, "_decode", lambda unit: decoded.append(unit) or real(unit))
    stream = iter_frames(sources, workers=2, lookahead=4)
    first = next(stream)
    assert first.name == "copy0.png"
    assert len(decoded) <= 5  # the frame handed out and at most 4 waiting
    stream.close()


def test_a_raster_is_read_as_what_it_holds_not_as_its_suffix(tmp_path: Path) -> None:
    """A JPEG named .png and a PNG named .jpg are intact, and so is a JPEG with a long
    trailer after its end (a phone's motion photo) or an EXIF thumbnail, whose own end
    marker does not end a cut-off image."""
    ramp = np.round(gradient() * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.jpg"), ramp, [cv2.IMWRITE_JPEG_QUALITY, 100])
    cv2.imwrite(str(tmp_path / "a.png"), ramp)
    jpeg = (tmp_path / "a.jpg").read_bytes()
    (tmp_path / "jpeg.png").write_bytes(jpeg)
    (tmp_path / "png.jpg").write_bytes((tmp_path / "a.png").read_bytes())
    (tmp_path / "trailer.jpg").write_bytes(jpeg + bytes(range(256)) * 16)
    for name in ("jpeg.png", "png.jpg", "trailer.jpg"):
        (frame,) = read_frames(tmp_path / name)
        assert frame.error is None, name
        np.testing.assert_allclose(frame.image, ramp / 255, atol=3 / 255)
    # An APP1 segment holding a whole JPEG (its end marker inside), then the image cut off.
    app1 = b"Exif\x00\x00" + jpeg
    with_thumbnail = jpeg[:2] + b"\xff\xe1" + (len(app1) + 2).to_bytes(2, "big") + app1 + jpeg[2:]
    (tmp_path / "thumb.jpg").write_bytes(with_thumbnail)
    assert read_frames(tmp_path / "thumb.jpg")[0].error is None
    (tmp_path / "thumb_cut.jpg").write_bytes(with_thumbnail[: len(with_thumbnail) - 200]
                                             + bytes(2048))
    assert "truncated JPEG" in read_frames(tmp_path / "thumb_cut.jpg")[0].error


def test_a_name_no_utf8_holds_is_read_and_named_with_escapes(tmp_path: Path) -> None:
    """A latin-1 file name (an old share's) is kept by Python as lone surrogates, which
    OpenCV could not open and no UTF-8 writer could write."""
    ramp = np.round(gradient() * 255).astype(np.uint8)
    ok, data = cv2.imencode(".png", ramp)
    path = Path(os.fsdecode(bytes(tmp_path) + b"/caf\xe9.png"))
    path.write_bytes(data.tobytes())
    (source,) = find_images(tmp_path)
    assert source.name == "caf\\xe9.png"
    (frame,) = iter_frames([source], workers=0)
    assert frame.error is None and frame.name == "caf\\xe9.png"
    np.testing.assert_allclose(frame.image, ramp / 255, atol=0.5 / 255 + 1e-6)


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_exif_orientation_turns_the_pixels_as_viewers_show_them(tmp_path: Path,
                                                                suffix: str) -> None:
    """Each of EXIF's eight orientations against Pillow's own exif_transpose (a phone's JPEG
    turned 90 deg had given a pose 90 deg off)."""
    stored = np.round(gradient(40, 56) * 255).astype(np.uint8)
    stored[5:9, 30:33] = 255  # asymmetric, so every turn and flip shows
    for orientation in range(1, 9):
        path = tmp_path / f"o{orientation}{suffix}"
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(stored).save(path, exif=exif, **({"quality": 100} if suffix == ".jpg"
                                                        else {}))
        with Image.open(path) as im:
            shown = np.asarray(ImageOps.exif_transpose(im)) / 255
        image = read_image(path)
        assert image.shape == shown.shape
        np.testing.assert_allclose(image, shown, atol=0.5 / 255 + 1e-6)


def test_a_bare_dicom_dataset_without_preamble_or_file_meta_is_read(tmp_path: Path) -> None:
    """Old exports store the dataset alone; pydicom reads it only by force, and it had been
    refused as 'not a DICOM file'. Its pixels and tags are those of the same dataset stored
    whole."""
    pixels = (gradient() * 4000).astype(np.uint16)
    whole = write_dicom(tmp_path / "whole.dcm", pixels, DistanceSourceToDetector=1100.0,
                        ImagerPixelSpacing=[0.2, 0.2])
    for implicit in (True, False):
        ds = pydicom.dcmread(whole)
        del ds.file_meta
        buffer = DicomBytesIO()
        buffer.is_little_endian, buffer.is_implicit_VR = True, implicit
        write_dataset(buffer, ds)
        bare = tmp_path / f"bare_{implicit}.dcm"
        bare.write_bytes(buffer.getvalue())
        with pytest.raises(pydicom.errors.InvalidDicomError):
            pydicom.dcmread(bare)
        (frame,) = read_frames(bare)
        assert frame.error is None
        np.testing.assert_array_equal(frame.image, read_frames(whole)[0].image)
        assert (frame.sdd_mm, frame.pixel_spacing_mm) == (1100.0, 0.2)
    (tmp_path / "text.dcm").write_bytes(b"\x08\x00" + b"no dataset at all" * 40)
    assert "not a DICOM file" in read_frames(tmp_path / "text.dcm")[0].error


def test_coloured_annotations_are_inpainted_and_a_tinted_image_is_averaged(tmp_path: Path
                                                                          ) -> None:
    """A green ellipse and red text drawn on a grey screenshot had become grey edges (one
    such ellipse on a cup gave a pose 32 deg off, unflagged): they are inpainted from their
    surround, and the rest of the image is the channels' mean, untouched."""
    ramp = np.round(gradient(120, 160) * 200 + 20).astype(np.uint8)
    grey = np.repeat(ramp[..., None], 3, -1)
    annotated = grey.copy()
    cv2.ellipse(annotated, (80, 60), (40, 25), 20, 0, 360, (0, 255, 0), 2)  # BGR: green
    cv2.putText(annotated, "L", (10, 110), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 255), 2)
    cv2.imwrite(str(tmp_path / "annotated.png"), annotated)
    # Colour images are min-max scaled: back to the ramp's own range.
    image = read_image(tmp_path / "annotated.png") * (ramp.max() - ramp.min()) + ramp.min()
    drawn = np.abs(annotated.astype(int) - grey).max(-1) > 0
    averaged = annotated.mean(-1)
    assert np.abs(averaged - ramp)[drawn].mean() > 20  # what plain averaging left
    assert np.abs(image - ramp)[drawn].mean() < 3  # the ramp again, from its surround
    far = ~cv2.dilate(drawn.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    np.testing.assert_allclose(image[far], ramp[far], atol=1e-3)
    # A tint over the whole image is no annotation: the channels' mean, as before.
    tinted = grey.astype(int) + np.array([0, 30, 60])
    cv2.imwrite(str(tmp_path / "tinted.png"), np.clip(tinted, 0, 255).astype(np.uint8))
    mean = np.clip(tinted, 0, 255).mean(-1)
    expected = (mean - mean.min()) / (mean.max() - mean.min())
    np.testing.assert_allclose(read_image(tmp_path / "tinted.png"), expected, atol=1e-5)


def test_dicom_padding_is_left_out_of_the_stretch_and_shown_black(tmp_path: Path) -> None:
    """A CR's 12-bit picture in a border of padding at 65535: read as the picture alone
    would be, the border 0 (it had squeezed the picture into [0, 0.06])."""
    picture = np.round(gradient() * 4000).astype(np.uint16) + 50
    alone = read_image(write_dicom(tmp_path / "alone.dcm", picture))
    padded = np.full((picture.shape[0] + 20, picture.shape[1] + 20), 65535, np.uint16)
    padded[10:-10, 10:-10] = picture
    for photometric, expected in (("MONOCHROME2", alone), ("MONOCHROME1", 1 - alone)):
        image = read_image(write_dicom(tmp_path / f"{photometric}.dcm", padded, photometric,
                                       PixelPaddingValue=65535))
        np.testing.assert_allclose(image[10:-10, 10:-10], expected, atol=1e-6)
        assert image[:10].max() == image[:, -10:].max() == 0
    # A range of padding values (PixelPaddingRangeLimit), here a dark border of 0-9.
    padded[:10], padded[-10:] = 0, 9
    padded[:, :10] = padded[:, -10:] = 5
    image = read_image(write_dicom(tmp_path / "range.dcm", padded, PixelPaddingValue=9,
                                   PixelPaddingRangeLimit=0))
    np.testing.assert_allclose(image[10:-10, 10:-10], alone, atol=1e-6)


def test_a_tiffs_palette_is_read_as_the_greys_it_shows(tmp_path: Path) -> None:
    greys = np.round(gradient() * 255).astype(np.uint8)
    order = np.random.default_rng(1).permutation(256)  # index i shows grey order[i]
    indices = np.argsort(order)[greys].astype(np.uint8)
    page = Image.fromarray(indices, "P")
    page.putpalette(np.repeat(order[:, None], 3, 1).astype(np.uint8).ravel().tolist())
    page.save(tmp_path / "palette.tif")
    np.testing.assert_allclose(read_image(tmp_path / "palette.tif"), greys / 255, atol=1e-6)


def test_a_16_bit_raster_of_fewer_bits_fills_its_range(tmp_path: Path) -> None:
    """10-bit data in a 16-bit PNG reads as a 10-bit image would (it had reached 0.016)."""
    ramp = np.round(gradient() * 1023).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "ten.png"), ramp)
    np.testing.assert_allclose(read_image(tmp_path / "ten.png"), ramp / 1023, atol=1e-6)
    dark = (ramp // 8).astype(np.uint16)  # under 8 bits: as an 8-bit image, not stretched
    cv2.imwrite(str(tmp_path / "dark.png"), dark)
    np.testing.assert_allclose(read_image(tmp_path / "dark.png"), dark / 255, atol=1e-6)


def test_a_tiff_page_past_the_size_limit_is_that_pages_error(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch
                                                            ) -> None:
    monkeypatch.setattr("cupnet.io.images.MAX_SIDE", 64)
    pages = [Image.fromarray(np.zeros((32, 32), np.uint8)),
             Image.fromarray(np.zeros((100, 100), np.uint8))]
    pages[0].save(tmp_path / "pages.tif", save_all=True, append_images=pages[1:])
    first, second = read_frames(tmp_path / "pages.tif")
    assert first.error is None and "too large: 100 x 100 px" in second.error


@pytest.mark.parametrize(("frames", "message"), [
    (-1, "invalid DICOM NumberOfFrames -1"),
    (3000, "DICOM NumberOfFrames 3000 of 40 x 32 px needs 7,680,000 bytes of pixel data"),
])
def test_a_dicom_frame_count_the_file_cannot_hold_is_one_error(tmp_path: Path, frames: int,
                                                               message: str) -> None:
    path = write_dicom(tmp_path / "claims.dcm", np.ones((32, 40), np.uint16))
    ds = pydicom.dcmread(path)
    ds.NumberOfFrames = frames
    ds.save_as(path)
    (frame,) = read_frames(path)  # one row: not none, and not one a claimed frame
    assert frame.image is None and message in frame.error


def test_a_file_is_read_as_what_it_holds_between_dicom_and_raster(tmp_path: Path) -> None:
    """A DICOM named .png (a PACS export) and a PNG named .dcm are read as what they hold."""
    stored = np.round(gradient() * 4000).astype(np.uint16)
    write_dicom(tmp_path / "export.png", stored, DistanceSourceToDetector=1000.0)
    (frame,) = read_frames(tmp_path / "export.png")
    assert frame.error is None and frame.sdd_mm == 1000.0
    np.testing.assert_allclose(frame.image, (stored - stored.min()) / np.ptp(stored), atol=1e-6)
    cv2.imwrite(str(tmp_path / "picture.png"), np.round(gradient() * 255).astype(np.uint8))
    (tmp_path / "picture.png").rename(tmp_path / "picture.dcm")
    (frame,) = read_frames(tmp_path / "picture.dcm")
    assert frame.error is None
    np.testing.assert_allclose(frame.image, gradient(), atol=0.5 / 255 + 1e-6)
    assert [s.name for s in find_images(tmp_path)] == ["export.png", "picture.dcm"]
