"""The README's Python examples run as printed, and do what their comments say."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from data_synth import SynthDataset
from data_synth.config import SynthConfig

README = Path(__file__).resolve().parent.parent / "README.md"
EXAMPLES = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_the_readme_has_the_two_examples() -> None:
    assert len(EXAMPLES) == 2


def test_solver_example_recovers_the_pose_with_a_gradient() -> None:
    torch.manual_seed(0)
    names: dict = {}
    exec(EXAMPLES[0], names)  # noqa: S102 - the README's own code
    sol, points, fit = names["sol"], names["points"], names["fit"]
    error = (sol.pose - names["true_pose"]).abs()[0]
    assert (error[:2] < 0.2).all() and (error[2:4] < 0.2).all() and error[4] < 2.0
    assert points.grad is not None and torch.isfinite(points.grad).all()
    assert points.grad.abs().max() > 0
    # The fit's centre lies near the rim's own projected centre of points.
    assert fit.valid.all()
    np.testing.assert_allclose(fit.params[0, :2].numpy(), names["rim"][0].mean(0).numpy(),
                               atol=2.0)


def test_model_example_finds_the_cup_of_a_png(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture) -> None:
    # The example's geometry and cup: SDD 1040 mm, 0.3 mm/px, principal point at the centre.
    config = SynthConfig(image_size=(512, 512), sdd_mm=(1040.0, 1040.0),
                         pixel_spacing_mm=(0.3, 0.3), principal_offset_frac=0.0,
                         cup_diameter_mm=(52.0, 52.0), p_bilateral=0.0, p_no_cup=0.0)
    sample = next(iter(SynthDataset(config, seed=5, length=1)))
    cv2.imwrite(str(tmp_path / "hip.png"),
                np.round(sample["image"][0].numpy() * 65535).astype(np.uint16))
    monkeypatch.chdir(tmp_path)
    names: dict = {}
    exec(EXAMPLES[1], names)  # noqa: S102 - the README's own code
    (cup,) = names["cups"]
    truth = sample["pose"][0].numpy()
    assert abs(cup.pose[0] - truth[0]) < 2.0 and abs(cup.pose[1] - truth[1]) < 2.0
    assert cup.status in ("ok", "ambiguous")
    assert capsys.readouterr().out.count("\n") == 1
