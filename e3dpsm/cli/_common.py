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


def add_threads(parser: argparse.ArgumentParser | Any, what: str = "intra-op threads of each runtime and of torch",
                default_means: str = "every core of this machine") -> None:
    """--threads N, one rule for every command: a positive count, default None (the runtime's
    own choice, every core); benchmarks that compare runs pass it explicitly."""
    parser.add_argument("--threads", type=positive_int, default=None, metavar="N",
                        help=f"{what} (default: {default_means})")


def add_force(parser: argparse.ArgumentParser | Any, target: str = "--out") -> None:
    """--force, one wording for every command that refuses to overwrite its output."""
    parser.add_argument("--force", action="store_true", help=f"replace what {target} already holds")
