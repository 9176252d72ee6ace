"""The PyTorch model behind the stepping protocol (`e3dpsm.runtime.stepping.Stepper`):
numpy in, numpy out, so parity and golden record drive the model and a graph alike. Lives
on the export side because it needs torch; the runtime never imports it."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import torch

from e3dpsm.runtime.stepping import StateArrays


class TorchStepper:
    """`model.step` in eval mode without gradients, batch and window length as given."""

    def __init__(self, model: Any) -> None:
        self.model = model.eval()

    def init_state(self, batch: int = 1) -> StateArrays:
        return {k: v.numpy() for k, v in self.model.init_state(batch).items()}

    @torch.no_grad()
    def step(self, lnes: np.ndarray, state: Mapping[str, np.ndarray],
             window_ms: float) -> tuple[dict[str, np.ndarray], StateArrays]:
        window = torch.tensor([window_ms], dtype=torch.float32)
        # from_numpy shares memory, so handing states back and forth copies nothing.
        out, new = self.model.step(torch.from_numpy(lnes), {k: torch.from_numpy(v) for k, v in state.items()}, window)
        return {k: v.numpy() for k, v in out.items()}, {k: v.numpy() for k, v in new.items()}
