"""SynthDataset / synthesize: shapes, determinism across workers, truth that matches the image."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from cupnet.ellipse import params_to_conic, sampson_distance
from cupnet.geometry import Geometry
from data_synth import MAX_CUPS, SynthConfig, SynthDataset, synthesize
from data_synth.dataset import rim_truth
from data_synth.scene import reflect_into, sample_geometry, sample_poses

SMALL = {"image_size": (64, 48)}


def test_sample_shapes_and_dtypes():
    sample = synthesize(SynthConfig(**SMALL), 0, 0)
    expected = {
        "image": ((1, 48, 64), torch.float32), "mask": ((1, 48, 64), torch.float32),
        "geometry": ((4,), torch.float64), "pose": ((MAX_CUPS, 5), torch.float64),
        "ellipse": ((MAX_CUPS, 5), torch.float64), "rim": ((MAX_CUPS, 64, 2), torch.float64),
        "cup_diameter": ((MAX_CUPS,), torch.float64), "cup_valid": ((MAX_CUPS,), torch.bool),
        "index": ((), torch.int64),
    }
    assert set(sample) == set(expected)
    for key, (shape, dtype) in expected.items():
        assert sample[key].shape == shape and sample[key].dtype == dtype, key
    assert 0 <= sample["image"].min() and sample["image"].max() <= 1
    assert 0 <= sample["mask"].min() and sample["mask"].max() <= 1


def test_same_seed_and_index_give_the_same_sample():
    config = SynthConfig(**SMALL)
    a, b, c = synthesize(config, 7, 3), synthesize(config, 7, 3), synthesize(config, 7, 4)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert not torch.equal(a["image"], c["image"])


def test_stream_is_the_same_for_any_number_of_workers():
    dataset = SynthDataset(SynthConfig(**SMALL), seed=11, length=6)

    def by_index(workers):
        samples = {}
        for batch in DataLoader(dataset, batch_size=2, num_workers=workers):
            for i, index in enumerate(batch["index"].tolist()):
                samples[index] = {key: value[i] for key, value in batch.items()}
        return samples

    single, multi = by_index(0), by_index(2)
    assert sorted(single) == sorted(multi) == list(range(6))
    for index, sample in single.items():
        for key in sample:
            assert torch.equal(sample[key], multi[index][key]), (index, key)
    assert torch.equal(single[2]["image"], dataset[2]["image"])


def test_ddp_processes_make_disjoint_shares(monkeypatch: pytest.MonkeyPatch):
    """Under DDP each process reads its own share of the stream (Lightning does not split
    an iterable dataset), so two GPUs do not train on the same images."""
    dataset = SynthDataset(SynthConfig(**SMALL), seed=11, length=7)
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.distributed, "get_world_size", lambda: 2)
    shares = []
    for rank in (0, 1):
        monkeypatch.setattr(torch.distributed, "get_rank", lambda rank=rank: rank)
        shares.append([int(s["index"]) for s in dataset])
    assert shares == [[0, 2, 4, 6], [1, 3, 5]]
    assert torch.equal(next(iter(dataset))["image"], dataset[1]["image"])  # rank 1's first


def test_truth_of_a_cup_facing_the_detector_is_its_magnified_circle():
    """theta = 90 deg puts the rim parallel to the detector: its image is a circle of the
    radius magnified by SDD / (SDD - h), in pixels of the spacing, centred on (k, l) so
    magnified from the principal point (hand-derived, CONVENTIONS' frames)."""
    sdd, spacing, u0, v0 = 1040.0, 0.5, 100.0, 80.0
    pose = torch.tensor([[90.0, 0.0, 12.0, -7.0, 300.0]], dtype=torch.float64)
    _, ellipse, rim = rim_truth(pose, torch.tensor([50.0], dtype=torch.float64),
                                Geometry(sdd, spacing, u0, v0))
    magnified = sdd / (sdd - 300.0) / spacing  # px per mm in the rim's plane
    cx, cy, a, b, _ = ellipse[0].tolist()
    assert (cx, cy) == pytest.approx((u0 + 12.0 * magnified, v0 - 7.0 * magnified), abs=1e-9)
    assert (a, b) == pytest.approx((25.0 * magnified, 25.0 * magnified), abs=1e-9)
    centre = torch.tensor([cx, cy], dtype=torch.float64)
    torch.testing.assert_close((rim[0] - centre).norm(dim=-1),
                               torch.full((rim.shape[1],), 25.0 * magnified,
                                          dtype=torch.float64))


@pytest.mark.parametrize("seed", range(8))
def test_truth_is_consistent_with_itself_and_the_image(seed):
    # No anatomy and no round field: the implant is the only thing on a flat background.
    config = SynthConfig(image_size=(96, 80), p_invert=0.0, p_no_cup=0.0, p_bilateral=0.0,
                         p_anatomy=0.0, p_bones=0.0, smooth_background=(0.0, 0.0),
                         p_circular_field=0.0)
    sample = synthesize(config, seed, 0)
    assert sample["cup_valid"].tolist() == [True, False]
    ellipse, rim = sample["ellipse"][0], sample["rim"][0]
    # Rim landmarks lie on the truth ellipse, and inside the image.
    distance = sampson_distance(params_to_conic(ellipse[None]), rim[None])
    assert distance.abs().max() < 1e-6
    assert (rim[:, 0] >= 0).all() and (rim[:, 0] <= 95).all()
    assert (rim[:, 1] >= 0).all() and (rim[:, 1] <= 79).all()
    # The mask is the filled ellipse: its area and centroid.
    mask = sample["mask"][0].double()
    cx, cy, a, b, _ = ellipse.tolist()
    assert abs(mask.sum() - math.pi * a * b) < 0.02 * math.pi * a * b + 0.05 * (a + b) + 0.5
    v, u = torch.meshgrid(torch.arange(80.0), torch.arange(96.0), indexing="ij")
    centroid = torch.stack([(mask * u.double()).sum(), (mask * v.double()).sum()]) / mask.sum()
    # A rim seen edge-on is thinner than a pixel: its mask cannot place it within a pixel.
    atol = 0.1 if b >= 2 else 0.5
    assert torch.allclose(centroid, torch.tensor([cx, cy], dtype=torch.float64), atol=atol)
    # Behind the opening lies the metal dome: darker than the field on average.
    image = sample["image"][0]
    assert image[mask > 0.5].mean() < image[mask == 0].mean()


def test_no_cup_images():
    sample = synthesize(SynthConfig(**SMALL, p_no_cup=1.0), 3, 0)
    assert not sample["cup_valid"].any()
    assert sample["mask"].sum() == 0 and sample["pose"].abs().sum() == 0
    # The diameter a user would give stays, so a detector can run on the image.
    assert (sample["cup_diameter"] >= 44).all()


def test_bilateral_cups_sit_on_opposite_hips():
    config = SynthConfig(image_size=(128, 128), p_bilateral=1.0, p_no_cup=0.0,
                         detector_width_mm=(420.0, 420.0), h_mm=(100.0, 200.0))
    pairs = [s for s in (synthesize(config, 5, i) for i in range(8)) if s["cup_valid"].all()]
    assert pairs, "a wide field should fit both hips"
    for sample in pairs:
        (phi0, k0), (phi1, k1) = sample["pose"][:, [1, 2]].tolist()
        assert abs(phi0 + phi1) < 30  # mirrored inclination (with jitter)
        # A right hip (phi > 0, on the image's left) has its partner to its right.
        assert (k1 > k0) == (phi0 > 0)
        assert sample["cup_diameter"][0] == sample["cup_diameter"][1]
        assert sample["mask"].sum() > 0


def test_reflect_into_folds_at_both_ends():
    """Hand cases: inside unchanged, beyond an end back by as much, twice the span around."""
    values = np.array([25.0, 0.0, 50.0, -3.0, 53.0, 104.0, -0.5])
    assert np.allclose(reflect_into(values, (0.0, 50.0)), [25.0, 0.0, 50.0, 3.0, 47.0, 4.0, 0.5])
    assert np.allclose(reflect_into(7.0, (2.0, 2.0)), 2.0)


def test_bilateral_second_cups_pile_on_no_range_end():
    """Second cups near the ends of narrow anteversion and h ranges (the first cup's plus
    noise) stay in range and none sits on an end, as a clipped draw would."""
    config = SynthConfig(image_size=(128, 128), p_bilateral=1.0, p_no_cup=0.0,
                         detector_width_mm=(420.0, 420.0), theta_deg=(0.0, 4.0),
                         h_mm=(100.0, 110.0))
    rng = np.random.default_rng(3)
    seconds = []
    for _ in range(40):
        geometry = sample_geometry(config, rng)
        poses, _ = sample_poses(config, rng, geometry, field_radius=1e6, bilateral=True)
        if len(poses) == 2:
            seconds.append(poses[1].numpy())
    seconds = np.array(seconds)
    assert len(seconds) >= 20
    theta, h = seconds[:, 0], seconds[:, 4]
    assert ((theta >= 0.0) & (theta <= 4.0) & (h >= 100.0) & (h <= 110.0)).all()
    assert not np.isin(theta, [0.0, 4.0]).any() and not np.isin(h, [100.0, 110.0]).any()


def test_seed_errors_and_generator_input():
    config = SynthConfig(**SMALL)
    with pytest.raises(ValueError, match="seed"):
        synthesize(config, -1, 0)
    with pytest.raises(ValueError, match="seed"):
        SynthDataset(config, seed=-3)
    a = synthesize(config, np.random.default_rng([2, 5]))
    b = synthesize(config, 2, 5)
    assert torch.equal(a["image"], b["image"]) and torch.equal(a["pose"], b["pose"])
    # numpy's integers are integers (np.int64(2) had been refused, naming itself as the
    # problem); a bool is none (True had run as seed 1).
    assert torch.equal(synthesize(config, np.int64(2), np.int32(5))["image"], b["image"])
    assert SynthDataset(config, seed=np.int64(3), length=np.int64(1)).seed == 3
    with pytest.raises(ValueError, match="seed"):
        synthesize(config, True, 0)
