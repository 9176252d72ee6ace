"""Session-scoped data and runs shared by the training / evaluation / distributed tests.

The prepared folders are 96 x 128 (a uniform 0.2 resize of the sensor) so that the tiny
model trains a step in about a second on two cores."""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from e3dpsm.cli import main

if TYPE_CHECKING:
    import torch

HW = ("--height", "96", "--width", "128")
FAST_TRAIN = ("--variant", "tiny", "--seq-len", "3", "--batch-size", "2", "--warmup-steps", "1",
              "--lr", "3e-3", "--log-every", "1", "--no-progress", "--threads", "2")


@pytest.fixture(scope="session")
def small_raw_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("train_data")
    rc = main(["synth", "--out", str(root / "raw"), "--sequences", "3", "--seconds", "1.2", "--seed", "5",
               "--render-hz", "50", "--render-scale", "0.25", "--workers", "1"])
    assert rc == 0
    return root / "raw"


@pytest.fixture(scope="session")
def prepared_small(small_raw_data: Path) -> Path:
    out = small_raw_data.parent / "prep20"
    assert main(["prepare", "--data", str(small_raw_data), "--out", str(out), "--no-progress", *HW]) == 0
    return out


@pytest.fixture(scope="session")
def prepared_small_40ms(small_raw_data: Path) -> Path:
    out = small_raw_data.parent / "prep40"
    assert main(["prepare", "--data", str(small_raw_data), "--out", str(out), "--window-ms", "40",
                 "--no-progress", *HW]) == 0
    return out


@pytest.fixture(scope="session")
def training_runs(prepared_small: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """full: 8 steps straight; resumed: 8 steps, stopped at 4 then resumed."""
    root = tmp_path_factory.mktemp("runs")
    data = ("--data", str(prepared_small), "--split", "all")
    assert main(["train", *data, "--out", str(root / "full"), "--steps", "8", *FAST_TRAIN]) == 0
    assert main(["train", *data, "--out", str(root / "resumed"), "--steps", "8", "--stop-at", "4", *FAST_TRAIN]) == 0
    shutil.copy(root / "resumed" / "checkpoint.pt", root / "step4.pt")
    assert main(["train", "--data", str(prepared_small), "--out", str(root / "resumed"), "--resume",
                 "--no-progress", "--variant", "tiny"]) == 0
    return {"full": root / "full", "resumed": root / "resumed", "step4": root / "step4.pt"}


def numpy_terms(student: dict[str, torch.Tensor], teacher: dict[str, torch.Tensor], eps: float) -> dict[str, float]:
    """The documented loss, written independently: Charbonnier distance per joint, in mm."""
    def charbonnier(a: np.ndarray, b: np.ndarray) -> float:
        out = np.empty(a.shape[:-1])
        for index in np.ndindex(*a.shape[:-1]):  # explicit loop over batch, frame, joint
            d = a[index].astype(np.float64) - b[index].astype(np.float64)
            out[index] = np.sqrt(d @ d + eps * eps) - eps
        return float(out.mean())

    s = {k: v.detach().numpy() for k, v in student.items()}
    t = {k: v.detach().numpy() for k, v in teacher.items()}
    return {"fused": charbonnier(s["pose"], t["pose"]),
            "direct": charbonnier(s["pose_direct"], t["pose_direct"]),
            "delta": charbonnier(s["pose_delta"][:, 1:], t["pose_delta"][:, 1:])}
