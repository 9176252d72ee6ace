"""Shared fixtures. Session-scoped models and exports keep the suite within minutes."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import e3dpsm

# e3dpsm.testing: the e3dpsm_golden fixture, registered as users register it. The helper
# modules' session fixtures are registered here once, so that every test module shares one
# instance (a fixture imported into a module is a separate definition, built again there).
pytest_plugins = ["e3dpsm.testing", "_quantize_helpers", "_profile_helpers", "_training_helpers"]

# One intra-op thread: the test models are tiny, and PyTorch's OpenMP workers busy-wait
# between steps, which starves ONNX Runtime when both alternate in one process (parity).
torch.set_num_threads(1)


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


@pytest.fixture(scope="session")
def synthetic_data(tmp_path_factory: pytest.TempPathFactory):
    """Three 2-second synthetic sequences (train / val / test), made once per session."""
    from e3dpsm.cli import main

    root = tmp_path_factory.mktemp("synth") / "data"
    code = main(["synth", "--out", str(root), "--sequences", "3", "--seconds", "2", "--seed", "11"])
    assert code == 0, "e3dpsm synth failed"
    return root


@pytest.fixture(scope="session")
def prepared_data(synthetic_data, tmp_path_factory: pytest.TempPathFactory):
    """The synthetic sequences as a prepared LNES cache (20 ms windows, 192 x 256)."""
    from e3dpsm.cli import main

    out = tmp_path_factory.mktemp("prepared") / "prep20"
    code = main(["prepare", "--data", str(synthetic_data), "--out", str(out), "--window-ms", "20", "--no-progress"])
    assert code == 0, "e3dpsm prepare failed"
    return out
