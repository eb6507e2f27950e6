"""SynthDataset / synthesize: shapes, determinism across workers, truth that matches the image."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from cupnet.ellipse import params_to_conic, sampson_distance
from cupnet.geometry import Geometry
from data_synth import MAX_CUPS, SynthConfig, SynthDataset, synthesize
from data_synth.dataset import render_bones, rim_truth
from data_synth.implant import Ellipsoid
from data_synth.raycast import render_parts
from data_synth.scene import reflect_into, sample_geometry, sample_poses, sample_scene

SMALL = {"image_size": (64, 48)}
# The implant alone (no anatomy, bones, stem or screw holes) on a flat, noise-free, unblurred
# background without scatter, vignetting, round field or inversion: nothing but the cup moves
# the image's centroid.
PLAIN = {"p_no_cup": 0.0, "p_bilateral": 0.0, "p_stem": 0.0, "p_screw_holes": 0.0,
         "p_anatomy": 0.0, "p_bones": 0.0, "smooth_background": (0.0, 0.0),
         "photons": (1e12, 1e12), "electronic_noise": (0.0, 0.0), "blur_sigma_px": (0.0, 0.0),
         "scatter_fraction": (0.0, 0.0), "vignetting": (0.0, 0.0), "p_invert": 0.0,
         "p_circular_field": 0.0, "p_8bit": 0.0}


def centroid(weights: torch.Tensor) -> torch.Tensor:
    """``(u, v)`` px, float64, of non-negative ``weights (H, W)`` (pixel centres at integers)."""
    weights = weights.double()
    v, u = torch.meshgrid(torch.arange(weights.shape[0], dtype=torch.float64),
                          torch.arange(weights.shape[1], dtype=torch.float64), indexing="ij")
    return torch.stack([(weights * u).sum(), (weights * v).sum()]) / weights.sum()


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
    # A rim seen edge-on is thinner than a pixel: its mask cannot place it within a pixel.
    atol = 0.1 if b >= 2 else 0.5
    assert torch.allclose(centroid(mask), torch.tensor([cx, cy], dtype=torch.float64), atol=atol)
    # Behind the opening lies the metal dome: darker than the field on average.
    image = sample["image"][0]
    assert image[mask > 0.5].mean() < image[mask == 0].mean()


@pytest.mark.parametrize("seed", range(4))
def test_image_of_a_cup_facing_the_detector_is_centred_on_its_truth(seed):
    """A cup facing the detector on the central ray (theta = 90, k = l = 0): shell, liner and
    head are solids of revolution about the ray through the principal point, so their
    shadow is symmetric about (u0, v0), where the truth ellipse is centred too. The
    principal point lies up to ~7 px off the image centre, so image and truth must agree on
    it: a metal render with its principal point one pixel off had passed every test."""
    config = SynthConfig(image_size=(96, 80), principal_offset_frac=0.08,
                         theta_deg=(90.0, 90.0), k_mm=(0.0, 0.0), l_mm=(0.0, 0.0),
                         pixel_spacing_mm=(2.0, 2.5), h_mm=(100.0, 250.0), **PLAIN)
    sample = synthesize(config, seed, 0)
    image = sample["image"][0].double()
    shadow = image.max() - image  # metal darkens a flat background (no inversion)
    # The whole shadow lies inside the image: a clipped one has its centroid moved.
    assert shadow[[0, -1]].max() < 1e-3 and shadow[:, [0, -1]].max() < 1e-3
    principal = sample["geometry"][2:]
    torch.testing.assert_close(sample["ellipse"][0, :2], principal, rtol=0, atol=1e-9)
    torch.testing.assert_close(centroid(shadow), principal, rtol=0, atol=0.05)


@pytest.mark.parametrize(("size", "principal"), [((127, 95), (60.3, 44.8)),
                                                 ((127, 95), (66.75, 49.2)),
                                                 ((128, 96), (62.0, 47.5))])
def test_bones_cast_at_half_resolution_sit_where_the_metal_would(size, principal):
    """render_bones casts at half resolution and upsamples; the metal's render_parts casts
    every pixel. One ellipsoid rendered both ways has one centroid, so bones and implant
    stay in register (a half-resolution principal point of u0 / 2, not (u0 - 1/2) / 2, had
    put every bone half a pixel off the metal). Odd sizes and fractional principal points:
    the half-resolution grid's end and phase. The half-resolution cast aliases the
    ellipsoid's sharp silhouette by ~0.03 px at this size (46 x 62 px)."""
    geometry = Geometry(1000.0, 0.5, *principal)
    bone = Ellipsoid(np.array([1.0, -2.0, 300.0]), np.eye(3), np.array([8.0, 11.0, 9.0]),
                     0.04).part()
    full = render_parts([bone], geometry, *size)
    assert full[[0, -1]].max() == 0 and full[:, [0, -1]].max() == 0  # not clipped
    half = render_bones([bone], geometry, *size)
    assert half.shape == full.shape
    torch.testing.assert_close(centroid(half), centroid(full), rtol=0, atol=0.05)


