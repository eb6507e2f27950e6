"""cupnet demo: synthesise, predict and evaluate end to end (a tiny set, an untrained model)."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import pytest
import torch

from cupnet.cli import main
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
