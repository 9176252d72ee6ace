"""A toy `.tflite` for the INT8 LiteRT converter's pieces (tests/test_litert_int8_pieces.py),
converted by litert-torch in seconds: a convolution and fully connected layers named like the
step's scopes (a group of one operator, a group of two of different sizes), a pose head a
keep-float rule names, and a layer no group or rule names."""
from __future__ import annotations

import functools

import torch
from torch import nn


class FeedForward(nn.Module):
    def __init__(self, features_in: int, features_out: int) -> None:
        super().__init__()
        self.proj_in = nn.Linear(features_in, features_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj_in(x)


class Block(nn.Module):
    """Its layer two modules down, names with underscores: `ff_net.proj_in`, as the step's
    `ff.proj_in` (the narrowing's unit labels read that path)."""

    def __init__(self, features_in: int, features_out: int) -> None:
        super().__init__()
        self.ff_net = FeedForward(features_in, features_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.ff_net(x)


class Toy(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.stem = nn.Conv2d(2, 4, 3, padding=1)                      # 72 weights
        self.blocks = nn.ModuleList([Block(8, 4), Block(4, 16)])       # 32 and 64: the larger second
        self.extra = nn.Linear(4, 4)                                   # in no group
        self.direct_head = nn.Linear(16, 3)                            # a FLOAT_RULES pose head

    def forward(self, x: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = torch.cat([self.stem(x).mean((2, 3)), self.extra(s)], -1)
        h = torch.sigmoid(self.blocks[1](self.blocks[0](h)))
        return self.direct_head(h) + s[:, :3], h


def toy_model() -> Toy:
    torch.manual_seed(0)
    return Toy().eval()


@functools.lru_cache(maxsize=1)
def toy_litert() -> bytes:
    import litert_torch

    example = {"x": torch.randn(1, 2, 8, 8), "s": torch.randn(1, 4)}
    return bytes(litert_torch.convert(toy_model(), sample_kwargs=example).model_content())


def toy_feeds(count: int, outlier: float = 0.0) -> list[dict]:
    """Seeded calibration feeds by signature input name; `outlier` lands once in one feed."""
    generator = torch.Generator().manual_seed(1)
    feeds = [{"x": torch.randn(1, 2, 8, 8, generator=generator).numpy(),
              "s": torch.randn(1, 4, generator=generator).numpy()} for _ in range(count)]
    if outlier:
        feeds[-1]["x"][0, 0, 3, 3] = outlier
    return feeds
