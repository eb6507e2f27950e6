"""Shared fixtures: a fixed seed; a model for the tests of cupnet predict's bookkeeping."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from cupnet.config import CupNetConfig
from cupnet.model import CupNet, save_model


@pytest.fixture(scope="session", autouse=True)
def onnx_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The session's own cache of exported networks (cupnet.runtime; predict runs its
    networks in ONNX Runtime by default): the tests export each model once and write nothing
    under the user's home."""
    root = tmp_path_factory.mktemp("cupnet-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CUPNET_CACHE_DIR", str(root))
        yield root


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(1234)


@pytest.fixture(scope="session")
def blind_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained CupNet that never reports a cup (threshold above any probability): for
    the tests of bookkeeping, where detections only cost time."""
    model = CupNet(CupNetConfig(detect_threshold=2.0))
    return save_model(model, tmp_path_factory.mktemp("model") / "blind.safetensors")