@pytest.mark.parametrize(("size", "spacing"), [((64, 48), 5.0), ((48, 64), 320.0 / 48)])
def test_pixel_spacing_spans_the_detector_width(size, spacing):
    """Without pixel_spacing_mm the spacing is detector_width_mm over the image's width
    (columns), whatever its height (SynthConfig's docstring)."""
    config = SynthConfig(image_size=size, detector_width_mm=(320.0, 320.0))
    geometry = sample_geometry(config, np.random.default_rng(0))
    assert geometry.pixel_spacing == pytest.approx(spacing, rel=1e-12)


def test_rims_stay_inside_the_round_field_with_its_margin():
    """With the image intensifier's round field on (its radius and centre, the image
    centre, are the scene's), every rim point lies at least field_margin * min(W, H) inside
    it. A margin added instead of subtracted had put rims up to 7 px past the field's edge
    in a tenth of the scenes. Landmarks lie between the 32 points the placement checks:
    0.5 px of slack for the chords' sag."""
    config = SynthConfig(p_circular_field=1.0, p_no_cup=0.0)
    width, height = config.image_size
    margin = config.field_margin * min(width, height)
    for seed in range(200):
        scene = sample_scene(config, np.random.default_rng([seed, 0]))
        _, _, rim = rim_truth(scene.poses, scene.diameters, scene.geometry)
        radius = torch.hypot(rim[..., 0] - (width - 1) / 2, rim[..., 1] - (height - 1) / 2)
        assert radius.max() <= scene.field_radius - margin + 0.5, seed


@pytest.mark.parametrize(("phi_deg", "side"), [((5.0, 90.0), -1), ((-89.9, -5.0), 1)])
def test_the_stem_lies_on_the_hips_lateral_side(phi_deg, side):
    """CONVENTIONS' AP display puts the patient's right on the image's left (-u), and a
    right hip has phi > 0: its lateral side, where the femoral neck and stem leave the cup,
    is at -u; a left hip's (phi < 0) at +u. A lateral sign flipped had drawn the stem (and
    femur) medially, into the pelvis."""
    size = (96, 96)
    config = SynthConfig(image_size=size, pixel_spacing_mm=(4.0, 4.0), p_head=1.0,
                         p_stem=1.0, p_no_cup=0.0, p_bilateral=0.0, phi_deg=phi_deg)
    for seed in range(6):
        scene = sample_scene(config, np.random.default_rng([seed, 0]))
        _, *stem = scene.metal  # the cup, then its stem
        assert len(stem) == 2  # neck and shaft
        _, ellipse, _ = rim_truth(scene.poses, scene.diameters, scene.geometry)
        stem_u = centroid(render_parts(stem, scene.geometry, *size))[0]
        assert side * (stem_u - ellipse[0, 0]) > 3.0, seed


def _bounds(parts: list) -> list[list[float]]:
    """Each part's bounding box, ``(2, 3)`` mm, as nested lists (the order kept)."""
    return [part.bounds.tolist() for part in parts]


def test_surgical_hardware_adds_to_the_same_scene_and_truth():
    """Screws and the inserter draw from a generator of their own: the same seed gives the
    same truth and, but for the hardware, the same scene (every bone, and with screws alone
    every other metal part, in the same place), so a benchmark with and without them
    compares the same cups."""
    config = SynthConfig(image_size=(128, 128), p_no_cup=0.0, p_bilateral=0.5)
    fitted = dataclasses.replace(config, p_screws=1.0, p_impactor=1.0)
    screwed = dataclasses.replace(config, p_screws=1.0)
    for index in range(4):
        plain, held = synthesize(config, 11, index), synthesize(fitted, 11, index)
        for key in ("pose", "ellipse", "rim", "mask", "geometry", "cup_diameter", "cup_valid"):
            assert torch.equal(plain[key], held[key]), key
        assert not torch.equal(plain["image"], held["image"])
        bare = sample_scene(config, np.random.default_rng([11, index]))
        scenes = [sample_scene(other, np.random.default_rng([11, index]))
                  for other in (fitted, screwed)]
        for scene in scenes:
            assert _bounds(scene.bones) == _bounds(bare.bones)
            assert scene.geometry == bare.geometry and torch.equal(scene.poses, bare.poses)
        # with screws alone, 1-3 a cup added to the same parts
        with_screws = scenes[1]
        metal = _bounds(with_screws.metal)
        assert all(box in metal for box in _bounds(bare.metal))
        assert len(bare.poses) <= len(metal) - len(bare.metal) <= 3 * len(bare.poses)


