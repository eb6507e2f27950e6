"""The blur-trained fine rim network (``CupNetConfig.blur_rim``) and ``blurred``, which runs it
in every rim stage (``cupnet predict --blurred``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from benchmarks.model import blurrier, counting_strips
from cupnet.config import CupNetConfig
from cupnet.geometry import Geometry
from cupnet.model import CupNet, load_model, save_model
from data_synth import SynthDataset
from train.data import synth_config


def test_blurred_runs_every_rim_stage_with_the_blur_trained_network() -> None:
    """A DRR blurred 2 px more than the training's (seed 20,261,164 at 512 px, image 19, as
    the degraded table's row): the shipped model's rim network gives a pose 36 deg off,
    flagged; with ``blurred`` only the blur-trained network runs and the pose is within
    the targets, believed."""
    fields = yaml.safe_load(Path("configs/synth_eval.yaml").read_text())
    sample = blurrier(SynthDataset(synth_config(fields, 512), seed=20_261_164,
                                   length=20)[19], 2.0)
    model = load_model()
    geometry = Geometry.from_row(sample["geometry"])
    truth = sample["pose"][0].double().numpy()
    errors = {}
    for blurred in (False, True):
        model.config.blurred = blurred
        with counting_strips(model) as (fine, _, blur):
            (cup,) = model.detect(sample["image"][None], geometry,
                                  float(sample["cup_diameter"][0]), return_masks=False)[0]
        ran, idle = (blur, fine) if blurred else (fine, blur)
        assert ran.count > 0 and idle.count == 0
        errors[blurred] = (np.abs(cup.pose - truth), cup.check)
    assert errors[False][0][0] > 20.0 and errors[False][1]
    error, check = errors[True]
    assert (error[:2] < 1.0).all() and (error[2:4] < 1.0).all() and error[4] < 8.0
    assert not check


def test_blurred_needs_the_blur_trained_network() -> None:
    with pytest.raises(ValueError, match="blurred needs blur_rim"):
        CupNetConfig(blurred=True)
    model = CupNet(CupNetConfig(rim_passes=2))
    assert model.blur_rim is None and model.fine_rim() is model.rim
    with pytest.raises(ValueError, match="blurred needs blur_rim"):
        model.config.blurred = True  # as a caller may set it on a loaded model
    assert not model.config.blurred
    # A config told it has the network after the model was made without it: the rim stage
    # names the cause (it would have failed on a missing network).
    model.config.update(blur_rim=True, blurred=True)
    with pytest.raises(ValueError, match="blurred needs blur_rim"):
        model.rim_landmarks(torch.rand(1, 1, 64, 64), torch.zeros(1, dtype=torch.long),
                            torch.tensor([[32.0, 32.0, 20.0, 12.0, 0.0]]))
    assert not any(key.startswith("blur_rim.") for key in CupNet().state_dict())


def test_a_model_with_the_blur_trained_network_round_trips(tmp_path) -> None:
    model = CupNet(CupNetConfig(rim_passes=2, blur_rim=True, blurred=True))
    assert model.fine_rim() is model.blur_rim
    loaded = load_model(save_model(model, tmp_path / "blur.safetensors"))
    assert loaded.config.blurred and loaded.fine_rim() is loaded.blur_rim
    for name, value in model.blur_rim.state_dict().items():
        torch.testing.assert_close(loaded.blur_rim.state_dict()[name], value, rtol=0, atol=0)
