"""``benchmarks.stages``: each stage timed and counted, the model and modules left as they were."""

from __future__ import annotations

import torch

import cupnet.model
from benchmarks.stages import stage_seconds
from benchmarks.throughput import forward_cups
from cupnet.geometry import Geometry
from cupnet.model import load_model
from cupnet.parallel import map_on_cores


def test_stage_seconds_counts_each_stage_and_leaves_the_model_as_it_was() -> None:
    model = load_model().eval()
    images = torch.rand(2, 1, 256, 256, generator=torch.Generator().manual_seed(0))
    geometry = Geometry.from_rows(torch.tensor([[1000.0, 0.3, 127.5, 127.5]] * 2))
    total, stages = stage_seconds(forward_cups, model, (images, geometry, torch.full((2,), 50.0)),
                                  torch.device("cpu"))
    # forward: the locator, its blobs and the solver once each; no detect-only stage
    assert stages["locate"][0] == stages["ellipses_from_locator"][0] == stages["solve"][0] == 1
    assert "rough_ellipses" not in stages and "trusted_rim_landmarks" not in stages
    assert 0 < stages["locate"][1] < total
    assert not {"locate", "solve"} & set(vars(model))  # the timers are gone
    assert cupnet.model.map_on_cores is map_on_cores
