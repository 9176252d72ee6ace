"""Models for tests that read weights (pruning's importance and replay)."""
from __future__ import annotations

import torch

import e3dpsm


def randomised_tiny(seed: int, **overrides) -> e3dpsm.E3DPSM:
    """The tiny at 64 x 96 with every parameter drawn from N(0, 1) (seeded): distinct channel
    scores, signs that matter; `overrides` change its config."""
    model = e3dpsm.create_model("tiny", height=64, width=96, **overrides).eval()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=gen))
    return model


def converter_tiny() -> e3dpsm.E3DPSM:
    """The tiny at 32 x 64 (the smallest frame its four stages take), seeded, in eval mode: the
    model the converters' pieces files export, lower or read a contract from, in seconds."""
    torch.manual_seed(0)
    return e3dpsm.create_model("tiny", height=32, width=64).eval()
