"""A thin module that turns `model.step` into the positional signature exporters need:
(lnes, window_ms, *states) -> (pose, pose_direct, pose_delta, *new_states), in the order
of the I/O spec, which itself follows `state_spec()`."""
from __future__ import annotations

import torch
from torch import nn

from e3dpsm.models import OUTPUT_NAMES, E3DPSM


class StepGraph(nn.Module):
    def __init__(self, model: E3DPSM) -> None:
        super().__init__()
        self.model = model
        self.state_names = [s.name for s in model.state_spec()]

    def forward(self, lnes: torch.Tensor, window_ms: torch.Tensor, *states: torch.Tensor) -> tuple[torch.Tensor, ...]:
        outputs, new_state = self.model.step(lnes, dict(zip(self.state_names, states)), window_ms)
        return (*(outputs[k] for k in OUTPUT_NAMES), *(new_state[n] for n in self.state_names))

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        cfg = self.model.config
        device = next(self.model.parameters()).device
        lnes = torch.zeros(batch, cfg.in_channels, cfg.height, cfg.width, device=device)
        window = torch.full((batch,), cfg.train_window_ms, device=device)
        state = self.model.init_state(batch, device)
        return (lnes, window, *(state[n] for n in self.state_names))
