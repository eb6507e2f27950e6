"""cupnet.runtime: CupNet's networks in ONNX Runtime, checked against PyTorch's own outputs."""

from __future__ import annotations

import csv
import importlib.metadata
import importlib.util
import json
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from cupnet.cli import main
from cupnet.fold import fold_batchnorm
from cupnet.geometry import Geometry
from cupnet.model import load_model
from cupnet.offload import NETWORKS
from cupnet.rim import RimNet, memoised_strips
from cupnet.runtime import InOnnxRuntime, cache_dir, export_key, networks_in_onnx_runtime
from data_synth import SynthConfig, SynthDataset, synthesize
from train.data import synth_config


@pytest.fixture(scope="module")
def shipped() -> torch.nn.Module:
    return fold_batchnorm(load_model())


def rim_net(seed: int) -> RimNet:
    torch.manual_seed(seed)
    rim = RimNet(8)
    for layer in rim.body:  # BatchNorm statistics away from the identity
        layer.norm.running_mean.uniform_(-0.5, 0.5)
        layer.norm.running_var.uniform_(0.5, 2.0)
    return rim.eval()


def test_a_rim_network_gives_what_pytorch_gives(generator: torch.Generator) -> None:
    """Strips of the rim's and of other shapes (the graph's dimensions are dynamic), one by
    one and at once."""
    rim = rim_net(0)
    wrapped = InOnnxRuntime(rim)
    assert wrapped.columns_seen == rim.columns_seen
    for shape in [(3, 1, 64, 128), (1, 1, 48, 96)]:
        strips = torch.rand(shape, generator=generator)
        with torch.no_grad():
            expected = rim(strips)
            got, at_once = wrapped(strips), wrapped.run(strips)
        for mine, theirs in [(got, expected), (at_once, expected)]:
            assert [m.shape for m in mine] == [t.shape for t in theirs]
            for m, t in zip(mine, theirs, strict=True):
                assert m.dtype == torch.float32
                torch.testing.assert_close(m, t, atol=1e-4, rtol=1e-4)


