"""Rim stage: strip frames, sampling, landmarks, the network's symmetry and its use in CupNet."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from cupnet.config import CupNetConfig
from cupnet.ellipse import ellipse_points, fit_ellipse, params_to_conic, sampson_distance
from cupnet.geometry import Geometry
from cupnet.landmarks import ellipse_coverage
from cupnet.model import CupNet, load_model, save_model
from cupnet.pose import ellipse_of_pose
from cupnet.rim import (
    RimLandmarks,
    RimNet,
    ellipse_step_basis,
    memoised_strips,
    normal_crossings,
    rim_frame,
    sample_strips,
    scaled_offsets,
    settled_offsets,
    strip_landmarks,
    strip_offsets,
    thin_rim_starts,
)
from train.losses import rim_loss

ELLIPSES = torch.tensor([[120.0, 95.0, 60.0, 22.0, 31.0], [70.5, 140.2, 48.0, 47.0, 170.0],
                         [150.0, 150.0, 80.0, 1.5, 95.0]], dtype=torch.float64)


def test_rim_frame_points_and_outward_normals():
    points, normals = rim_frame(ELLIPSES, 96)
    t = torch.arange(96, dtype=torch.float64) * (2 * math.pi / 96)
    assert torch.allclose(points, ellipse_points(ELLIPSES, t), atol=1e-12)
    # Outward unit normals: along the conic's gradient (C p)_xy, pointing away from the centre.
    hom = torch.cat([points, torch.ones_like(points[..., :1])], -1)
    grad = torch.einsum("kij,knj->kni", params_to_conic(ELLIPSES)[:, :2], hom)
    grad = grad / grad.norm(dim=-1, keepdim=True)
    assert torch.allclose(normals, grad * grad.mul(normals).sum(-1, keepdim=True).sign(),
                          atol=1e-9)
    assert ((points - ELLIPSES[:, None, :2]) * normals).sum(-1).min() > 0


def test_normal_crossings_hand_derived_on_a_circle():
    circle = torch.tensor([[0.0, 0.0, 10.0, 10.0, 0.0]], dtype=torch.float64)
    # Outside moving out (leaves behind it), inside moving out, a chord, a line that misses.
    points = torch.tensor([[[12.0, 0.0], [0.0, -9.5], [6.0, 0.0], [0.0, 20.0]]],
                          dtype=torch.float64)
    normals = torch.tensor([[[1.0, 0.0], [0.0, -1.0], [0.0, 1.0], [1.0, 0.0]]],
                           dtype=torch.float64)
    expected = torch.tensor([[-2.0, 0.5, 8.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(normal_crossings(points, normals, circle), expected, atol=1e-9)
    # Frames of a perturbed ellipse: the crossings lie on the true ellipse.
    frame_points, frame_normals = rim_frame(ELLIPSES + torch.tensor([2.0, -1.0, 3.0, 0.5, 2.0],
                                                                    dtype=torch.float64), 64)
    s = normal_crossings(frame_points, frame_normals, ELLIPSES)
    on_rim = frame_points + s[..., None] * frame_normals
    assert sampson_distance(params_to_conic(ELLIPSES), on_rim)[:2].abs().max() < 1e-6


def test_ellipse_step_basis_matches_finite_differences_of_the_crossings():
    """Each column's edge offset per unit step of each ellipse parameter equals the central
    difference of :func:`normal_crossings` to the stepped ellipse (an independent exact
    intersection), the thin ellipse included."""
    points, normals = rim_frame(ELLIPSES, 64)
    basis = ellipse_step_basis(ELLIPSES, normals)
    step = 1e-4
    for i in range(5):
        delta = torch.zeros(5, dtype=torch.float64)
        delta[i] = step
        numeric = (normal_crossings(points, normals, ELLIPSES + delta)
                   - normal_crossings(points, normals, ELLIPSES - delta)) / (2 * step)
        assert torch.allclose(basis[..., i], numeric, atol=1e-5), i


def test_settled_offsets_take_out_an_ellipse_step_but_not_another_edge():
    """Offsets to a slightly moved ellipse (under a pixel and half a degree) settle to under a
    tenth of a pixel (the thin ellipse's tips, where the step is far from linear, aside).
    Twelve columns 6 px off on another edge keep most of their offset, and the Laplace
    reweighting roughly halves their pull on the others against one plain weighted fit."""
    points, normals = rim_frame(ELLIPSES, 128)
    moved = ELLIPSES + torch.tensor([0.8, -0.5, 0.6, 0.8, 0.5], dtype=torch.float64)
    offset = normal_crossings(points, normals, moved)
    sigma = torch.full_like(offset, 0.5)
    residual = settled_offsets(offset, sigma, ELLIPSES, normals)
    assert (offset.abs().median(-1).values > 0.5).all()
    assert (residual.abs().median(-1).values < 0.1).all()
    assert offset[:2].abs().amax() > 1.5
    assert residual[:2].abs().amax() < 0.1
    other = offset[:2].clone()
    other[:, 20:32] += 6.0

    def pulled(iterations: int) -> torch.Tensor:
        residual = settled_offsets(other, sigma[:2], ELLIPSES[:2], normals[:2], iterations)
        assert (residual[:, 20:32] > 3.0).all()
        return torch.cat([residual[:, :20], residual[:, 32:]], 1).abs().median(-1).values

    plain, reweighted = pulled(1), pulled(2)
    assert (reweighted < 0.6 * plain).all()
    assert (reweighted < 0.3).all()
    empty = offset[:0]
    assert settled_offsets(empty, sigma[:0], ELLIPSES[:0], normals[:0]).shape == (0, 128)
    with pytest.raises(ValueError, match="at least one fit"):
        settled_offsets(offset, sigma, ELLIPSES, normals, iterations=0)


def test_scaled_offsets_reach_a_fraction_of_each_cups_major_axis():
    offsets = scaled_offsets(5, ELLIPSES, 0.5)
    # a = 60, 48, 80: rows 0.25 a apart from -a/2 to a/2.
    assert torch.allclose(offsets, torch.tensor([[-30.0, -15, 0, 15, 30], [-24, -12, 0, 12, 24],
                                                 [-40, -20, 0, 20, 40]], dtype=torch.float64))


@pytest.mark.parametrize("per_cup", [False, True])
def test_sample_strips_is_exact_on_a_linear_image(per_cup):
    # Bilinear interpolation reproduces a linear image exactly: the samples must equal the
    # ramp at p + s n, in CONVENTIONS pixels (centres at integers).
    height, width = 220, 260
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64),
                          torch.arange(width, dtype=torch.float64), indexing="ij")
    images = torch.stack([0.01 * u + 0.02 * v, 0.5 - 0.003 * u + 0.004 * v])[:, None]
    index = torch.tensor([1, 0, 1])
    ellipses = ELLIPSES * torch.tensor([1, 1, 0.5, 0.5, 1.0])
    points, normals = rim_frame(ellipses, 32)
    offsets = scaled_offsets(16, ellipses, 0.3) if per_cup else strip_offsets(16, 0.75)
    strips = sample_strips(images, index, points, normals, offsets)
    assert strips.shape == (3, 1, 16, 32)
    where = points[:, None] + offsets.expand(3, 16)[:, :, None, None] * normals[:, None]
    coef = torch.tensor([[0.0, 0.01, 0.02], [0.5, -0.003, 0.004]], dtype=torch.float64)[index]
    expected = (coef[:, None, None, :1] + (where * coef[:, None, None, 1:]).sum(-1, keepdim=True))
    assert torch.allclose(strips[:, 0], expected[..., 0], atol=1e-12)


def test_strip_landmarks_sit_at_the_expected_offset():
    points, normals = rim_frame(ELLIPSES[:1], 8)
    offsets = strip_offsets(9, 0.5)
    logits = torch.full((1, 9, 8), -1e4, dtype=torch.float64)
    rows = torch.tensor([0, 2, 4, 6, 8, 4, 4, 3])
    logits[0, rows, torch.arange(8)] = 0.0
    log_sigma = torch.log(torch.tensor([[0.5, 1, 1, 1, 1, 1, 1, 2]], dtype=torch.float64))
    rim = strip_landmarks(logits, log_sigma, points, normals, offsets)
    assert torch.allclose(rim.offset, offsets[rows][None])
    assert torch.allclose(rim.landmarks, points + offsets[rows][None, :, None] * normals)
    assert torch.allclose(rim.sigma, log_sigma.exp())
    assert torch.allclose(rim.weights, rim.sigma.pow(-2) / rim.sigma.pow(-2).mean())
    assert torch.equal(rim.reach, torch.tensor([[2.0]], dtype=torch.float64))  # 4 rows of 0.5


def test_rim_net_is_equivariant_to_turning_around_the_rim():
    # Columns are positions around a closed curve: the network pads circularly, so rolling a
    # strip's columns rolls its outputs.
    torch.manual_seed(0)
    net = RimNet(channels=8).eval()
    strips = torch.randn(2, 1, 32, 24)
    logits, log_sigma = net(strips)
    rolled_logits, rolled_sigma = net(strips.roll(5, -1))
    assert logits.shape == (2, 32, 24) and log_sigma.shape == (2, 24)
    assert torch.allclose(rolled_logits, logits.roll(5, -1), atol=1e-5)
    assert torch.allclose(rolled_sigma, log_sigma.roll(5, -1), atol=1e-5)



def test_rim_net_runs_strips_one_by_one_only_in_eval_mode():
    torch.manual_seed(1)
    net = RimNet(channels=8)
    for norm in net.modules():  # BatchNorm statistics that differ from a batch's own
        if isinstance(norm, nn.BatchNorm2d):
            norm.running_mean.uniform_(-0.5, 0.5)
            norm.running_var.uniform_(0.5, 2.0)
    strips = torch.randn(5, 1, 32, 24)
    whole = net.eval().forward_batch(strips)
    batches: list[int] = []
    forward_batch = net.forward_batch
    net.forward_batch = lambda x: batches.append(len(x)) or forward_batch(x)
    for ours, theirs in zip(net(strips), whole, strict=True):
        assert torch.allclose(ours, theirs, atol=1e-5)
    assert batches == [1] * 5
    # Training: the batch's BatchNorm statistics, so the outputs of one strip depend on the
    # others in its batch.
    batches.clear()
    net.train()
    together = net(strips)[0][:1]
    assert batches == [5]
    assert not torch.allclose(together, net(strips[:2])[0][:1], atol=1e-3)

@pytest.mark.parametrize("threads", [1, 2])
def test_memoised_strips_run_each_distinct_strip_once(threads):
    torch.manual_seed(2)
    net = RimNet(channels=8).eval()
    strips = torch.randn(3, 1, 32, 24)
    batches: list[int] = []
    forward_batch = net.forward_batch
    net.forward_batch = lambda x: batches.append(len(x)) or forward_batch(x)
    plain = net(strips)
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.inference_mode(), memoised_strips():
            batches.clear()
            first = net(strips)
            # Strip 1 again, a new strip, strip 2 again (a copy: equal values, other storage).
            again = net(torch.cat([strips[1:2], torch.randn(1, 1, 32, 24), strips[2:].clone()]))
            assert batches == [1] * 4  # the three strips, then only the new one
            other = RimNet(channels=8).eval()  # another network's outputs are its own
            assert not torch.allclose(other(strips[:1])[0], first[0][:1])
        with torch.inference_mode():  # outside the block: no memo
            batches.clear()
            net(strips)
            assert batches == [1] * 3
    finally:
        torch.set_num_threads(previous)
    for ours, theirs in zip(first, plain, strict=True):
        assert torch.equal(ours, theirs)
    assert torch.equal(again[0][0], first[0][1]) and torch.equal(again[0][2], first[0][2])
    assert torch.equal(again[1][2], first[1][2])
    # With gradients (a loss through the network) nothing is reused.
    with memoised_strips():
        batches.clear()
        net(strips), net(strips)
        assert batches == [1] * 6


def test_rim_loss_is_the_laplace_likelihood_of_the_offset_error():
    circle = torch.tensor([[0.0, 0.0, 10.0, 10.0, 0.0]], dtype=torch.float64)
    points = torch.tensor([[[12.0, 0.0], [0.0, -9.5], [0.0, 4.0]]], dtype=torch.float64)
    normals = torch.tensor([[[1.0, 0.0], [0.0, -1.0], [0.0, 1.0]]], dtype=torch.float64)
    offset = torch.tensor([[-1.0, 0.0, 5.5]], dtype=torch.float64)
    sigma = torch.tensor([[1.0, 0.25, 2.0]], dtype=torch.float64)
    rim = RimLandmarks(points + offset[..., None] * normals, sigma.pow(-2), sigma, offset,
                       points, normals, torch.tensor([[5.0]], dtype=torch.float64))
    # Crossings at -2, 0.5 and 6, the last clipped to the reach of 5.
    error = torch.tensor([1.0, 0.5, 0.5], dtype=torch.float64)
    expected = (error / sigma[0] + sigma[0].log()).mean()
    assert float(rim_loss(rim, circle)) == pytest.approx(float(expected))
    # Each cup's own reach: clipped at 4 instead, the last error is 1.5.
    reach = torch.tensor([[5.0], [4.0]], dtype=torch.float64)
    two = RimLandmarks(*(torch.cat([x, x]) for x in rim[:-1]), reach)
    error = torch.tensor([1.0, 0.5, 1.5], dtype=torch.float64)
    expected = (expected + (error / sigma[0] + sigma[0].log()).mean()) / 2
    assert float(rim_loss(two, circle.repeat(2, 1))) == pytest.approx(float(expected))


class EdgeRimNet(nn.Module):
    """Stand-in rim network: each column's offset distribution is proportional to the
    strip's slope magnitude along the normal (the landmark is the slope's centroid)."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.tensor(1.0))

    def forward(self, strips: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = strips[:, 0]
        slope = torch.cat([x[:, 1:2] - x[:, :1], (x[:, 2:] - x[:, :-2]) / 2,
                           x[:, -1:] - x[:, -2:-1]], 1)
        return torch.log(self.scale * slope.abs() + 1e-30), torch.zeros_like(x[:, 0])


RIM = CupNetConfig(encoder="resnet18", decoder_channels=(8, 8), n_rays=48, ray_samples=96,
                   rim_passes=2, rim_points=64, rim_samples=48, rim_step=0.5, rim_channels=8)


def _rim_scene() -> tuple[torch.Tensor, Geometry, torch.Tensor]:
    geometry = Geometry.for_image(320, 300, 1040.0, 0.3)
    ellipse = ellipse_of_pose(torch.tensor([[24.0, 33.0, 8.0, -6.0, 300.0]], dtype=torch.float64),
                              52.0, geometry)
    # 8 x 8 supersampled area coverage: a step edge exactly on the rim.
    image = ellipse_coverage(ellipse[None], 300, 320, supersample=8)[0]
    return image, geometry, ellipse


def test_rim_stage_moves_landmarks_onto_the_rim():
    image, geometry, ellipse = _rim_scene()
    model = CupNet(RIM).double()
    model.rim = EdgeRimNet().double()
    start = ellipse + torch.tensor([[3.0, -2.5, 4.0, -3.0, 4.0]], dtype=torch.float64)
    landmarks, weights = model.rim_landmarks(image[None], torch.tensor([0]), start)[:2]
    dist = sampson_distance(params_to_conic(ellipse), landmarks)
    assert landmarks.shape == (1, 64, 2) and dist.abs().max() < 0.1 and dist.abs().mean() < 0.03
    fitted = fit_ellipse(landmarks.detach(), weights.detach()).params[0]
    assert torch.allclose(fitted[:4], ellipse[0, :4], atol=0.05)
    assert math.isclose(float(fitted[4]), float(ellipse[0, 4]), abs_tol=0.1)


def test_coarse_rim_stage_reaches_a_rim_beyond_the_fine_stages_reach():
    image, geometry, ellipse = _rim_scene()
    model = CupNet(CupNetConfig(**{**RIM.__dict__, "coarse_rim_passes": 1})).double()
    model.rim, model.coarse_rim = EdgeRimNet().double(), EdgeRimNet().double()
    # A femoral head's outline for a rim: rounder and smaller, beyond the fine strips' 12 px.
    start = ellipse + torch.tensor([[3.0, -2.0, -16.0, 20.0, 6.0]], dtype=torch.float64)
    index = torch.tensor([0])
    conic = params_to_conic(ellipse)

    def worst_distance(landmarks: torch.Tensor) -> float:
        return float(sampson_distance(conic, landmarks).abs().max())

    assert worst_distance(model.rim_landmarks(image[None], index, start).landmarks) > 5.0
    coarse = model.rim_landmarks(image[None], index, start, coarse=True)
    assert coarse.offset.abs().max() > model.rim_reach and worst_distance(coarse.landmarks) < 1.5
    refined = model.coarse_framed_rim_landmarks(image[None], index, start)
    assert worst_distance(refined.landmarks) < 0.1


class SureEdgeRimNet(EdgeRimNet):
    """:class:`EdgeRimNet` whose ``sigma`` is small where its column sees an edge."""

    def forward(self, strips: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, _ = super().forward(strips)
        return logits, -logits.exp().amax(1).clamp_min(1e-3).log()


@pytest.mark.parametrize(("gate", "rescued"), [(None, False), (100.0, False), (0.0, True)])
def test_trusted_rim_landmarks_take_the_coarse_path_where_the_fine_stage_doubts(gate, rescued):
    image, geometry, ellipse = _rim_scene()
    # One fine pass: from a far start, the columns that see no edge cannot follow the others.
    config = {**RIM.__dict__, "coarse_rim_passes": 1, "rim_passes": 1, "coarse_rim_gate": gate}
    model = CupNet(CupNetConfig(**config)).double()
    model.rim, model.coarse_rim = SureEdgeRimNet().double(), EdgeRimNet().double()
    far = ellipse + torch.tensor([[3.0, -2.0, -16.0, 20.0, 6.0]], dtype=torch.float64)
    landmarks, _ = model.trusted_rim_landmarks([image], torch.tensor([0]), far)
    worst = float(sampson_distance(params_to_conic(ellipse), landmarks).abs().max())
    assert worst < 0.1 if rescued else worst > 5.0


def test_thin_rim_starts_spread_thin_ellipses_over_half_a_turn():
    ellipse = torch.tensor([[100.0, 80.0, 50.0, 40.0, 33.0], [10.0, 20.0, 30.0, 30.0, 0.0]],
                           dtype=torch.float64)
    starts = thin_rim_starts(ellipse, 12, 0.15)
    assert starts.shape == (2, 12, 5)
    assert torch.equal(starts[..., :3], ellipse[:, None, :3].expand(2, 12, 3))
    assert torch.allclose(starts[..., 3], 0.15 * ellipse[:, None, 2].expand(2, 12))
    assert torch.allclose(starts[0, :, 4], torch.arange(0.0, 180.0, 15.0, dtype=torch.float64))


@pytest.mark.parametrize(("gate", "margin", "rescued"),
                         [(None, 0.0, False), (0.0, 0.0, True), (0.0, 0.5, True),
                          (0.0, 20.0, False)])
def test_thin_rim_hypotheses_find_a_rim_the_segmentation_took_for_a_disc(gate, margin, rescued):
    # A nearly edge-on rim 4 degrees off the nearest hypothesis, and the round outline a
    # segmentation of cup and femoral head gives for it: the fine strips (12 px) reach the
    # rim only near its tips. (Wide enough that no strip crosses both of its long sides: the
    # stand-in network would average them.)
    rim = torch.tensor([[200.0, 190.0, 120.0, 15.0, 34.0]], dtype=torch.float64)
    image = ellipse_coverage(rim[None], 380, 400, supersample=8)[0]
    disc = torch.tensor([[201.0, 189.0, 118.0, 110.0, 100.0]], dtype=torch.float64)
    config = {**RIM.__dict__, "thin_rim_gate": gate, "thin_rim_margin": margin}
    model = CupNet(CupNetConfig(**config)).double()
    model.rim = SureEdgeRimNet().double()
    landmarks, weights = model.trusted_rim_landmarks([image], torch.tensor([0]), disc)
    # The stand-in trusts the thin rim's landmarks far more than the disc's (a margin of 0.5
    # keeps them, one of 20 in log sigma does not).
    # The stand-in places the columns at the thin rim's tips poorly: it takes the slope's
    # centroid across a strip that runs along the rim there, and says it is unsure.
    typical = float(sampson_distance(params_to_conic(rim), landmarks).abs().median())
    assert typical < 0.1 if rescued else typical > 5.0
    if rescued:
        fitted = fit_ellipse(landmarks, weights).params[0]
        assert torch.allclose(fitted[[0, 1, 3]], rim[0, [0, 1, 3]], atol=0.3)  # disc: b 95 px off
        assert abs(float(fitted[2] - rim[0, 2])) < 4.0  # tips short by the stand-in's
        assert math.isclose(float(fitted[4]), float(rim[0, 4]), abs_tol=0.2)


def test_pose_loss_reaches_the_rim_network():
    torch.manual_seed(0)
    image, geometry, ellipse = _rim_scene()
    model = CupNet(RIM)
    # Stand-in refiner that thresholds the standardised crop, so the rim stage starts near
    # the rim (an untrained U-Net's map is arbitrary); the rim network is the real one.
    model.refiner = nn.Conv2d(1, 1, 1)
    with torch.no_grad():
        model.refiner.weight.fill_(20.0)
        model.refiner.bias.zero_()
    out = model(image.float()[None], geometry, torch.tensor([52.0]),
                crop_frames=model.frames(ellipse)[None])
    assert out.landmarks.shape == (1, 64, 2) and out.rim.sigma.shape == (1, 64)
    assert out.solution.valid.all(), out.solution.status
    out.solution.pose.sum().backward()
    grad = model.rim.body[0].conv.weight.grad
    assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_rim_model_round_trips_and_detects(tmp_path):
    torch.manual_seed(2)
    model = CupNet(RIM).eval()
    loaded = load_model(save_model(model, tmp_path / "rim.safetensors"))
    assert loaded.config == model.config and loaded.rim is not None
    strips = torch.rand(2, 1, RIM.rim_samples, RIM.rim_points)
    with torch.no_grad():
        assert all(torch.equal(x, y) for x, y in zip(model.rim(strips), loaded.rim(strips),
                                                     strict=True))
    image, geometry, _ = _rim_scene()
    assert loaded.detect(torch.zeros(1, 1, 300, 320), geometry, 52.0) == [[]]
    # Untrained networks: the landmarks are the rim stage's, or the refiner's where the rim
    # stage's gave no pose.
    for found in loaded.detect(image.float()[None], geometry, 52.0):
        assert all(det.landmarks.shape in ((RIM.rim_points, 2), (RIM.n_rays, 2)) for det in found)


class PartlyBrokenRimNet(nn.Module):
    """Stand-in rim network: :class:`EdgeRimNet` for the first cup of a batch, NaN (no pose
    can come of it) for the others."""

    def __init__(self) -> None:
        super().__init__()
        self.edges = EdgeRimNet()

    def forward(self, strips: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, log_sigma = self.edges(strips)
        logits, log_sigma = logits.clone(), log_sigma.clone()
        logits[1:], log_sigma[1:] = math.nan, math.nan
        return logits, log_sigma


def _wide_scene(poses_deg: list[list[float]]) -> tuple[torch.Tensor, Geometry, torch.Tensor]:
    """A 640 x 360 image (0.5 mm pixels) of the cups' openings as step edges, its geometry
    and the true ellipses."""
    geometry = Geometry.for_image(640, 360, 1040.0, 0.5)
    ellipse = ellipse_of_pose(torch.tensor(poses_deg, dtype=torch.float64), 52.0, geometry)
    return ellipse_coverage(ellipse[None], 360, 640, supersample=8)[0], geometry, ellipse


def _threshold_locator_and_refiner(model: CupNet) -> None:
    """Stand-in locator and refiner that threshold the standardised image: they segment a
    bright opening exactly (an untrained U-Net's map is arbitrary)."""
    model.locator, model.refiner = nn.Conv2d(1, 1, 1), nn.Conv2d(1, 1, 1)
    with torch.no_grad():
        for net in (model.locator, model.refiner):
            net.weight.fill_(20.0)
            net.bias.zero_()


@pytest.mark.parametrize("coarse", [False, True])
def test_detect_falls_back_where_the_rim_stage_fails(coarse):
    # Crops of one cup must not hold the other (the stand-in refiner would segment both).
    image, geometry, ellipse = _wide_scene([[24.0, 33.0, -45.0, -6.0, 300.0],
                                            [18.0, -28.0, 50.0, 8.0, 320.0]])
    # Short coarse strips: the stand-in's slope centroid would take in the other cup's rim.
    config = {**RIM.__dict__, "coarse_rim_passes": int(coarse), "coarse_rim_reach": 0.2}
    model = CupNet(CupNetConfig(**config)).double()
    _threshold_locator_and_refiner(model)
    model.rim = PartlyBrokenRimNet().double()
    if coarse:
        model.coarse_rim = EdgeRimNet().double()
    (found,) = model.detect(image[None], geometry, 52.0)
    assert len(found) == 2 and all(det.status in ("ok", "ambiguous") for det in found)
    # The larger cup comes first: the rim stage's landmarks, on the rim. The other, whose
    # rim-stage landmarks give no pose, falls back on the coarse stage's path where the model
    # has one (run on that cup alone, where the stand-in works), else on the refiner's.
    assert found[0].landmarks.shape == (RIM.rim_points, 2)
    assert found[1].landmarks.shape == ((RIM.rim_points, 2) if coarse else (RIM.n_rays, 2))
    for det in found:
        true = ellipse[int(abs(det.ellipse[0] - ellipse[:, 0]).argmin())]
        assert abs(det.ellipse[2] - float(true[2])) < (0.1 if det is found[0] or coarse else 2.0)


@pytest.mark.parametrize(("limit", "thin_gate"), [(None, None), (52.0, None), (52.0, 0.0)])
def test_detect_passes_over_a_pose_beyond_max_theta(limit, thin_gate):
    # The fine rim stage (stood in for) follows a round outline around the rim, as it does
    # for a nearly edge-on cup and its femoral head: a pose near theta = 90 deg. Beyond
    # max_theta_deg the cup goes on to the next landmark source: the refiner's, which
    # segments the true opening, before the thin-rim hypotheses where the model has them.
    image, geometry, ellipse = _wide_scene([[24.0, 33.0, -5.0, -6.0, 300.0]])
    config = {**RIM.__dict__, "max_theta_deg": limit, "thin_rim_gate": thin_gate}
    model = CupNet(CupNetConfig(**config)).double()
    _threshold_locator_and_refiner(model)
    model.rim = EdgeRimNet().double()
    outline = ellipse.clone()
    outline[:, 3] = outline[:, 2]
    t = torch.arange(RIM.rim_points, dtype=torch.float64) * (2 * math.pi / RIM.rim_points)
    round_points = ellipse_points(outline, t)
    model.trusted_rim_landmarks = lambda images, index, start: (
        round_points.expand(len(index), -1, -1), torch.ones(len(index), RIM.rim_points,
                                                            dtype=torch.float64))
    ((det,),) = model.detect(image[None], geometry, 52.0)
    assert det.status in ("ok", "ambiguous")
    if limit is None:
        assert det.pose[0] > 60.0 and det.landmarks.shape == (RIM.rim_points, 2)
    else:
        assert abs(det.pose[0] - 24.0) < 1.5 and det.landmarks.shape == (RIM.n_rays, 2)


def test_detect_keeps_a_pose_beyond_max_theta_over_a_failure():
    image, geometry, _ = _rim_scene()  # theta 24 deg
    model = CupNet(CupNetConfig(**{**RIM.__dict__, "max_theta_deg": 10.0})).double()
    _threshold_locator_and_refiner(model)
    model.rim = NaNRimNet()  # the rim stage gives no pose; the refiner's landmarks one
    ((det,),) = model.detect(image[None], geometry, 52.0)
    assert det.status == "ok" and abs(det.pose[0] - 24.0) < 2.0
    assert det.landmarks.shape == (RIM.n_rays, 2)


class NaNRimNet(nn.Module):
    """Stand-in rim network whose landmarks give no pose."""

    def forward(self, strips: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.full(strips[:, 0].shape, math.nan, dtype=strips.dtype),
                torch.full(strips[:, 0, 0].shape, math.nan, dtype=strips.dtype))


def test_detect_keeps_the_first_pose_where_none_is_within_max_theta():
    image, geometry, ellipse = _rim_scene()  # theta 24 deg
    model = CupNet(CupNetConfig(**{**RIM.__dict__, "max_theta_deg": 10.0})).double()
    _threshold_locator_and_refiner(model)
    model.rim = EdgeRimNet().double()
    ((det,),) = model.detect(image[None], geometry, 52.0)
    assert det.status == "ok" and abs(det.pose[0] - 24.0) < 0.5
    assert det.landmarks.shape == (RIM.rim_points, 2)  # the rim stage's, the first source


class HeadRefiner(nn.Module):
    """Stand-in refiner that segments a small disc at the centre of every crop, as the real
    one segments a femoral head inside the cup: each pass frames the next on a smaller
    ellipse, and the landmarks end far inside the rim."""

    def forward(self, crops: torch.Tensor) -> torch.Tensor:
        size = crops.shape[-1]
        head = torch.tensor([[[(size - 1) / 2, (size - 1) / 2, 0.2 * size, 0.2 * size, 0.0]]],
                            dtype=torch.float64)
        coverage = ellipse_coverage(head, size, size, supersample=4)[0].to(crops.dtype)
        return (20.0 * coverage - 10.0).expand(crops.shape[0], 1, size, size)


@pytest.mark.parametrize("scale", [None, 1.45])
def test_detect_grows_a_start_too_small_for_the_cup(scale):
    # a = 73 px; 52 px at magnification 1
    image, geometry, _ = _wide_scene([[24.0, 33.0, -5.0, -6.0, 300.0]])
    config = {**RIM.__dict__, "coarse_rim_passes": 1, "grown_rim_scale": scale}
    model = CupNet(CupNetConfig(**config)).double()
    _threshold_locator_and_refiner(model)
    model.refiner = HeadRefiner()
    model.rim, model.coarse_rim = EdgeRimNet().double(), EdgeRimNet().double()
    ((det,),) = model.detect(image[None], geometry, 52.0)
    if scale is None:  # every other source keeps to the small disc: no pose
        assert det.status.startswith("error")
        assert det.landmarks.shape == (RIM.n_rays, 2)  # the refiner's, as its mask shows
    else:
        assert det.status in ("ok", "ambiguous")
        assert abs(det.pose[0] - 24.0) < 1.0 and abs(det.pose[4] - 300.0) < 15.0
        assert det.landmarks.shape == (RIM.rim_points, 2)



@pytest.mark.parametrize("min_scale", [None, 0.8])
def test_refiner_fits_grow_to_reframe_min_scale(min_scale):
    image, geometry, _ = _rim_scene()
    config = {**RIM.__dict__, "reframe_min_scale": min_scale, "refine_passes": 3}
    model = CupNet(CupNetConfig(**config)).double()
    _threshold_locator_and_refiner(model)
    model.refiner = HeadRefiner()  # its fits: about half the frame's ellipse
    model.rim = EdgeRimNet().double()
    framed: list[torch.Tensor] = []
    segment_crops = model.segment_crops

    def recording(images, frames, index):
        framed.append(frames[:, 2].clone())
        return segment_crops(images, frames, index)

    model.segment_crops = recording
    starts: list[torch.Tensor] = []
    rim_landmarks = model.trusted_rim_landmarks
    model.trusted_rim_landmarks = lambda images, index, start: (
        starts.append(start[:, 2].clone()) or rim_landmarks(images, index, start))
    model.detect(image[None], geometry, 52.0)
    # Each pass frames the next, and the last pass starts the rim stage, on its fit: a
    # disc half its frame's size, grown to 0.8 of it where the limit is set.
    last_frame_ellipse = framed[-1] * RIM.crop_fill / 2
    ratios = [float(b / a) for a, b in zip(framed[:-1], framed[1:], strict=True)]
    ratios.append(float(starts[0] / last_frame_ellipse))
    assert len(ratios) == 3
    for ratio in ratios:
        assert math.isclose(ratio, 0.8, abs_tol=1e-6) if min_scale else ratio < 0.6
