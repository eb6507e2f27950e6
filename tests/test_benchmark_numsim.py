"""benchmarks/numsim.py scores poses as ``cupnet evaluate`` does."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.numsim import errors, resolve_ambiguity
from cupnet.evaluate import pose_errors


def test_inclination_errors_wrap_as_evaluate_scores_them():
    """Across phi = +-90 deg: 89.9 for a truth of -89.9 is 0.2 deg off, not 179.8."""
    truth = torch.tensor([[20.0, -89.9, 1.0, 2.0, 300.0], [30.0, 10.0, 0.0, 0.0, 200.0]],
                         dtype=torch.float64)
    estimate = torch.tensor([[21.0, 89.9, 1.5, 2.0, 310.0], [30.0, 14.0, 0.0, -1.0, 205.0]],
                            dtype=torch.float64)
    got = errors(estimate, truth)
    reference = pose_errors(estimate.numpy(), truth.numpy())
    assert np.allclose(got["phi"].numpy(), np.abs(reference["inclination_deg"]))
    assert np.allclose(got["phi"].numpy(), [0.2, 4.0])
    assert got["theta"].tolist() == [1.0, 0.0] and got["h"].tolist() == [10.0, 5.0]
    # The pose across the boundary is the nearer one of a pair.
    alt = estimate + torch.tensor([0.0, -170.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert torch.equal(resolve_ambiguity(estimate, alt, truth)[0], estimate[0])
