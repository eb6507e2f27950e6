"""Training: the smoke config learns, checkpoints round-trip, seeds reproduce batches and losses."""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import math
import subprocess
import warnings
from pathlib import Path
from types import SimpleNamespace

import lightning as L
import pytest
import torch
import yaml
from torch.utils.data import DataLoader

from cupnet.cli import main as cupnet_main
from cupnet.crops import resample_batch, square_windows
from cupnet.model import DEFAULT_CHECKPOINT, config_path, load_model, save_model
from data_synth.dataset import stream_share
from train.cli import add_arguments, lightning_args, main
from train.data import CupDataModule, RoundRobinBatches
from train.losses import (
    distill_loss,
    ellipse_loss,
    pose_errors,
    pose_loss,
    ramp,
    segmentation_loss,
    wrap_angle,
)
from train.merge import main as merge_main
from train.merge import merged
from train.module import (
    CosineToFloor,
    CupNetModule,
    _pose_maes,
    coarse_rim_starts,
    far_rim_starts,
    jittered_ellipses,
)

ROOT = Path(__file__).resolve().parent.parent
SMOKE = ROOT / "configs" / "smoke.yaml"


def test_cli_implies_fit():
    assert lightning_args(["--config", "c.yaml"]) == ["fit", "--config", "c.yaml"]
    assert lightning_args(["validate", "-c", "c.yaml"]) == ["validate", "-c", "c.yaml"]


def test_sub_commands_the_module_has_no_step_for_name_what_to_use(capsys):
    """Lightning had failed deep in its loop ("No test_step()")."""
    assert cupnet_main(["train", "test", "-c", str(SMOKE)]) == 2
    assert "cupnet train test is not offered; use cupnet evaluate" in capsys.readouterr().err
    with pytest.raises(ValueError, match="use cupnet predict"):
        lightning_args(["predict", "-c", "c.yaml"])


@pytest.mark.parametrize("argv", [["--config", "c.yaml", "--trainer.max_steps", "3"],
                                  ["fit", "-c", "c.yaml"], ["-h"]])
def test_cupnet_train_hands_every_argument_to_lightning(argv):
    # The `cupnet` dispatcher parses a sub-command's arguments with its add_arguments().
    parser = argparse.ArgumentParser(prog="cupnet train")
    add_arguments(parser)
    assert parser.parse_args(argv).argv == argv


def test_a_network_setting_given_on_the_command_line_builds_that_network(capsys):
    """``--model.model.rim_channels 8``: the module takes CupNet's config as a dict, whose
    keys jsonargparse cannot type, so the value arrives as a string ('8'); the module
    builds the 8-channel rim network it names (it had failed deep in torch)."""
    with pytest.raises(SystemExit):
        main(["fit", "-c", str(SMOKE), "--model.model.rim_channels", "8",
              "--model.model.rim_passes", "1", "--print_config"])
    settings = yaml.safe_load(capsys.readouterr().out)["model"]["model"]
    assert settings["rim_channels"] == "8"
    module = CupNetModule(model=settings)
    assert module.model.rim.offset_head.in_channels == 8


def test_phi_errors_wrap_at_180_degrees():
    pred = torch.tensor([[10.0, 89.0, 0, 0, 0], [10.0, -60.0, 1, 2, 3]], dtype=torch.float64)
    truth = torch.tensor([[12.0, -89.0, 0, 0, 0], [10.0, 60.0, 0, 0, 0]], dtype=torch.float64)
    err = pose_errors(pred, truth)
    assert torch.allclose(err[:, 0], torch.tensor([-2.0, 0.0], dtype=torch.float64))
    assert torch.allclose(err[:, 1], torch.tensor([-2.0, 60.0], dtype=torch.float64))
    assert float(wrap_angle(torch.tensor(181.0))) == pytest.approx(1.0)
    # theta in [0, 90] has no period: a 95-deg error is 95, not -85.
    assert pose_errors(torch.tensor([[95.0, 0, 0, 0, 0]]), torch.zeros(1, 5))[0, 0] == 95.0


def test_a_cup_without_truth_is_left_out_of_the_pose_and_ellipse_losses():
    """A NaN truth row (a missing cup) is left out as an invalid one: it had made each loss,
    and every gradient of its step, NaN."""
    pred = torch.tensor([[20.0, 10.0, 1.0, 2.0, 300.0], [30.0, 5.0, 0.0, 0.0, 250.0]],
                        dtype=torch.float64, requires_grad=True)
    truth = torch.tensor([[21.0, 10.0, 1.0, 2.0, 300.0], [math.nan] * 5], dtype=torch.float64)
    valid = torch.tensor([True, True])
    loss = pose_loss(pred, truth, valid)
    assert torch.equal(loss, pose_loss(pred[:1], truth[:1], valid[:1]))
    loss.backward()
    assert torch.isfinite(pred.grad).all() and pred.grad[1].abs().sum() == 0
    circle = torch.diag(torch.tensor([1.0, 1.0, -100.0], dtype=torch.float64))[None].repeat(2, 1, 1)
    t = torch.linspace(0, 6.0, 16, dtype=torch.float64)
    rim = torch.stack([10.5 * torch.cos(t), 10.5 * torch.sin(t)], -1)[None].repeat(2, 1, 1)
    rim[1, 3] = math.nan
    scale = torch.ones(2, dtype=torch.float64)
    assert torch.equal(ellipse_loss(circle, rim, scale, valid),
                       ellipse_loss(circle[:1], rim[:1], scale[:1], valid[:1]))
    assert torch.isfinite(ellipse_loss(circle, rim, scale, valid))



