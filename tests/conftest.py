"""Shared fixtures: float64 everywhere in the geometry tests, a fixed seed."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(1234)
