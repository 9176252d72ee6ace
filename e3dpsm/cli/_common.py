"""Argument helpers shared by sub-commands."""
from __future__ import annotations

import argparse
from typing import Any

from e3dpsm.errors import ConfigError


def add_model_source(parser: argparse.ArgumentParser, *, required: bool = True) -> None:
    """--checkpoint CKPT | --variant NAME [--seed K]."""
    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument("--checkpoint", help="trained checkpoint (config inside)")
    group.add_argument("--variant", help="registered variant with initial weights (paper, released, small, tiny)")
    parser.add_argument("--seed", type=int, default=0, help="weight seed with --variant (default 0)")


def load_model_from_args(args: argparse.Namespace) -> Any:
    """The model named by --checkpoint or --variant/--seed, in eval mode."""
    import e3dpsm
    from e3dpsm.checkpoint import load_checkpoint

    if getattr(args, "checkpoint", None):
        model, _ = load_checkpoint(args.checkpoint)
        return model
    if not getattr(args, "variant", None):
        raise ConfigError("give --checkpoint CKPT or --variant NAME")
    return e3dpsm.create_model(args.variant, seed=args.seed).eval()


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {text}")
    return value
