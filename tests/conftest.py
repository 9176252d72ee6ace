"""Shared fixtures. Session-scoped models and exports keep the suite within minutes."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import e3dpsm

torch.set_num_threads(2)


def sparse_lnes(shape: tuple[int, ...], density: float = 0.03, seed: int = 0) -> torch.Tensor:
    """Random sparse LNES-like frames: most pixels 0, the rest a timestamp fraction in [0, 1)."""
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) < density
    return torch.from_numpy((mask * rng.random(shape)).astype(np.float32))


@pytest.fixture(scope="session")
def tiny_model() -> torch.nn.Module:
    model = e3dpsm.create_model("tiny").eval()
    # A realistic offset (mm), so tolerances are checked at the magnitude of real poses.
    model.set_pose_prior(torch.linspace(-800.0, 1200.0, 48).view(16, 3))
    return model
