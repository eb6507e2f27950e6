"""``cupnet.batched.batched_cups`` against ``CupNet.detect`` following the same landmark sources."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from cup_cases import networks_not_reached

from benchmarks.model import samples
from benchmarks.throughput import stacked
from cupnet.batched import batched_cups
from cupnet.config import apply_speed_preset
from cupnet.fold import fold_batchnorm
from cupnet.geometry import Geometry
from cupnet.model import load_model, takes_pick


@pytest.fixture(scope="module")
def drrs() -> list[dict]:
    """Twelve 512 px DRRs with the CT background, as the throughput benchmark's; three of
    their cups are ambiguous pairs."""
    return samples("configs/synth_speed.yaml", 777, 12)


# detect's settings that try what batched_cups tries, one cup at a time: no grown-rim
# source, verification, search or later looks (the fastest preset has none of the last
# three, nor the outline; with outline=True the outline stage is compared too).
SAME_SOURCES = {"grown_rim_scale": None, "second_look": False, "third_look_gamma": None,
                "high_gamma_look": None, "fourth_look_turned": False}


@pytest.mark.parametrize(("preset", "thin_rims", "outline"),
                         [("fastest", False, False), ("fastest", True, False),
                          ("fast", True, True)])
def test_batched_cups_are_detects_with_the_same_sources(
        drrs: list[dict], preset: str, thin_rims: bool, outline: bool) -> None:
    """``detect`` trying the same sources in the same order (with the shipped thin-rim
    hypotheses or without; with the outline stage or without), one cup at a time: the
    same cups, poses (an ambiguous cup's second pose too, the pair ordered by doubt with
    the outline stage) and ellipses (a failed cup's the refiner's)."""
    model = fold_batchnorm(load_model())
    shipped = model.config
    model.config = apply_speed_preset(copy.copy(shipped), preset)
    for name, value in SAME_SOURCES.items():
        setattr(model.config, name, value)
    model.config.thin_rim_gate = shipped.thin_rim_gate if thin_rims else None
    images, geometry, diameter = stacked(drrs, torch.device("cpu"))
    found = batched_cups(model, images, geometry, diameter, outline=outline)
    detected = model.detect(images, geometry, diameter, return_masks=False)
    owner = found.cup_index[:, 0].numpy()
    assert len(owner) >= 10  # most DRRs hold a cup the locator finds
    for image, cups in enumerate(detected):
        rows = np.flatnonzero(owner == image)
        assert len(rows) == len(cups)
        for row, cup in zip(rows, cups, strict=True):
            np.testing.assert_allclose(found.pose[row].numpy(), cup.pose, atol=1e-6)
            np.testing.assert_allclose(found.ellipse[row].numpy(), cup.ellipse, atol=1e-6)
            assert bool(found.valid[row]) == np.isfinite(cup.pose).all()
            second = cup.alt_pose if cup.ambiguous else np.full(5, np.nan)
            np.testing.assert_allclose(found.alt_pose[row].numpy(), second, atol=1e-6)
    assert found.valid.float().mean() >= 0.9
    assert sum(cup.ambiguous for cups in detected for cup in cups) >= 2


def test_batched_cups_of_an_image_without_a_cup_and_of_bad_input() -> None:
    model = fold_batchnorm(load_model())
    blank = torch.full((1, 1, 256, 256), 0.5)
    geometry = Geometry.from_rows(torch.tensor([[1000.0, 0.3, 128.0, 128.0]]))
    found = batched_cups(model, blank, geometry, torch.tensor([50.0]))
    assert found.cup_index.shape == (0, 2) and found.pose.shape == (0, 5)
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        batched_cups(model, blank[0], geometry, torch.tensor([50.0]))
    # Named as detect names them; a NaN image had given no cup, the others deep errors.
    two = torch.cat([blank, blank])
    nan = two.clone()
    nan[1, 0, 100:110] = float("nan")
    with pytest.raises(ValueError, match="image 1: contains NaN or infinite values"):
        batched_cups(model, nan, geometry, torch.full((2,), 50.0))
    with pytest.raises(ValueError, match=r"cup_diameter must be a scalar or \(2,\), got \(3,\)"):
        batched_cups(model, two, geometry, torch.full((3,), 50.0))
    three = Geometry.from_rows(torch.tensor([[1000.0, 0.3, 128.0, 128.0]] * 3))
    with pytest.raises(ValueError, match=r"geometry sdd must be a scalar or one per item \(2\)"):
        batched_cups(model, two, three, 50.0)
    for call in (model.detect, lambda *a: model(a[0], a[1], torch.full((2,), a[2]))):
        with pytest.raises(ValueError,
                           match=r"geometry sdd must be a scalar or one per item \(2\)"):
            call(two, three, 50.0)


def test_a_found_cup_whose_rims_give_no_pose_has_none(drrs: list[dict]) -> None:
    """Four times the cup's diameter puts every cup behind the detector: each is found and
    none solved, so each reports no pose (NaN), not zeros, and no second pose."""
    model = fold_batchnorm(load_model())
    images, geometry, diameter = stacked(drrs[:3], torch.device("cpu"))
    found = batched_cups(model, images, geometry, 4 * diameter)
    assert len(found.cup_index) >= 2 and not found.valid.any()
    assert found.pose.isnan().all() and found.alt_pose.isnan().all()


def test_batched_cups_run_a_model_in_train_mode_as_in_eval_mode(drrs: list[dict]) -> None:
    """As detect: evaluated in eval mode, the mode restored; in train mode its BatchNorms had
    used the batch's statistics (h 160.9 -> 143.6 mm) and kept them for later calls."""
    model = load_model()
    images, geometry, diameter = stacked(drrs[:2], torch.device("cpu"))
    expected = batched_cups(model.eval(), images, geometry, diameter)
    state = copy.deepcopy(model.state_dict())
    found = batched_cups(model.train(), images.double(), geometry, diameter)
    assert model.training
    assert all(torch.equal(state[k], v) for k, v in model.state_dict().items())
    assert torch.equal(found.cup_index, expected.cup_index)
    np.testing.assert_allclose(found.pose.numpy(), expected.pose.numpy(), atol=1e-9)


