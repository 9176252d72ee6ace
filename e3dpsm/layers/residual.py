"""Convolutional encoder: pre-activation residual blocks (BatchNorm, SiLU) and stride-2 stages."""
from __future__ import annotations

import torch
from torch import nn


class PreActResBlock(nn.Module):
    """BN-SiLU-conv3x3, BN-SiLU-conv3x3, plus the shortcut: the identity where the widths
    match, a 1x1 conv only where they differ, as released (docs/model.md#citations, Encoder
    stages).

    `hidden` (default `out_ch`): the width between the two convs, which pruning cuts; 0
    removes the residual branch, leaving the shortcut alone."""

    def __init__(self, in_ch: int, out_ch: int, hidden: int | None = None) -> None:
        super().__init__()
        hidden = out_ch if hidden is None else hidden
        self.hidden = hidden
        if hidden > 0:
            self.norm1 = nn.BatchNorm2d(in_ch)
            self.conv1 = nn.Conv2d(in_ch, hidden, 3, padding=1)
            self.norm2 = nn.BatchNorm2d(hidden)
            self.conv2 = nn.Conv2d(hidden, out_ch, 3, padding=1)
        self.shortcut = nn.Conv2d(in_ch, out_ch, 1) if in_ch != out_ch else nn.Identity()
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.hidden == 0:
            return self.shortcut(x)
        h = self.conv1(self.act(self.norm1(x)))
        h = self.conv2(self.act(self.norm2(h)))
        return self.shortcut(x) + h


class EncoderStage(nn.Module):
    """One pyramid stage as released: two residual blocks, a 3x3 stride-2 conv, one more
    residual block (docs/model.md#citations, Encoder stages; the paper's Sec. 4.1, Eq. 4 omits
    the third block)."""

    def __init__(
        self, in_ch: int, out_ch: int, extra_block: bool = True, hidden: tuple[int, ...] | None = None,
    ) -> None:
        super().__init__()
        hidden = hidden or (out_ch,) * (3 if extra_block else 2)
        self.block1 = PreActResBlock(in_ch, out_ch, hidden[0])
        self.block2 = PreActResBlock(out_ch, out_ch, hidden[1])
        self.down = nn.Conv2d(out_ch, out_ch, 3, stride=2, padding=1)
        self.block3 = PreActResBlock(out_ch, out_ch, hidden[2]) if extra_block else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.block3(self.down(self.block2(self.block1(x))))