def test_the_log_says_what_share_of_cups_was_posed():
    """With no cup posed the pose loss reads 0, as for a perfect fit: the share posed and
    the NaN MAEs say which it is."""
    truth = torch.tensor([[20.0, 10.0, 1.0, 2.0, 300.0]] * 4, dtype=torch.float64)
    pred = truth + torch.tensor([2.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    some = SimpleNamespace(pose=pred, valid=torch.tensor([True, False, True, False]))
    logged = _pose_maes(some, truth)
    assert float(logged["posed"]) == 0.5 and float(logged["mae_theta"]) == pytest.approx(2.0)
    none = SimpleNamespace(pose=pred, valid=torch.zeros(4, dtype=torch.bool))
    logged = _pose_maes(none, truth)
    assert float(pose_loss(pred, truth, none.valid)) == 0.0 and float(logged["posed"]) == 0.0
    assert math.isnan(float(logged["mae_theta"]))

def test_pose_loss_divides_each_error_by_its_target_mae():
    """Huber (quadratic within 1) of errors in target MAEs (1 deg, 1 deg, 1 mm, 1 mm, 8 mm),
    averaged over the five components: an 8 mm error in h weighs as 1 mm in k."""
    truth = torch.tensor([[20.0, 10.0, 1.0, 2.0, 300.0]], dtype=torch.float64)
    valid = torch.tensor([True])
    for error, expected in (([0.5, 0, 0, 0, 0], 0.5 * 0.5**2 / 5),  # theta, quadratic
                            ([0, 0, 0, 0, 4.0], 0.5 * 0.5**2 / 5),  # h: 4 mm is half a target
                            ([0, 0, 2.0, 0, 0], (2.0 - 0.5) / 5),  # k: linear beyond 1
                            ([0, 0, 0, 0, 16.0], (2.0 - 0.5) / 5)):
        pred = truth + torch.tensor([error], dtype=torch.float64)
        assert float(pose_loss(pred, truth, valid)) == pytest.approx(expected, rel=1e-12)


def test_ellipse_loss_is_the_huber_of_sampson_distances_in_crop_pixels():
    """A circle of radius 10 px and true rim points at 10.5 px: Sampson distance
    (r^2 - 100) / (2 r) = 0.488 image px, 0.244 crop px at 2 image px a crop px."""
    circle = torch.diag(torch.tensor([1.0, 1.0, -100.0], dtype=torch.float64))[None]
    t = torch.linspace(0, 6.0, 16, dtype=torch.float64)
    rim = torch.stack([10.5 * torch.cos(t), 10.5 * torch.sin(t)], -1)[None]
    distance = (10.5**2 - 100) / (2 * 10.5) / 2.0
    loss = ellipse_loss(circle, rim, torch.tensor([2.0], dtype=torch.float64),
                        torch.tensor([True]))
    assert float(loss) == pytest.approx(0.5 * distance**2, rel=1e-12)


def test_segmentation_loss_vanishes_on_sure_right_logits_and_not_on_wrong_ones():
    target = torch.zeros(2, 1, 16, 16)
    target[:, :, 4:12, 5:10] = 1.0
    sure = 30.0 * (2 * target - 1)
    assert float(segmentation_loss(sure, target)) < 1e-6  # BCE and Dice both at their floor
    # All wrong: BCE ~30, Dice 1 - 1 / (40 + 216 + 1) of its smoothing term.
    wrong = float(segmentation_loss(-sure, target))
    assert wrong == pytest.approx(30.0 + 1 - 1 / (40 + 216 + 1), abs=1e-5)


def test_schedule_ramps_in():
    assert ramp(9, 10, 5) == 0.0 and ramp(10, 10, 5) == pytest.approx(0.2)
    assert ramp(100, 10, 5) == 1.0


def test_jitter_keeps_axes_ordered_and_skips_missing_cups():
    torch.manual_seed(0)
    ellipse = torch.tensor([[[100.0, 120.0, 40.0, 39.0, 10.0], [math.nan] * 5]]).double()
    out = jittered_ellipses(ellipse.expand(64, 2, 5), torch.tensor([[True, False]]).expand(64, 2),
                            0.5, 0.15, 0.3, 0.05, 0.1, 8.0, 0.2)
    assert (out[:, 0, 2] >= out[:, 0, 3]).all() and torch.isnan(out[:, 1]).all()


def _metrics(root: Path) -> list[dict]:
    (path,) = root.glob("runs/smoke/csv/version_*/metrics.csv")
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    """One run of configs/smoke.yaml in a scratch directory."""
    root = tmp_path_factory.mktemp("smoke")
    cwd = Path.cwd()
    try:
        import os

        os.chdir(root)
        main(["fit", "-c", str(SMOKE), "--data.synth", str(ROOT / "configs/synth_smoke.yaml")])
    finally:
        os.chdir(cwd)
    return root


def test_a_resumed_run_goes_on_as_the_stopped_one_would_have(tmp_path, monkeypatch):
    """Six smoke steps at once, and three, then three more resumed from the checkpoint: the
    same images (the streams had started again at their first) and the same losses (the
    random draws had started again too, and the validation after the checkpoint's step,
    which the resumed run does not repeat, had drawn none of them)."""
    def run(name: str, *extra: str) -> list[dict]:
        (tmp_path / name).mkdir()
        monkeypatch.chdir(tmp_path / name)
        main(["fit", "-c", str(SMOKE), "--data.synth", str(ROOT / "configs/synth_smoke.yaml"),
              "--trainer.max_steps", "6", "--trainer.val_check_interval", "3", *extra])
        return [r for r in _metrics(tmp_path / name) if r.get("train/loss")]

    every = tmp_path / "every3"
    whole = run("whole", "--trainer.callbacks+=ModelCheckpoint",
                f"--trainer.callbacks.dirpath={every}",
                "--trainer.callbacks.every_n_train_steps=3", "--trainer.callbacks.save_top_k=-1")
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        resumed = run("resumed", "--ckpt_path", str(every / "epoch=0-step=3.ckpt"))
    # Nothing given was dropped, and the schedule's steps are the run's.
    assert not [w for w in said if "are not used" in str(w.message) or "cosine" in str(w.message)]
    assert [r["step"] for r in resumed] == ["3", "4", "5"]
    assert [r["train/loss"] for r in resumed] == [r["train/loss"] for r in whole[3:]]


def test_a_resume_says_which_given_settings_it_drops_and_holds_the_rate_past_its_cosine(
        tmp_path, monkeypatch):
    """Resumed with another learning rate and network width, and twice the steps: both are
    named as not used (Lightning takes the checkpoint's), and the rate stays at its floor
    (lr / 20) past the checkpoint's cosine, where torch's cosine rose again."""
    monkeypatch.chdir(tmp_path)
    smoke = ["fit", "-c", str(SMOKE), "--data.synth", str(ROOT / "configs/synth_smoke.yaml"),
             "--trainer.limit_val_batches", "0"]
    first, second = tmp_path / "first.safetensors", tmp_path / "second.safetensors"
    main([*smoke, "--trainer.max_steps", "3", "--model.export_path", str(first)])
    (tmp_path / "runs").rename(tmp_path / "first")
    exported = first.read_bytes()
    with pytest.warns(UserWarning) as said:
        main([*smoke, "--trainer.max_steps", "6", "--model.lr", "0.01",
              "--model.model.rim_channels", "8", "--model.model.crop_size", "96",
              "--trainer.callbacks+=LearningRateMonitor", "--model.export_path", str(second),
              "--ckpt_path", str(tmp_path / "first/smoke/checkpoints/last.ckpt")])
    # The export goes where this command says (the checkpoint's path had overwritten the
    # first run's), and is the resumed model.
    assert first.read_bytes() == exported and second.is_file()
    assert any(not torch.equal(a, b) for a, b in zip(load_model(first).state_dict().values(),
                                                     load_model(second).state_dict().values(),
                                                     strict=True))
    text = " ".join(str(w.message) for w in said)
    assert "--model.lr 0.01 (the checkpoint's: 0.003)" in text
    assert "--model.model.rim_channels '8'" in text
    assert "crop_size" not in text  # given as text, '96' is the checkpoint's 96
    assert "cosine runs over 3 steps: it holds its floor" in text
    rates = [float(r["lr-AdamW"]) for r in _metrics(tmp_path) if r.get("lr-AdamW")]
    assert len(rates) == 3 and rates == pytest.approx([0.003 / 20] * 3, rel=1e-12)
    # Where the command names none, where the checkpoint's run wrote it.
    (tmp_path / "runs").rename(tmp_path / "second")
    main([*smoke, "--trainer.max_steps", "4", "--model.export_path", "null",
          "--ckpt_path", str(tmp_path / "first/smoke/checkpoints/last.ckpt")])
    assert first.read_bytes() != exported


def test_a_resume_takes_a_checkpoint_file_not_a_keyword(tmp_path, monkeypatch, capsys):
    """Lightning takes a checkpoint's settings for a file only: given `last`, it had built
    the module from the given settings and restored the checkpoint's schedule beside them."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stopped:
        main(["fit", "-c", str(SMOKE), "--ckpt_path", "last"])
    assert stopped.value.code == 2
    assert "--ckpt_path last: no such checkpoint file" in capsys.readouterr().err


@pytest.mark.parametrize(("flags", "message"), [
    (["--model.lr", "-0.1"], "lr must be a learning rate > 0, got -0.1"),
    (["--data.batch_size", "0"], "batch_size must be >= 1, got 0"),
    (["--data.synth", "nope.yaml"], "synthesis config not found: nope.yaml"),
    (["--model.model.crop_sise", "96"], "unknown CupNet config keys: ['crop_sise']"),
    (["--model.model.n_rays", "4"], "n_rays must be >= 5, got 4"),
    (["--model.model.refine_passes", "0"], "refine_passes must be >= 1, got 0"),
    (["--model.model.encoder", "resnet19"], "unknown encoder 'resnet19'"),
    (["--model.model.decoder_channels", "[8, 0]"], "decoder_channels must be one or more"),
    (["--model.pose_weight", "-1"], "pose_weight must be >= 0, got -1"),
    (["--model.weight_decay", "-1"], "weight_decay must be >= 0, got -1"),
    (["--model.coarse_fraction", "1.5"], "coarse_fraction must be a fraction in [0, 1], got 1.5"),
    (["--model.crops_per_cup", "0"], "crops_per_cup must be >= 1, got 0"),
    (["--model.init_weights", str(DEFAULT_CHECKPOINT)],
     "does not fit this model: 64 tensors of another shape, in ['locator', 'refiner']"),
])
def test_a_setting_the_run_cannot_take_is_an_argument_error(tmp_path, monkeypatch, capsys,
                                                           flags, message):
    """Each had ended in a traceback once the model, loggers and trainer were made (a
    negative rate at AdamW's first step, a batch of 0 in the collation)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stopped:
        main(["fit", "-c", str(SMOKE), "--data.synth", str(ROOT / "configs/synth_smoke.yaml"),
              *flags])
    assert stopped.value.code == 2
    assert message in capsys.readouterr().err


def test_a_resume_from_a_file_that_is_no_training_checkpoint_is_named(tmp_path, monkeypatch,
                                                                     capsys):
    """A file cut short, an export, a plain state dict: Lightning had failed in a
    traceback, one without the file's name."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "cut.ckpt").write_bytes(b"PK\x03\x04" + bytes(200))
    torch.save(load_model(DEFAULT_CHECKPOINT).state_dict(), tmp_path / "plain.pt")
    for path, message in ((tmp_path / "cut.ckpt", "not a readable checkpoint (corrupt"),
                          (DEFAULT_CHECKPOINT, "not a checkpoint of cupnet train"),
                          (tmp_path / "plain.pt", "not a checkpoint of cupnet train")):
        with pytest.raises(SystemExit) as stopped:
            main(["fit", "-c", str(SMOKE), "--ckpt_path", str(path)])
        assert stopped.value.code == 2
        err = capsys.readouterr().err
        assert f"--ckpt_path {path}: {message}" in err and "--model.init_weights" in err


def test_a_second_run_into_the_same_folder_leaves_its_own_last_checkpoint(tmp_path,
                                                                         monkeypatch):
    """Lightning's version counter had written the second run's as last-v1.ckpt beside the
    first's last.ckpt, which the documented resume command then resumed."""
    monkeypatch.chdir(tmp_path)
    smoke = ["fit", "-c", str(SMOKE), "--data.synth", str(ROOT / "configs/synth_smoke.yaml"),
             "--trainer.limit_val_batches", "0"]
    main([*smoke, "--trainer.max_steps", "3"])
    main([*smoke, "--trainer.max_steps", "2"])
    folder = tmp_path / "runs/smoke/checkpoints"
    assert sorted(p.name for p in folder.glob("last*")) == ["last.ckpt"]
    assert torch.load(folder / "last.ckpt", weights_only=True)["global_step"] == 2


def test_a_resume_of_a_run_that_used_its_max_time_says_no_step_will_run(tmp_path,
                                                                         monkeypatch):
    monkeypatch.chdir(tmp_path)
    smoke = ["fit", "-c", str(SMOKE), "--data.synth", str(ROOT / "configs/synth_smoke.yaml"),
             "--trainer.limit_val_batches", "0", "--trainer.max_time", "00:00:00:01"]
    main(smoke)  # stops on its time after its first step
    with pytest.warns(UserWarning, match="had used its max_time .* no step will run"):
        main([*smoke, "--ckpt_path", "runs/smoke/checkpoints/last.ckpt"])


def test_the_rate_follows_torchs_cosine_to_its_floor_and_stays_there():
    def rates(schedule: type, steps: int) -> list[float]:
        optimizer = torch.optim.AdamW([torch.nn.Parameter(torch.zeros(1))], lr=2e-3)
        scheduler = schedule(optimizer, 50, 1e-4)
        out = []
        for _ in range(steps):
            optimizer.step()
            scheduler.step()
            out.append(optimizer.param_groups[0]["lr"])
        return out

    ours, torchs = rates(CosineToFloor, 80), rates(torch.optim.lr_scheduler.CosineAnnealingLR, 80)
    assert ours[:50] == torchs[:50]  # bit for bit: the shipped recipes' rates
    assert ours[49:] == [1e-4] * 31 and torchs[55] > 1.1e-4


def test_smoke_config_loss_decreases(smoke_run):
    rows = [r for r in _metrics(smoke_run) if r.get("train/seg_crop")]
    seg = [float(r["train/seg_crop"]) + float(r["train/seg_locator"]) for r in rows]
    assert len(seg) >= 10
    assert sum(seg[-3:]) / 3 < sum(seg[:3]) / 3
    # validation ran the full detect path and scored it
    assert any(r.get("val/score") for r in _metrics(smoke_run))


def test_smoke_checkpoints_round_trip(smoke_run):
    exported = smoke_run / "runs/smoke/cupnet.safetensors"
    lightning_ckpt = smoke_run / "runs/smoke/checkpoints/last.ckpt"
    a, b = load_model(exported), load_model(lightning_ckpt)  # both weights-only
    x = torch.rand(2, 1, 96, 96)
    with torch.no_grad():
        assert torch.equal(a.refiner(x), b.refiner(x))
        assert torch.equal(a.locator(x), b.locator(x))


def _first_losses(steps: int = 2) -> tuple[list[torch.Tensor], list[float]]:
    L.seed_everything(0)
    data = CupDataModule(synth=str(ROOT / "configs/synth_smoke.yaml"), batch_size=2,
                         image_sizes=[128, 160])
    module = CupNetModule(model={"decoder_channels": [16, 16, 8, 8, 8], "locator_size": 64,
                                 "crop_size": 64, "n_rays": 16},
                          ellipse_start=0, pose_start=0, ramp_steps=1)
    images, losses = [], []
    for step, batch in zip(range(steps), iter(data.train_dataset()), strict=False):
        images.append(batch["image"])
        losses.append(float(module.losses(batch, step)["loss"]))
    return images, losses


def test_same_seed_same_batches_and_losses():
    images_a, losses_a = _first_losses()
    images_b, losses_b = _first_losses()
    assert [i.shape[-1] for i in images_a] == [128, 160]  # sizes taken in turn
    assert all(torch.equal(x, y) for x, y in zip(images_a, images_b, strict=True))
    assert losses_a == losses_b and all(math.isfinite(v) for v in losses_a)


def test_a_validation_draws_nothing_from_torchs_global_generator():
    """Each validation's iterator takes its base seed from the loader's own generator: from
    the global one it would shift every later training step's random draws (the jitter of
    the crops), so a run that validates more often would train otherwise."""
    loader = CupDataModule(synth={"image_size": [64, 64], "supersample": 1}, batch_size=1,
                           val_length=1).val_dataloader()
    torch.manual_seed(0)
    next(iter(loader))
    after_validation = torch.rand(3)
    torch.manual_seed(0)
    assert torch.equal(after_validation, torch.rand(3))


def test_a_list_of_synthesis_configs_is_mixed_batch_by_batch():
    thin = {"image_size": [128, 128], "supersample": 1, "theta_deg": [0.0, 1.0]}
    open_ = {**thin, "theta_deg": [49.0, 50.0]}
    mixed = CupDataModule(synth=[thin, open_], batch_size=2, image_sizes=[96, 128])
    batches = [b for _, b in zip(range(4), mixed.train_dataset(), strict=False)]
    # Streams in order (configs, sizes within each): thin 96, thin 128, open 96, open 128.
    assert [b["image"].shape[-1] for b in batches] == [96, 128, 96, 128]
    # Each stream has a seed of its own: a config's sizes do not repeat each other's cups.
    assert not torch.equal(batches[0]["pose"], batches[1]["pose"])
    for b, low in zip(batches, (0, 0, 49, 49), strict=True):
        theta = b["pose"][..., 0][b["cup_valid"].bool()]
        assert ((theta >= low) & (theta <= low + 1)).all()
    # A single config keeps its streams' seeds: the thin stream alone starts the same.
    alone = next(iter(CupDataModule(synth=thin, batch_size=2, image_sizes=[96, 128])
                      .train_dataset()))
    assert torch.equal(alone["image"], batches[0]["image"])


RIM_MODEL = {"decoder_channels": [16, 16, 8, 8, 8], "locator_size": 64, "crop_size": 64,
             "n_rays": 16, "rim_passes": 1, "rim_points": 32, "rim_samples": 32,
             "rim_channels": 8}


def _smoke_batch() -> dict:
    L.seed_everything(3)
    data = CupDataModule(synth=str(ROOT / "configs/synth_smoke.yaml"), batch_size=2,
                         image_sizes=[160])
    return next(iter(data.train_dataset()))


def test_rim_only_training_moves_the_rim_network_alone():
    batch = _smoke_batch()
    module = CupNetModule(model=RIM_MODEL, rim_only=True, rim_copies=2, rim_refiner_starts=0.5)
    optimizer = torch.optim.Adam((p for p in module.parameters() if p.requires_grad), lr=3e-3)
    losses = []
    for _ in range(25):
        torch.manual_seed(0)  # the same jittered starts each step
        terms = module.losses(batch, 0)
        assert set(terms) >= {"rim", "pose", "loss"} and math.isfinite(terms["loss"].item())
        optimizer.zero_grad()
        terms["loss"].backward()
        optimizer.step()
        losses.append(terms["rim"].item())
    assert losses[-1] < losses[0]


def test_a_pose_loss_that_reaches_no_trained_network_is_warned_of():
    """With a rim stage the pose comes from the rim network's landmarks alone: frozen, the
    pose loss trains nothing (a 'refiner-only' stage's pose_weight had done nothing
    silently); the rim network trained, it gets the gradient."""
    batch = _smoke_batch()
    frozen = CupNetModule(model=RIM_MODEL, freeze=("locator", "rim"), pose_start=0,
                          ramp_steps=1)
    with pytest.warns(UserWarning, match="the pose loss reaches no network this run trains"):
        terms = frozen.losses(batch, 10)
    assert not terms["pose"].requires_grad
    trained = CupNetModule(model=RIM_MODEL, freeze=("locator",), pose_start=0, ramp_steps=1)
    trained.losses(batch, 10)["pose"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0
               for p in trained.model.rim.parameters())
    assert all(p.grad is None for p in trained.model.refiner.parameters())


def _fit_moves_only(module: CupNetModule, trained: str, tmp_path: Path) -> None:
    """Three steps of Lightning's own loop (which decides the modules' modes): the weights
    and BatchNorm statistics of every network but ``trained`` must not move; its must."""
    data = CupDataModule(synth=str(ROOT / "configs/synth_smoke.yaml"), batch_size=2,
                         image_sizes=[160], val_length=1, num_workers=0)
    before = {k: v.clone() for k, v in module.model.state_dict().items()}
    trainer = L.Trainer(max_steps=3, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0, default_root_dir=tmp_path)
    trainer.fit(module, datamodule=data)
    after = module.model.state_dict()
    moved = {k for k, v in before.items() if not torch.equal(v, after[k])}
    assert moved and all(k.startswith(trained + ".") for k in moved)


def test_rim_only_fit_leaves_the_frozen_unets_untouched(tmp_path):
    # With the refiner run on every start.
    module = CupNetModule(model=RIM_MODEL, rim_only=True, rim_copies=1, rim_refiner_starts=1.0)
    _fit_moves_only(module, "rim", tmp_path)


def test_freeze_trains_the_other_networks_alone(tmp_path):
    # A refiner-only stage: the locator still runs in every forward, the rim stage on the
    # refiner's fits; neither may move.
    module = CupNetModule(model=RIM_MODEL, freeze=("locator", "rim"), ellipse_start=0,
                          pose_start=0, ramp_steps=1)
    _fit_moves_only(module, "refiner", tmp_path)
    with pytest.raises(ValueError, match="unknown networks"):
        CupNetModule(model=RIM_MODEL, freeze=("encoder",))


def test_locator_targets_widen_thin_openings():
    batch = _smoke_batch()
    plain, widened = (CupNetModule(locator_only=True, locator_min_ratio=r) for r in (0.0, 0.3))
    _, letterbox = plain.model.letterbox(list(batch["image"]))
    mask = plain.locator_targets(batch, letterbox)
    # From the ellipses (a ratio no opening is under): the synthesised mask's coverage.
    drawn = CupNetModule(locator_only=True, locator_min_ratio=1e-6).locator_targets(batch,
                                                                                  letterbox)
    assert torch.allclose(drawn.sum((1, 2, 3)), mask.sum((1, 2, 3)), rtol=0.01)
    # A nearly edge-on opening is drawn 0.3 a wide: area pi a (0.3 a) in the view.
    thin = {**batch, "ellipse": batch["ellipse"].clone()}
    thin["ellipse"][..., 3] = 0.02 * thin["ellipse"][..., 2]
    target = widened.locator_targets(thin, letterbox)
    scale = letterbox[:, 0, 0].double()  # image px per view px
    valid = thin["cup_valid"].bool()
    area = (math.pi * 0.3 * (thin["ellipse"][..., 2].double() / scale[:, None]) ** 2
            * valid).sum(1)
    assert torch.allclose(target.sum((1, 2, 3)).double(), area, rtol=0.02)


def test_locator_stage_sees_an_oblong_image_through_the_windows_detect_shows_it(monkeypatch):
    L.seed_everything(5)
    data = CupDataModule(synth=str(ROOT / "configs/synth_smoke.yaml"), batch_size=8,
                         image_sizes=[[240, 160]])
    batch = next(iter(data.train_dataset()))
    assert batch["image"].shape[-2:] == (160, 240)
    module = CupNetModule(model=RIM_MODEL, locator_only=True)
    seen = []
    monkeypatch.setattr("train.module.segmentation_loss",
                        lambda logits, target: seen.append(target) or logits.mean())
    module.locator_losses(batch)
    # The inference's windows (two, one at each end) of each image, drawn at random, and
    # each view's target the image's openings in that window.
    windows, places = square_windows(160, 240, 64)
    assert places[:, 0].tolist() == [0, 32]
    masks = torch.stack([resample_batch(batch["mask"], windows[j].expand(8, 2, 3), 64)
                         for j in range(2)], 1)  # (B, window, 1, S, S)
    apart = [k for k in range(8) if not torch.allclose(masks[k, 0], masks[k, 1])]
    assert len(apart) >= 6  # images whose cups the two windows show differently
    drawn = [[j for j in range(2) if torch.allclose(seen[0][k], masks[k, j])] for k in apart]
    assert all(len(j) == 1 for j in drawn)  # each target is one window's
    assert {j[0] for j in drawn} == {0, 1}


def test_locator_only_fit_trains_the_locator_alone(tmp_path):
    module = CupNetModule(model=RIM_MODEL, locator_only=True, locator_dark_views=0.5)
    _fit_moves_only(module, "locator", tmp_path)


def test_coarse_rim_starts_perturb_towards_a_round_outline():
    truth = torch.tensor([[100.0, 80.0, 60.0, 3.0, 30.0], [50.0, 60.0, 40.0, 30.0, 100.0]],
                         dtype=torch.float64).repeat(500, 1)
    assert torch.equal(coarse_rim_starts(truth, 0.0, head=0.0), truth)  # no jitter: the truth
    torch.manual_seed(0)
    start = coarse_rim_starts(truth, 1.0, head=0.0)
    assert (start[:, 3] <= start[:, 2]).all() and (start[:, 3] >= 0.5).all()
    thin = start[0::2]
    # A thin rim is read as anything from itself to a round outline, rarely thinner.
    assert thin[:, 3].max() > 0.8 * thin[:, 2].min() and (thin[:, 3] > 3.0).float().mean() > 0.7
    assert (start[:, :2] - truth[:, :2]).abs().max() < 0.06 * 60 * 5
    # Femoral heads: round, half to all of the rim's size, centred near it.
    heads = coarse_rim_starts(truth, 1.0, head=1.0)
    relative = heads[:, 2] / truth[:, 2]
    assert relative.min() >= 0.5 and relative.max() <= 1.0 and relative.std() > 0.1
    assert (heads[:, 3] >= 0.8 * heads[:, 2]).all() and (heads[:, 3] <= heads[:, 2]).all()
    assert (heads[:, :2] - truth[:, :2]).abs().max() < 0.05 * 60 * 5


def test_far_rim_starts_are_discs_or_thin_ellipses_at_any_angle():
    truth = torch.tensor([[100.0, 80.0, 60.0, 6.0, 30.0]], dtype=torch.float64).repeat(2000, 1)
    torch.manual_seed(0)
    start = far_rim_starts(truth, 0.15)
    ratio = start[:, 3] / start[:, 2]
    thin, disc = ratio < 0.2, ratio >= 0.8
    assert (thin | disc).all() and 0.45 < thin.float().mean() < 0.55
    assert torch.allclose(ratio[thin], torch.full_like(ratio[thin], 0.15))
    assert (start[disc, 2] >= 30.0).all() and (start[disc, 2] <= 60.0).all()  # heads
    angles = start[thin, 4]
    assert angles.min() < 10 and angles.max() > 170 and 60 < angles.median() < 120
    assert (start[:, :2] - truth[:, :2]).abs().max() < 0.05 * 60 * 5


def test_coarse_rim_only_fit_trains_the_coarse_rim_network_alone(tmp_path):
    fine = CupNetModule(model=RIM_MODEL).model
    weights = tmp_path / "fine.safetensors"
    save_model(fine, weights)
    module = CupNetModule(model={**RIM_MODEL, "coarse_rim_passes": 1}, rim_only=True,
                          rim_stage="coarse", rim_copies=1, rim_refiner_starts=0.5,
                          init_weights=str(weights))
    state = module.model.state_dict()
    assert all(torch.equal(v, state[k]) for k, v in fine.state_dict().items())
    _fit_moves_only(module, "coarse_rim", tmp_path)
    with pytest.raises(ValueError, match="rim_stage"):
        CupNetModule(model=RIM_MODEL, rim_only=True, rim_stage="coarse")


def test_full_training_of_a_rim_model_adds_the_rim_loss():
    batch = _smoke_batch()
    module = CupNetModule(model=RIM_MODEL, ellipse_start=0, pose_start=0, ramp_steps=1)
    terms = module.losses(batch, 0)
    assert math.isfinite(terms["rim"].item()) and math.isfinite(terms["loss"].item())
    # The ellipse loss is the refiner's (its landmarks frame the rim stage and are detect's
    # fallback); the rim loss is the rim network's alone.
    terms["ellipse"].backward(retain_graph=True)
    head = module.model.refiner.segmentation_head[0].weight
    assert head.grad is not None and head.grad.abs().sum() > 0
    assert all(p.grad is None for p in module.model.rim.parameters())
    terms["rim"].backward()
    grads = [p.grad for p in module.model.rim.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_before_their_start_the_ellipse_and_pose_losses_weigh_nothing():
    """The schedule starts on segmentation (and the rim's landmarks) and brings in the
    ellipse and pose losses: before their start the total leaves them out, though the pose
    loss is still computed for the logs."""
    batch = _smoke_batch()
    module = CupNetModule(model=RIM_MODEL, ellipse_start=5, pose_start=5, ramp_steps=1)
    hp = module.hparams
    terms = module.losses(batch, 0)
    assert float(terms["pose"].detach()) > 0
    expected = (hp.locator_weight * terms["seg_locator"] + terms["seg_crop"]
                + hp.rim_weight * terms["rim"])
    torch.testing.assert_close(terms["loss"], expected.float())
    on = module.losses(batch, 5)
    with_pose = (hp.locator_weight * on["seg_locator"] + on["seg_crop"] + hp.rim_weight * on["rim"]
                 + hp.ellipse_weight * on["ellipse"] + hp.pose_weight * on["pose"])
    torch.testing.assert_close(on["loss"], with_pose.float())


def test_distill_loss_is_zero_on_the_teacher_and_its_gradient_is_the_softmax_gap():
    torch.manual_seed(0)
    logits, log_sigma = torch.randn(3, 16, 10, dtype=torch.float64), torch.randn(3, 10)
    assert distill_loss((logits, log_sigma), (logits, log_sigma)).item() == pytest.approx(0.0)
    teacher = (torch.randn(3, 16, 10), torch.randn(3, 10))
    student = logits.float().requires_grad_()
    distill_loss((student, log_sigma), teacher).backward()
    # d/ds of the mean over K n columns of KL(t || softmax(s)): (softmax(s) - t) / (K n)
    gap = (torch.softmax(student.detach(), 1) - torch.softmax(teacher[0], 1)) / 30
    assert torch.allclose(student.grad, gap, atol=1e-6)


def test_a_narrower_rim_network_is_taught_by_a_wider_one(tmp_path):
    """init_weights of a wider rim network: every other network's weights load, the rim
    network starts afresh; rim_teacher adds the distillation term, and it falls as the
    narrow network learns to match the teacher on the same strips."""
    wide = CupNetModule(model={**RIM_MODEL, "rim_channels": 12, "coarse_rim_passes": 1}).model
    weights = tmp_path / "wide.safetensors"
    save_model(wide, weights)
    narrow = {**RIM_MODEL, "rim_channels": 4, "coarse_rim_channels": 12, "coarse_rim_passes": 1}
    with pytest.warns(UserWarning, match=r"holds no \['rim'\] this model can take .*afresh$"):
        module = CupNetModule(model=narrow, rim_only=True, rim_copies=2,
                              init_weights=str(weights), rim_teacher=str(weights))
    state = module.model.state_dict()
    loaded = {k for k, v in wide.state_dict().items() if not k.startswith("rim.")}
    assert all(torch.equal(wide.state_dict()[k], state[k]) for k in loaded)
    assert module.model.rim.offset_head.in_channels == 4
    assert not any(k.startswith("_rim_teacher") for k in module.state_dict())
    batch = _smoke_batch()
    optimizer = torch.optim.Adam((p for p in module.parameters() if p.requires_grad), lr=3e-3)
    distill = []
    for _ in range(15):
        torch.manual_seed(0)  # the same jittered starts, so the same strips, each step
        terms = module.losses(batch, 0)
        optimizer.zero_grad()
        terms["loss"].backward()
        optimizer.step()
        distill.append(terms["distill"].item())
    assert distill[-1] < 0.7 * distill[0]
    with pytest.raises(ValueError, match="rim_teacher"):
        CupNetModule(model=narrow, rim_teacher=str(weights))
    # A network started afresh that the run does not train is named: its export holds it
    # untrained (the coarse one here, frozen by a fine rim-only run).
    with pytest.warns(UserWarning, match=r"\['coarse_rim'\] are not trained this run"):
        CupNetModule(model={**narrow, "coarse_rim_channels": 8}, rim_only=True,
                     init_weights=str(weights))
    # A network this model has not built is the cause named first.
    with pytest.raises(ValueError, match=r"networks this model has not built \['coarse_rim'\]"):
        CupNetModule(model={**RIM_MODEL, "rim_channels": 12}, init_weights=str(weights))


def _make_rules() -> dict[str, tuple[list[str], list[list[str]]]]:
    """Each Makefile rule: target -> (prerequisites, words of each recipe command, a
    backslash-continued command joined into one)."""
    rules: dict[str, tuple[list[str], list[list[str]]]] = {}
    target = None
    for line in (ROOT / "Makefile").read_text().replace("\\\n", " ").splitlines():
        if line.startswith("\t") and target is not None:
            rules[target][1].append(line.split())
        elif ":" in line and not line.startswith(("#", ".", "\t")) and ":=" not in line:
            target, prerequisites = line.split(":", 1)
            rules[target] = (prerequisites.split(), [])
        else:
            target = None
    return rules


def _make_variable(name: str) -> list[str]:
    """The words of the Makefile's ``name := ...``."""
    lines = (ROOT / "Makefile").read_text().splitlines()
    return next(x.split(":=", 1)[1].split() for x in lines if x.startswith(f"{name} :="))


def _stage_config(words: list[str], capsys: pytest.CaptureFixture[str]) -> dict:
    """The whole config of a Makefile training stage, ``$(TRAIN) -c ... $(HOUR_ARGS)``, as
    ``python -m train fit`` parses it (from the checkout's root)."""
    train = _make_variable("TRAIN")
    assert words[0] == "$(TRAIN)" and words[-1] == "$(HOUR_ARGS)"
    with pytest.raises(SystemExit):
        main([*train[train.index("fit"):], *words[1:-1], "--print_config"])
    return yaml.safe_load(capsys.readouterr().out)


def test_hour_recipe_runs_two_chains_then_merges_within_the_hour(capsys, monkeypatch):
    """``make train-hour``: two chains of one-thread training processes run side by side
    (``make -j2``); each stage parses and starts from the export of a stage it waits for;
    the merge takes the rim networks of chain B into chain A's export, the last stage trains
    on from the merged model; the time caps on the longest path sum to at most 58.5 minutes
    (the hour less the processes' start-up and the merge), and the shipped inference
    settings land beside the last stage's export."""
    monkeypatch.chdir(ROOT)  # the Makefile's paths are relative to the checkout
    rules = _make_rules()

    def config(words: list[str]) -> dict:
        return _stage_config(words, capsys)

    def minutes(cfg: dict) -> float:
        days, hours, mins, secs = map(int, cfg["trainer"]["max_time"].split(":"))
        return days * 1440 + hours * 60 + mins + secs / 60

    chains = ("hour-unet", "hour-rim", "hour-locator", "hour-coarse")
    stages = {name: config(rules[name][1][0]) for name in chains}
    assert all(stages[name]["model"]["torch_threads"] == 1 for name in chains)
    export = {name: stages[name]["model"]["export_path"] for name in chains}
    assert stages["hour-unet"]["model"]["init_weights"] is None
    assert stages["hour-rim"]["model"]["init_weights"] is None
    for name in ("hour-locator", "hour-coarse"):
        assert stages[name]["model"]["init_weights"] == export["hour-unet"]
        assert "hour-unet" in rules[name][0]
    # One chain a core: the coarse rim waits for the fine rim, so two processes at most.
    assert rules["hour-coarse"][0] == ["hour-unet", "hour-rim"]

    merge = rules["hour-merged"]
    assert merge[0] == ["hour-locator", "hour-coarse"]
    words = merge[1][0]
    assert words[1:4] == ["-m", "train.merge", export["hour-locator"]]
    takes = [words[i + 1] for i, word in enumerate(words) if word == "--take"]
    assert takes == [f"rim={export['hour-rim']}", f"coarse_rim={export['hour-coarse']}"]
    merged_path = words[words.index("--out") + 1]

    recipe = [words for words in rules["train-hour"][1] if words[0] != "@echo"]
    assert recipe[0] == ["$(MAKE)", "-j2", "-O", "hour-merged"]
    final = config(recipe[1])
    assert final["model"]["init_weights"] == merged_path
    assert final["model"]["locator_only"]
    longest = (max(minutes(stages["hour-unet"]), minutes(stages["hour-rim"]))
               + max(minutes(stages["hour-locator"]), minutes(stages["hour-coarse"]))
               + minutes(final))
    assert longest <= 58.5
    beside = Path(final["model"]["export_path"]).with_suffix(".json")
    assert beside == Path("runs/hour/cupnet.json")
    assert recipe[2] == ["cp", "cupnet/assets/cupnet_default.json", str(beside)]


def test_merge_takes_the_named_networks_and_keeps_the_rest(tmp_path, capsys):
    """``python -m train.merge``: the output holds the donors' rim networks and the base's
    U-Nets, tensor for tensor; a missing network or another width is a named error."""
    model = {**RIM_MODEL, "coarse_rim_passes": 1}
    torch.manual_seed(0)
    base, fine, coarse = (CupNetModule(model=model).model for _ in range(3))
    paths = {}
    for name, net in (("base", base), ("fine", fine), ("coarse", coarse)):
        paths[name] = save_model(net, tmp_path / f"{name}.safetensors")
    out = merge_main([str(paths["base"]), "--take", f"rim={paths['fine']}",
                      "--take", f"coarse_rim={paths['coarse']}",
                      "--out", str(tmp_path / "merged.safetensors")])
    state = load_model(out).state_dict()
    donor = {"rim": fine, "coarse_rim": coarse}
    for key, value in state.items():
        source = donor.get(key.split(".", 1)[0], base)
        assert torch.equal(value, source.state_dict()[key]), key
    assert not torch.equal(base.rim.offset_head.weight, fine.rim.offset_head.weight)

    no_coarse = CupNetModule(model=RIM_MODEL).model
    with pytest.raises(ValueError, match="'coarse_rim': the donor has no such network"):
        merged(base, {"coarse_rim": no_coarse})
    with pytest.raises(ValueError, match="'config': the base model has no such network"):
        merged(base, {"config": fine})
    wider = CupNetModule(model={**RIM_MODEL, "rim_channels": 12}).model
    before = {k: v.clone() for k, v in base.state_dict().items()}
    with pytest.raises(ValueError, match="'rim': its weights do not fit"):
        merged(base, {"coarse_rim": coarse, "rim": wider})
    # Nothing loaded, not even the part that fits: the misfit is found first.
    assert all(torch.equal(v, base.state_dict()[k]) for k, v in before.items())
    # Weights of the same shapes, learnt on strips sampled otherwise: it had merged silently.
    other_steps = CupNetModule(model={**RIM_MODEL, "rim_step": 2 * base.config.rim_step}).model
    with pytest.raises(ValueError, match=r"'rim': it learnt rim_step = .*, the base model runs"):
        merged(base, {"rim": other_steps})
    with pytest.raises(SystemExit):
        merge_main([str(paths["base"]), "--take", "rim", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit):
        merge_main([str(paths["base"]), "--take", f"rim={tmp_path / 'missing'}",
                    "--out", str(tmp_path / "x")])
    assert "checkpoint not found" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["cpu", "gpu"])
def test_last_checkpoint_is_written_at_the_runs_last_step(name):
    """A monitored ModelCheckpoint writes last.ckpt only where the score improves (Lightning
    2.6: a resume went back to the best step); last.ckpt comes from an unmonitored one whose
    interval divides max_steps, so the run's last step is in it."""
    config = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
    checkpoints = [c["init_args"] for c in config["trainer"]["callbacks"]
                   if c["class_path"].endswith("ModelCheckpoint")]
    assert not any(c.get("save_last") for c in checkpoints if c.get("monitor"))
    (last,) = [c for c in checkpoints if c.get("save_last")]
    assert last.get("monitor") is None
    assert config["trainer"]["max_steps"] % last["every_n_train_steps"] == 0


class _Counting(torch.utils.data.IterableDataset):
    """Samples ``{"index": (stream, i)}`` of a stream, shared among readers as SynthDataset
    shares its own (without synthesising anything)."""

    def __init__(self, stream: int) -> None:
        self.stream = stream

    def __iter__(self):
        return self.samples()

    def samples(self, skip: int = 0, rotate: int = 0):
        share, shares = stream_share(rotate)
        for i in itertools.count(share + skip * shares, shares):
            yield {"index": torch.tensor([self.stream, i])}


@pytest.mark.parametrize("workers", [0, 2, 3])
def test_batches_after_a_resume_are_those_the_stopped_run_would_have_made(workers):
    """Two streams taken in turn, read by several workers: resumed after 5 batches, the
    loader gives batches 5, 6, ... of the uninterrupted one."""
    def batches(done: int, count: int) -> list[list[list[int]]]:
        loader = DataLoader(RoundRobinBatches([_Counting(0), _Counting(1)], 2, None, done),
                            batch_size=None, num_workers=workers)
        return [b["index"].tolist() for b in itertools.islice(loader, count)]

    whole = batches(0, 12)
    assert len({tuple(map(tuple, b)) for b in whole}) == 12  # no batch made twice
    assert batches(5, 7) == whole[5:]
    # Epochs of 5 batches, the loader's whole (each worker's part had been 5), of one loader
    # with persistent workers (as CupDataModule's): each epoch goes on with the streams
    # (they had started again), and so does a loader resumed after 5.
    for done, first in ((0, 0), (5, 5)):
        loader = DataLoader(RoundRobinBatches([_Counting(0), _Counting(1)], 2, 5, done),
                            batch_size=None, num_workers=workers,
                            persistent_workers=workers > 0)
        epochs = [b["index"].tolist() for _ in range(2) for b in loader]
        assert epochs == (whole + batches(12, 3))[first:first + 10]


_RECORDER = '''
import json
import lightning as L
import torch


class RecordBatches(L.Callback):
    """Each rank's batch indices, and a digest of its weights at the end."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        with open(f"rank{trainer.global_rank}.jsonl", "a") as f:
            f.write(json.dumps({"index": batch["index"].tolist(),
                                "world": trainer.world_size}) + "\\n")

    def on_train_end(self, trainer, pl_module):
        digest = sum(float(p.double().square().sum()) for p in pl_module.parameters())
        with open(f"rank{trainer.global_rank}.jsonl", "a") as f:
            f.write(json.dumps({"digest": digest}) + "\\n")
'''


def test_two_process_ddp_runs_from_lightnings_flags_alone(tmp_path):
    """``--trainer.devices 2 --trainer.strategy ddp`` (gloo on the CPU, as NCCL on GPUs):
    the two processes train on disjoint shares of the stream, end with the same weights (DDP
    averaged their gradients), and one export is written that loads."""
    import json
    import os
    import sys

    (tmp_path / "record_batches.py").write_text(_RECORDER)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    run = subprocess.run(
        [sys.executable, "-m", "train", "fit", "-c", str(SMOKE),
         "--data.synth", str(ROOT / "configs/synth_smoke.yaml"), "--trainer.max_steps", "3",
         "--trainer.devices", "2", "--trainer.strategy", "ddp",
         "--trainer.callbacks+=record_batches.RecordBatches"],
        cwd=tmp_path, env=env, capture_output=True, encoding="utf-8", errors="replace",
        timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    ranks = [[json.loads(line) for line in (tmp_path / f"rank{r}.jsonl").read_text().splitlines()]
             for r in (0, 1)]
    seen = [[i for row in rows if "index" in row for i in row["index"]] for rows in ranks]
    assert all(row["world"] == 2 for rows in ranks for row in rows if "world" in row)
    assert len(seen[0]) == len(seen[1]) == 3 * 4  # 3 steps of the smoke config's batch of 4
    assert not set(seen[0]) & set(seen[1])
    digests = [rows[-1]["digest"] for rows in ranks]
    assert digests[0] == pytest.approx(digests[1], rel=1e-12)
    export = tmp_path / "runs" / "smoke" / "cupnet.safetensors"
    assert load_model(str(export)) is not None
    assert (tmp_path / "runs" / "smoke" / "checkpoints" / "last.ckpt").exists()


def test_hardware_recipe_starts_from_the_weights_shipped_before_it(capsys, monkeypatch):
    """``make train-hardware`` made the shipped weights from those shipped before it: both
    stages start from the weights its rule takes out of git, never from the shipped file
    (a rerun would fine-tune its own output), and wait for that rule; their time caps are
    40 min (on this machine their step caps ended them at 27 and 29 min)."""
    monkeypatch.chdir(ROOT)
    rules = _make_rules()
    [before] = _make_variable("PRE_HARDWARE")
    for name in ("hardware-locator", "hardware-rim"):
        prerequisites, [words] = rules[name]
        assert "$(PRE_HARDWARE)" in prerequisites
        stage = _stage_config(words, capsys)
        assert stage["model"]["init_weights"] == before
        assert (ROOT / before).resolve() != DEFAULT_CHECKPOINT.resolve()
        assert stage["trainer"]["max_time"] == "00:00:40:00"
    assert "$(PRE_HARDWARE)" in rules["train-hardware"][0]
    recipe = rules["$(PRE_HARDWARE)"][1]
    assert ["git", "show", "d89edca:cupnet/assets/cupnet_default.safetensors", ">",
            "$@.part"] in recipe


def test_the_hardware_recipes_starting_weights_load_as_shipped_before_it(tmp_path):
    """The Makefile's rule for the hardware stages' starting weights, run into a fresh
    folder, gives d89edca's weights with their settings beside them, so that they load with
    every network: without the JSON, ``load_model`` built the default architecture and
    refused the rim networks' weights, and both stages failed at once."""
    if subprocess.run(["git", "cat-file", "-e", "d89edca^{commit}"], cwd=ROOT,
                      capture_output=True).returncode:
        pytest.skip("a shallow clone lacks d89edca")
    target = tmp_path / "pre" / "cupnet.safetensors"
    subprocess.run(["make", "-s", f"PRE_HARDWARE={target}", str(target)], cwd=ROOT,
                   check=True, capture_output=True)
    shipped = subprocess.run(["git", "show", "d89edca:cupnet/assets/cupnet_default.safetensors"],
                             cwd=ROOT, check=True, capture_output=True).stdout
    assert target.read_bytes() == shipped
    model = load_model(target)
    assert model.rim is not None and model.coarse_rim is not None


def test_merge_gives_a_base_the_donors_fine_rim_network_as_its_blur_trained_one(tmp_path):
    """``--take blur_rim=``: the donor's fine rim network (fine-tuned on blurrier images)
    becomes the base's ``blur_rim``, the base's own networks kept; a base given one it
    cannot take (another width) is left without one."""
    torch.manual_seed(0)
    base, blurry = (CupNetModule(model=RIM_MODEL).model for _ in range(2))
    paths = {name: save_model(net, tmp_path / f"{name}.safetensors")
             for name, net in (("base", base), ("blurry", blurry))}
    out = merge_main([str(paths["base"]), "--take", f"blur_rim={paths['blurry']}",
                      "--out", str(tmp_path / "merged.safetensors")])
    merged_model = load_model(out)
    assert merged_model.config.blur_rim and not merged_model.config.blurred
    for key, value in merged_model.state_dict().items():
        network, rest = key.split(".", 1)
        expected = (blurry.rim.state_dict()[rest] if network == "blur_rim"
                    else base.state_dict()[key])
        assert torch.equal(value, expected), key
    wider = CupNetModule(model={**RIM_MODEL, "rim_channels": 12}).model
    with pytest.raises(ValueError, match="'blur_rim': its weights do not fit"):
        merged(base, {"blur_rim": wider})
    assert base.blur_rim is None and not base.config.blur_rim


def test_a_stage_fine_tuned_from_the_shipped_weights_starts_without_its_blur_trained_network():
    """The recipes that start from the shipped checkpoint (configs/blur_rim.yaml,
    cpu_locator3-5, cpu_rim_narrow) train a model without ``blur_rim``: its weights load,
    every network tensor for tensor, the blur-trained one left out with a warning."""
    stored = json.loads(config_path(DEFAULT_CHECKPOINT).read_text())
    config = {k: v for k, v in stored.items() if k not in ("blur_rim", "blurred")}
    with pytest.warns(UserWarning, match=r"blur-trained rim network \(blur_rim\) is not in"):
        module = CupNetModule(model=config, init_weights=str(DEFAULT_CHECKPOINT))
    shipped = load_model().state_dict()
    state = module.model.state_dict()
    assert module.model.blur_rim is None and state.keys() == {
        k for k in shipped if not k.startswith("blur_rim.")}
    assert all(torch.equal(value, shipped[key]) for key, value in state.items())