def test_batched_cups_turn_images_the_config_says_show_the_metal_bright(
        drrs: list[dict]) -> None:
    """``metal: bright`` on the images turned over gives what ``metal: dark`` gives on them
    as they are (the networks see the same pixels, but for 1 - (1 - x)'s float rounding)."""
    model = fold_batchnorm(load_model())
    images, geometry, diameter = stacked(drrs[:4], torch.device("cpu"))
    model.config = copy.copy(model.config)
    model.config.metal = "dark"
    expected = batched_cups(model, images, geometry, diameter)
    model.config.metal = "bright"
    found = batched_cups(model, 1 - images, geometry, diameter)
    assert torch.equal(found.cup_index, expected.cup_index) and len(found.cup_index) >= 3
    # 1 - (1 - x) rounds x: a thin rim's h moves by a few tenths of a millimetre with it.
    np.testing.assert_array_less(np.abs(found.pose - expected.pose).nan_to_num().numpy(),
                                 np.broadcast_to([0.05, 0.05, 0.05, 0.05, 0.5],
                                                 found.pose.shape))
    assert torch.equal(found.valid, expected.valid)


def test_the_picking_rule_by_hand():
    # Cups: (a) in range; (b) in range, replacing a pose out of range taken before; (c) a
    # pose out of range, none before; (d) the same with one before; (e) no pose, none
    # before; (f) no pose, one before.
    valid = torch.tensor([True, True, True, True, False, False])
    in_range = torch.tensor([True, True, False, False, False, False])
    before = torch.tensor([False, True, False, True, False, True])
    assert takes_pick(valid, in_range, before, refiner=False).tolist() == [
        True, True, True, False, False, False]
    # The refiner's failure stands for a cup with no pose yet: its mask's ellipse.
    assert takes_pick(valid, in_range, before, refiner=True).tolist() == [
        True, True, True, False, True, False]


@pytest.mark.parametrize("images, geometry, diameter, message", [
    (torch.rand(2, 1, 64, 64), Geometry(torch.tensor([1000.0, -1000.0]), 0.3, 32.0, 32.0),
     50.0, r"image 1: source-to-detector distance must be finite and > 0 mm, got -1000\.0"),
    (torch.rand(2, 1, 64, 64), Geometry(1000.0, 0.3, 32.0, 32.0), torch.tensor([50.0, -50.0]),
     r"image 1: cup diameter must be a finite number > 0 mm, got -50\.0"),
    (torch.rand(2, 3, 64, 64), Geometry(1000.0, 0.3, 32.0, 32.0), 50.0,
     r"images must be a \(B, 1, H, W\) tensor with B >= 1, got \(2, 3, 64, 64\)"),
])
def test_batched_cups_refuses_what_detect_refuses_before_its_networks(images, geometry,
                                                                      diameter, message):
    """As detect names them: an unusable value had given its cups NaN poses and an
    unexplained valid False (an image without a cup said nothing), three channels a
    later stage's error."""
    model = load_model()
    model.locate_windows = model.locate = networks_not_reached
    with pytest.raises(ValueError, match=message):
        batched_cups(model, images, geometry, diameter)