def test_graphs_are_cached_by_weights(onnx_cache: Path) -> None:
    """Exported once; the same weights load the cached graph, other weights export their
    own, and a cached graph that does not load is exported again."""
    first, same, other = rim_net(1), rim_net(1), rim_net(2)
    assert export_key(first) == export_key(same) != export_key(other)
    exports: list[Path] = []
    InOnnxRuntime(first, on_export=exports.append)
    assert cache_dir() == onnx_cache / "onnx"
    assert exports == [cache_dir() / f"rim-{export_key(first)}.onnx"]
    assert exports[0].is_file()
    InOnnxRuntime(same, on_export=exports.append)
    assert len(exports) == 1  # loaded, not exported again
    InOnnxRuntime(other, on_export=exports.append)
    assert exports[1] == cache_dir() / f"rim-{export_key(other)}.onnx"
    exports[1].write_bytes(b"not a graph")
    strips = torch.rand(2, 1, 64, 128)
    again = InOnnxRuntime(other, on_export=exports.append)
    assert len(exports) == 3 and exports[2] == exports[1]
    with torch.no_grad():
        torch.testing.assert_close(again(strips), other(strips), atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("library", ["torch", "onnxruntime", "onnxscript"])
def test_graphs_are_cached_by_library_versions(library: str,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """After an upgrade of a library that builds or runs the graph the network is exported
    anew: a graph of the old exporter, or for the old runtime, may not load or run alike."""
    rim = rim_net(1)
    before = export_key(rim)
    installed = importlib.metadata.version

    def upgraded(name: str) -> str:
        return "999.0" if name == library else installed(name)

    monkeypatch.setattr(importlib.metadata, "version", upgraded)
    assert export_key(rim) != before


def test_graphs_are_cached_by_the_source_of_the_layers_classes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An edit to the file defining a layer's class (its forward, a constant it reads)
    exports the network anew, the weights unchanged; the same file gives the same key."""
    source = tmp_path / "edited_layer.py"
    source.write_text("from torch import nn\n\nSCALE = 1.0\n\n\n"
                      "class Layer(nn.Module):\n"
                      "    def __init__(self):\n"
                      "        super().__init__()\n"
                      "        self.conv = nn.Conv2d(1, 1, 3)\n\n"
                      "    def forward(self, x):\n"
                      "        return SCALE * self.conv(x)\n")
    spec = importlib.util.spec_from_file_location("edited_layer", source)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "edited_layer", module)  # where inspect finds it
    spec.loader.exec_module(module)
    layer = module.Layer()
    before = export_key(layer)
    assert export_key(layer) == before
    source.write_text(source.read_text().replace("SCALE = 1.0", "SCALE = 2.0"))
    assert export_key(layer) != before


class TinyUNet(nn.Module):
    """A network on square images that is not a RimNet: exported, as a U-Net, for one side
    (in a second or two, where a real U-Net takes several)."""

    def __init__(self) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(1, 4, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(4, 1, 3, padding=1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


def tiny_unet(seed: int) -> TinyUNet:
    torch.manual_seed(seed)
    return TinyUNet().eval()


def test_a_unet_graph_is_cached_for_its_side(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The same weights for two sides (a changed locator_size) make two graphs: had the
    128 px wrapper loaded the 96 px graph, ONNX Runtime would fail on its first call and
    the network run in PyTorch for the rest of the run, with only a warning."""
    monkeypatch.setenv("CUPNET_CACHE_DIR", str(tmp_path))  # a cache of its own: both exported
    net = tiny_unet(5)
    exports: list[Path] = []
    small = InOnnxRuntime(net, side=96, on_export=exports.append)
    large = InOnnxRuntime(net, side=128, on_export=exports.append)
    assert [path.name.split("-")[0] for path in exports] == ["unet96", "unet128"]
    for wrapped, side in [(small, 96), (large, 128)]:
        views = torch.rand(2, 1, side, side)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("error")  # no fall-back to PyTorch
            torch.testing.assert_close(wrapped(views), net(views), atol=1e-5, rtol=1e-4)
        assert wrapped.failure is None


def test_an_input_of_another_side_runs_in_pytorch_that_call_alone(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A U-Net input of a side the graph was not made for is run in PyTorch with a warning
    naming both sides, and ONNX Runtime is not given up for the calls of the graph's side
    (had it been tried, it would fail and run every later call in PyTorch)."""
    net = tiny_unet(6)
    wrapped = InOnnxRuntime(net, side=128)
    odd = torch.rand(1, 1, 96, 96)
    with pytest.warns(UserWarning, match=r"^ONNX Runtime's graph takes 128 px inputs; "
                                         r"PyTorch runs these \(96, 96\)$"), torch.no_grad():
        torch.testing.assert_close(wrapped(odd), net(odd))
    assert wrapped.failure is None
    ran: list[tuple[int, ...]] = []
    graph = wrapped.run

    def recorded(inputs: torch.Tensor) -> torch.Tensor:
        ran.append(tuple(inputs.shape))
        return graph(inputs)

    monkeypatch.setattr(wrapped, "run", recorded)
    views = torch.rand(2, 1, 128, 128)
    with torch.no_grad():
        torch.testing.assert_close(wrapped(views), net(views), atol=1e-5, rtol=1e-4)
    assert ran == [(2, 1, 128, 128)]  # in ONNX Runtime


def test_a_cache_folder_that_cannot_be_made_is_warned_of(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """CUPNET_CACHE_DIR with a file on its path: the network runs, exported for the run
    alone, with a warning; the temporary file's clean-up had raised NotADirectoryError over
    the warning and stopped the run."""
    (tmp_path / "afile").write_text("")
    monkeypatch.setenv("CUPNET_CACHE_DIR", str(tmp_path / "afile"))
    rim = rim_net(3)
    with pytest.warns(UserWarning, match="cannot cache the exported network"):
        wrapped = InOnnxRuntime(rim)
    strips = torch.rand(2, 1, 64, 128)
    with torch.no_grad():
        torch.testing.assert_close(wrapped(strips), rim(strips), atol=1e-4, rtol=1e-4)


def test_a_failing_session_hands_over_to_pytorch(monkeypatch: pytest.MonkeyPatch) -> None:
    rim = rim_net(0)
    wrapped = InOnnxRuntime(rim)

    class Broken:
        def run(self, *args: object) -> None:
            raise RuntimeError("[ONNXRuntimeError] : 6 : RUNTIME_EXCEPTION")

    monkeypatch.setattr(wrapped, "session", Broken())
    strips = torch.rand(3, 1, 64, 128)
    with pytest.warns(UserWarning, match="ONNX Runtime failed"), torch.no_grad():
        got = wrapped(strips)
    assert wrapped.failure == "[ONNXRuntimeError] : 6 : RUNTIME_EXCEPTION"
    with torch.no_grad():
        expected = rim(strips)
    for mine, theirs in zip(got, expected, strict=True):
        torch.testing.assert_close(mine, theirs)


def test_no_gradients_through_onnx_runtime() -> None:
    wrapped = InOnnxRuntime(rim_net(0))
    with pytest.raises(RuntimeError, match="no gradients"):
        wrapped(torch.rand(1, 1, 64, 128, requires_grad=True))


def test_the_shipped_model_detects_the_same_cup(shipped: torch.nn.Module) -> None:
    """Every network wrapped, the original left as it is; the cup of a DRR found with the
    same pose to well within its error (float rounding only), and U-Net logits equal to
    PyTorch's; a U-Net input of a side the graph was not made for runs in PyTorch."""
    wrapped = networks_in_onnx_runtime(shipped, threads=1)
    assert all(isinstance(getattr(wrapped, name), InOnnxRuntime) for name in NETWORKS)
    assert not any(isinstance(getattr(shipped, name), InOnnxRuntime) for name in NETWORKS)
    sample = synthesize(SynthConfig(image_size=(512, 512), p_anatomy=0.0), 0, 0)
    geometry = Geometry.from_row(sample["geometry"])
    with memoised_strips():
        ours, theirs = (m.detect(sample["image"][None], geometry,
                                 float(sample["cup_diameter"][0]), return_masks=False)[0]
                        for m in (wrapped, shipped))
    assert len(ours) == len(theirs) == 1 and ours[0].status == theirs[0].status == "ok"
    np.testing.assert_allclose(ours[0].pose, theirs[0].pose, atol=1e-3)
    np.testing.assert_allclose(ours[0].landmarks, theirs[0].landmarks, atol=1e-2)
    views = torch.rand(2, 1, 128, 128)
    with torch.no_grad():
        torch.testing.assert_close(wrapped.locator(views), shipped.locator(views),
                                   atol=2e-4, rtol=1e-4)
        odd = torch.rand(1, 1, 96, 96)
        torch.testing.assert_close(wrapped.refiner(odd), shipped.refiner(odd))


def test_an_image_gives_the_same_cups_alone_and_in_a_batch(shipped: torch.nn.Module) -> None:
    """``detect`` solves a batch's cups together; each image's cups come out the same to the
    last digit alone and beside other images of other sizes (cupnet.batchwise; ONNX Runtime
    rounds a batch's items as each alone). Before, every one of these images' poses moved by
    1e-13 to 1e-6 in a batch, and the dome-outline passes had turned such digits into another
    pose for one image of a review's set."""
    wrapped = networks_in_onnx_runtime(shipped, threads=1)
    images = [sample for size, seed in ((512, 424242), (768, 424243))
              for sample in SynthDataset(synth_config("configs/synth_eval.yaml", size),
                                         seed=seed, length=2)]

    def cups(batch: list[dict]) -> list[list[np.ndarray]]:
        rows = torch.stack([torch.as_tensor(s["geometry"], dtype=torch.float64) for s in batch])
        found = wrapped.detect([s["image"] for s in batch], Geometry(*rows.T),
                               torch.tensor([float(s["cup_diameter"][0]) for s in batch],
                                            dtype=torch.float64), return_masks=False)
        return [[np.concatenate([cup.pose, cup.ellipse, cup.landmarks.ravel(), [cup.doubt]])
                 for cup in image] for image in found]

    together = cups(images[::-1])[::-1]
    for sample, in_batch in zip(images, together, strict=True):
        alone = cups([sample])[0]
        assert len(alone) == len(in_batch) >= 1
        for one, other in zip(alone, in_batch, strict=True):
            np.testing.assert_array_equal(one, other)


def test_predict_writes_the_same_rows_whatever_the_batch_size(tmp_path: Path) -> None:
    """``cupnet predict`` (the shipped model, its networks in ONNX Runtime) writes the same
    results.csv one image a batch as four, the time each image took aside."""
    folder = tmp_path / "drrs"
    assert main(["synth", "--n", "4", "--out", str(folder), "--config",
                 "configs/synth_eval.yaml", "--size", "512", "512", "--seed", "99"]) == 0

    def rows(batch_size: int) -> list[dict]:
        out = tmp_path / f"batch{batch_size}"
        assert main(["predict", str(folder / "images"), "--meta", str(folder / "meta.csv"),
                     "--out", str(out), "--batch-size", str(batch_size), "--no-overlays",
                     "--quiet"]) == 0
        with (out / "results.csv").open() as file:
            return [{key: value for key, value in row.items() if key != "seconds"}
                    for row in csv.DictReader(file)]

    one, four = rows(1), rows(4)
    assert len(one) >= 4 and one == four


def predict_blank(tmp_path: Path, checkpoint: Path, *flags: str) -> dict:
    """``cupnet predict`` on a blank image with ``flags``; its results.json."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    blank = tmp_path / "blank.png"
    assert cv2.imwrite(str(blank), np.zeros((256, 256), np.uint8))  # 256: runs, no cup
    out = tmp_path / "out"
    assert main(["predict", str(blank), "--out", str(out), "--assume-defaults", "--quiet",
                 "--checkpoint", str(checkpoint), *flags]) == 0
    return json.loads((out / "results.json").read_text())


def test_predict_runs_the_networks_in_onnx_runtime_by_default(
        tmp_path: Path, blind_checkpoint: Path) -> None:
    assert predict_blank(tmp_path, blind_checkpoint)["model"]["runtime"] == "onnx"


def test_predict_falls_back_on_pytorch(tmp_path: Path, blind_checkpoint: Path,
                                       monkeypatch: pytest.MonkeyPatch,
                                       capsys: pytest.CaptureFixture) -> None:
    """Where ONNX Runtime cannot run the networks, the default runs them in PyTorch and says
    why; asked for by name, it stops the run naming the problem."""
    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("no kernel for this CPU")

    monkeypatch.setattr("cupnet.runtime.networks_in_onnx_runtime", broken)
    assert predict_blank(tmp_path, blind_checkpoint)["model"]["runtime"] == "torch"
    assert ("ONNX Runtime cannot run the networks (no kernel for this CPU); they run in "
            "PyTorch") in capsys.readouterr().err
    assert main(["predict", str(tmp_path / "blank.png"), "--out", str(tmp_path / "again"),
                 "--assume-defaults", "--quiet", "--checkpoint", str(blind_checkpoint),
                 "--runtime", "onnx"]) == 2
    assert "cannot load the model: no kernel for this CPU" in capsys.readouterr().err
    assert predict_blank(tmp_path / "torch", blind_checkpoint,
                         "--runtime", "torch")["model"]["runtime"] == "torch"


def test_predict_refuses_onnx_runtime_on_another_device(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path), "--out", str(out), "--runtime", "onnx",
                 "--device", "cuda"]) == 2
    assert ("--runtime onnx runs the networks on the CPU, not on --device cuda"
            in capsys.readouterr().err)
    assert not out.exists()
