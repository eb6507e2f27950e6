"""Shared fixtures: a fixed seed; a model for the tests of cupnet predict's bookkeeping."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cupnet.config import CupNetConfig
from cupnet.model import CupNet, save_model


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(1234)


@pytest.fixture(scope="session")
def blind_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained CupNet that never reports a cup (threshold above any probability): for
    the tests of bookkeeping, where detections only cost time."""
    model = CupNet(CupNetConfig(detect_threshold=2.0))
    return save_model(model, tmp_path_factory.mktemp("model") / "blind.safetensors")
