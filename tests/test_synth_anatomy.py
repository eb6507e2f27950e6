"""Anatomy bank: the shipped bank, and a bank rendered once from a user's CT and cached."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
import torch

import data_synth.anatomy as anatomy
from data_synth import SynthConfig, synthesize


def test_shipped_bank_is_small_and_plausible():
    assert anatomy.SHIPPED_BANK.stat().st_size < 20e6
    maps = anatomy.load_bank(str(anatomy.SHIPPED_BANK))
    assert maps.ndim == 4 and maps.shape[1] == 1 and len(maps) >= 16
    # Water-equivalent attenuation of a trunk: a few units, never negative.
    assert maps.min() >= 0 and 1 < float(maps.mean()) < 8


def write_ct(folder, kind):
    """A 24 x 24 x 20 CT (8 mm voxels): a soft-tissue box around a bone column."""
    volume = np.full((24, 24, 20), -1000, dtype=np.int16)
    volume[4:20, 4:20, 2:18] = 40
    volume[10:14, 10:14, 2:18] = 900
    if kind == "nifti":
        path = folder / "ct.nii.gz"
        nib.save(nib.Nifti1Image(volume, np.diag([8.0, 8.0, 8.0, 1.0])), path)
        return path
    import SimpleITK as sitk

    path = folder / "ct_dicom"
    path.mkdir()
    image = sitk.GetImageFromArray(np.ascontiguousarray(volume.transpose(2, 1, 0)))
    image.SetSpacing((8.0, 8.0, 8.0))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(image.GetDepth()):
        piece = image[:, :, k]
        position = image.TransformIndexToPhysicalPoint((0, 0, k))
        for tag, value in (("0020|0032", "\\".join(map(str, position))), ("0020|0013", str(k)),
                           ("0008|0060", "CT"), ("0020|0037", "1\\0\\0\\0\\1\\0"),
                           ("0020|000d", "1.2.826.0.1.3680043.2.1125.2"),
                           ("0020|000e", "1.2.826.0.1.3680043.2.1125.1")):
            piece.SetMetaData(tag, value)
        writer.SetFileName(str(path / f"{k:03d}.dcm"))
        writer.Execute(piece)
    return path


@pytest.mark.parametrize("kind", ["nifti", "dicom"])
def test_user_ct_is_rendered_once_and_cached(tmp_path, monkeypatch, kind):
    import data_synth.build_bank as build_bank

    monkeypatch.setattr(anatomy, "CACHE_DIR", tmp_path / "cache")
    # A small bank of a coarse CT keeps the test to a second or two.
    monkeypatch.setattr(anatomy, "USER_BANK_VIEWS", 3)
    monkeypatch.setattr(anatomy, "USER_BANK_SIZE", 48)
    monkeypatch.setattr(build_bank, "VOXEL_MM", (8.0, 8.0, 8.0))
    ct = write_ct(tmp_path, kind)
    config = SynthConfig(image_size=(64, 64), anatomy_ct=str(ct), p_anatomy=1.0)
    first = synthesize(config, 0, 0)
    cached = list((tmp_path / "cache").glob("*.npz"))
    assert len(cached) == 1 and cached[0].name.startswith(ct.name)
    mtime = cached[0].stat().st_mtime_ns
    second = synthesize(config, 0, 0)
    assert cached[0].stat().st_mtime_ns == mtime  # reused, not rendered again
    assert torch.equal(first["image"], second["image"])
    maps = anatomy.load_bank(str(cached[0]))
    assert maps.max() > 0  # the CT's body shows in its renders


def test_banks_saved_at_once_by_several_writers_all_land_whole(tmp_path):
    """Data-loader workers or DDP ranks that all miss the cache save one bank at once: with
    one shared temporary name, a writer's rename took the file from under another's
    (FileNotFoundError) or left a torn one."""
    from concurrent.futures import ThreadPoolExecutor

    from data_synth.build_bank import save_bank

    path = tmp_path / "bank.npz"
    banks = [{"maps": np.random.default_rng(i).standard_normal((8, 256, 256))
              .astype(np.float32)} for i in range(4)]
    with ThreadPoolExecutor(4) as pool:  # zlib releases the GIL: the writes overlap
        list(pool.map(lambda bank: save_bank(bank, path), banks))
    with np.load(path) as saved:
        assert any(np.array_equal(saved["maps"], bank["maps"]) for bank in banks)
    assert [p.name for p in tmp_path.iterdir()] == ["bank.npz"]  # no temporary file left
