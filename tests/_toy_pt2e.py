"""A toy shaped like the step wrapper for PT2E with XNNPACK's quantizer: the quantised scopes'
module paths (`model.stem`, `model.stages.N`, `model.ssm`, `model.decoder`), a recurrent type
inside one (ToyRecurrent, standing in for S5), a head outside them all, and the ops the
quantizer leaves alone (a scalar product, a sum, a concatenation)."""
from __future__ import annotations

import torch
from torch import nn


class ToyRecurrent(nn.Module):
    """Stands in for S5 (a type the quantizer leaves float wherever it sits)."""

    def __init__(self) -> None:
        super().__init__()
        self.lin = nn.Linear(8, 8)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.lin(x)


class ToySSM(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.proj, self.rec = nn.Linear(8, 8), ToyRecurrent()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.rec(self.proj(x))


class ToyModel(nn.Module):
    """The quantised scopes' names, a recurrent type inside one, a head outside them all, and
    the ops the quantizer must leave alone: a scalar product, a sum, a concatenation."""

    def __init__(self) -> None:
        super().__init__()
        self.stem = nn.Conv2d(1, 4, 3, padding=1)
        self.stages = nn.ModuleList([nn.Conv2d(4, 4, 1), nn.Conv2d(4, 8, 1)])
        self.ssm, self.decoder, self.direct_head = ToySSM(), nn.Linear(8, 8), nn.Linear(8, 3)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.stages[1](self.stages[0](self.stem(x)))
        v = self.decoder(self.ssm(h.mean((2, 3)))) * 0.5
        return self.direct_head(v + 1.0), torch.cat([v, v], -1)


class ToyWrapper(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.model = ToyModel()

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.model(x)


def toy_program() -> tuple[torch.export.ExportedProgram, tuple[torch.Tensor]]:
    """The toy exported (seeded, eval) and its example input."""
    torch.manual_seed(0)
    wrapper = ToyWrapper().eval()
    example = (torch.randn(1, 1, 8, 8),)
    return torch.export.export(wrapper, example, strict=False), example
