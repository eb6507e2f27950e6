"""cupnet.offload: CupNet's networks on another device, the rest of detect on the CPU."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from cupnet.cli import main
from cupnet.config import CupNetConfig
from cupnet.geometry import Geometry
from cupnet.model import CupNet, load_model
from cupnet.offload import NETWORKS, OnDevice, networks_on, resolve_device
from cupnet.rim import RimNet
from data_synth import SynthConfig, synthesize

# A device no machine has: CUDA device 99 (also where CUDA is there).
MISSING = "cuda:99"


class DeviceRecorder(nn.Module):
    """Records the device type of each input and gives CPU tensors back (a meta tensor, the
    stand-in for an accelerator here, holds no values to copy back)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []
        self.marker = 7

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        self.seen.append(x.device.type)
        return torch.zeros(x.shape), torch.ones(x.shape[0])


def test_inputs_go_to_the_device_and_outputs_come_back() -> None:
    recorder = DeviceRecorder()
    wrapped = OnDevice(recorder, "meta")
    logits, sigma = wrapped(torch.rand(3, 1, 4, 5))
    assert recorder.seen == ["meta"]
    assert logits.device.type == sigma.device.type == "cpu"
    assert logits.shape == (3, 1, 4, 5) and sigma.shape == (3,)
    assert wrapped.marker == 7  # the wrapped module's attributes, through the wrapper
    with pytest.raises(AttributeError):
        _ = wrapped.no_such_attribute


class AnswersOnTheCpu(nn.Module):
    """Gives a tensor and a tuple of tensors on the CPU wherever its input is: the stand-in
    for an accelerator's outputs, for a caller on "meta" (the CPU's outputs can be copied
    there; a meta tensor holds no values to copy to the CPU)."""

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        return torch.zeros(x.shape), (torch.ones(x.shape[0]), torch.ones(x.shape[:2]))


def test_every_output_comes_back_to_the_first_inputs_device() -> None:
    """Each output, those in tuples too (the rim networks' logits and log sigma), arrives on
    the caller's device, not the one the module answered on (:class:`DeviceRecorder`'s CPU
    outputs, with the caller on the CPU, would arrive whether moved or not)."""
    wrapped = OnDevice(AnswersOnTheCpu(), "meta")
    zeros, (ones, more) = wrapped(torch.zeros(3, 4, device="meta"))
    assert [t.device.type for t in (zeros, ones, more)] == ["meta"] * 3
    assert zeros.shape == more.shape == (3, 4) and ones.shape == (3,)


def test_a_moved_wrapper_sends_inputs_where_its_weights_are() -> None:
    recorder = DeviceRecorder()
    recorder.weight = nn.Parameter(torch.zeros(1))
    wrapped = OnDevice(recorder, "cpu")
    wrapped(torch.rand(2, 3))
    wrapped.to("meta")
    wrapped(torch.rand(2, 3))
    assert recorder.seen == ["cpu", "meta"]


def test_rim_network_attributes_pass_through() -> None:
    rim = RimNet(4)
    assert OnDevice(rim, "cpu").columns_seen == rim.columns_seen == 11


def test_networks_on_the_cpu_give_the_same_detections() -> None:
    """Every network wrapped, the original left as it was, and the shipped model's
    detections on a DRR unchanged to the last digit (the same kernels run)."""
    model = load_model()
    moved = networks_on(model, "cpu")
    assert all(isinstance(getattr(moved, name), OnDevice) for name in NETWORKS)
    assert not any(isinstance(getattr(model, name), OnDevice) for name in NETWORKS)
    sample = synthesize(SynthConfig(image_size=(512, 512), p_anatomy=0.0), 0, 0)
    geometry = Geometry.from_row(sample["geometry"])
    ours, theirs = (m.detect(sample["image"][None], geometry, float(sample["cup_diameter"][0]),
                             return_masks=False)[0] for m in (moved, model))
    assert len(ours) == len(theirs) == 1 and ours[0].status == theirs[0].status == "ok"
    assert np.array_equal(ours[0].pose, theirs[0].pose)
    assert np.array_equal(ours[0].landmarks, theirs[0].landmarks)


def test_a_model_without_a_rim_stage_keeps_none() -> None:
    moved = networks_on(CupNet(CupNetConfig(rim_passes=0, coarse_rim_passes=0)), "cpu")
    assert moved.rim is None and moved.coarse_rim is None
    assert isinstance(moved.locator, OnDevice)


@pytest.mark.parametrize(("name", "message"), [
    ("tpu", "unknown device 'tpu': use cpu, cuda, cuda:N or mps"),
    ("xla", "device 'xla': use cpu, cuda, cuda:N or mps"),
    (MISSING, "device 'cuda:99': "),
])
def test_devices_this_machine_lacks_are_named(name: str, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        resolve_device(name)


def test_cpu_resolves() -> None:
    assert resolve_device("cpu") == torch.device("cpu")


def test_predict_stops_before_reading_on_a_missing_device(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path), "--out", str(out), "--device", MISSING]) == 2
    assert "cupnet predict: error: device 'cuda:99'" in capsys.readouterr().err
    assert not out.exists()


def test_predict_records_the_device(tmp_path: Path) -> None:
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.zeros((256, 256), np.uint8))  # 256: runs, no cup
    out = tmp_path / "out"
    assert main(["predict", str(blank), "--out", str(out), "--assume-defaults", "--quiet",
                 "--device", "cpu"]) == 0
    assert json.loads((out / "results.json").read_text())["model"]["device"] == "cpu"
