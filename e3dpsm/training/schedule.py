"""Learning-rate schedule: linear warm-up, then cosine decay to `min_ratio` x the base rate."""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class WarmupCosine:
    """Multiplier of the base learning rate at a step (a LambdaLR `lr_lambda`). A LambdaLR
    state dict stores this object's fields, plain numbers, so checkpoints stay loadable
    with `weights_only=True`."""

    total_steps: int
    warmup_steps: int
    min_ratio: float = 0.05

    def __call__(self, step: int) -> float:
        if step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        span = max(1, self.total_steps - self.warmup_steps)
        progress = min(1.0, (step - self.warmup_steps) / span)
        return self.min_ratio + (1.0 - self.min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))