def test_a_cup_on_its_inserter_has_no_liner_head_or_stem_yet():
    """The femoral side comes after the cup is impacted: the held cup's scene keeps only the
    cup and the rod of the parts a head, liner and stem would add to."""
    config = SynthConfig(p_no_cup=0.0, p_bilateral=0.0, p_head=1.0, p_liner=1.0, p_stem=1.0)
    held = dataclasses.replace(config, p_impactor=1.0)
    for index in range(3):
        bare = sample_scene(config, np.random.default_rng([5, index]))
        scene = sample_scene(held, np.random.default_rng([5, index]))
        assert len(bare.metal) == 3 and len(scene.metal) == 2  # cup, neck, shaft; cup, rod
        assert scene.metal[0].bounds.tolist() == bare.metal[0].bounds.tolist()


def test_screws_leave_the_dome_and_the_inserter_the_opening():
    """A screw's head sits at the cup's inner surface on its dome, its shank outside; the
    inserter's rod covers the axis beyond the opening and stops at the dome's pole, where
    it is screwed in (a ray through the axis behind the dome misses it); the held cup has
    no head or liner."""
    from data_synth.raycast import detector_rays
    from data_synth.scene import sample_cup, surgical_hardware

    config = SynthConfig(p_screws=1.0, p_impactor=1.0, p_screw_holes=0.0, p_head=1.0,
                         p_liner=1.0)
    geometry = Geometry(1000.0, 0.3, 255.5, 255.5)
    pose = torch.tensor([25.0, 40.0, 10.0, -5.0, 300.0], dtype=torch.float64)
    rng = np.random.default_rng(3)
    cup = sample_cup(config, rng, pose, 52.0)
    assert cup.head_radius > 0 and cup.liner_inner > 0
    (*screws, rod), held = surgical_hardware(config, rng, cup, pose, True, geometry.sdd)
    assert held and cup.head_radius == 0 and cup.liner_inner == 0
    centre, axis = pose[2:5].float(), cup.axes[:, 1]
    assert 1 <= len(screws) <= 3 and len(cup.screw_holes) == len(screws)
    for screw in screws:
        head = screw.bounds.mean(0) - centre  # the half-ellipsoid's flat end
        assert float(head @ axis) < 0
        assert abs(float(head.norm()) - (cup.radius - cup.wall)) < 1e-3

    def rod_integral(point: torch.Tensor) -> float:
        """The rod's line integral along the ray through 3D ``point`` (mm)."""
        scale = geometry.sdd / (geometry.sdd - float(point[2]))
        u = torch.tensor([float(point[0]) * scale / geometry.pixel_spacing + 255.5])
        v = torch.tensor([float(point[1]) * scale / geometry.pixel_spacing + 255.5])
        return float(rod.line_integral(detector_rays(geometry, u, v))[0])

    assert rod_integral(centre + axis * (cup.radius + 30)) > 5 * cup.mu_shell
    assert rod_integral(centre - axis * (cup.radius + 3)) == 0.0


def test_the_inserter_stops_short_of_the_source():
    """A rod pointing towards the source ends 10 % of the SDD short of its plane."""
    from data_synth.scene import sample_cup, surgical_hardware

    config = SynthConfig(p_impactor=1.0, impactor_length_mm=(500.0, 500.0))
    sdd = 1000.0
    pose = torch.tensor([40.0, 20.0, 0.0, 0.0, 600.0], dtype=torch.float64)
    cup = sample_cup(config, np.random.default_rng(0), pose, 50.0)
    axis = cup.axes[:, 1].double()
    assert axis[2] > 0.5  # this anteversion turns the opening towards the source
    (rod,), _ = surgical_hardware(config, np.random.default_rng(1), cup, pose, True, sdd)
    solid = rod.line_integral.__self__  # the rod's Ellipsoid
    pole_z = 600.0 - float(axis[2]) * (cup.radius - cup.wall)
    tip_z = pole_z + float(solid.semi_axes[0]) * float(axis[2])
    assert tip_z == pytest.approx(0.9 * sdd, abs=1e-3)


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
