"""cupnet demo: synthesise, predict and evaluate end to end (a tiny set, an untrained model)."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import pytest
import torch

from cupnet.cli import main
from cupnet.demo import commands
from cupnet.model import CupNet, save_model


def test_demo_runs_all_three_steps(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    torch.manual_seed(0)
    checkpoint = save_model(CupNet(), tmp_path / "untrained.safetensors")
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--n", "2", "--size", "320", "--checkpoint",
            str(checkpoint)]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert "| anteversion (deg) |" in captured.out
    assert f"report:   {out / 'evaluate' / 'report.md'}" in captured.out
    with (out / "predict" / "results.csv").open() as f:
        images = {row["image"] for row in csv.DictReader(f)}
    assert images == {p.name for p in (out / "data" / "images").iterdir()}
    with (out / "data" / "meta.csv").open() as f:
        assert {row["image"] for row in csv.DictReader(f)} == images
    assert all(cv2.imread(str(p), cv2.IMREAD_UNCHANGED).shape == (320, 320)
               for p in (out / "data" / "images").iterdir())
    assert len(list((out / "predict" / "overlays").iterdir())) == 2
    assert (out / "evaluate" / "plots" / "error_vs_distance.png").exists()
    # A second demo into the same folder must not silently replace the first.
    assert main(args) == 2
    assert "--overwrite" in capsys.readouterr().err


@pytest.mark.parametrize("overwrite", [False, True])
def test_demo_passes_overwrite_to_synth_and_predict(overwrite: bool) -> None:
    """``cupnet demo --overwrite`` into an earlier demo's folder: synth and predict would
    each refuse their existing outputs (exit 2) without it; evaluate has no such option."""
    out = Path("demo")
    again = ["--overwrite"] if overwrite else []
    assert commands(out, 3, 5, None, overwrite, 320) == [
        ["synth", "--n", "3", "--seed", "5", "--size", "320", "320", "--out", "demo/data",
         *again],
        ["predict", "demo/data/images", "--out", "demo/predict", "--meta", "demo/data/meta.csv",
         *again],
        ["evaluate", "--pred", "demo/predict/results.csv", "--truth", "demo/data/truth.csv",
         "--out", "demo/evaluate"],
    ]
