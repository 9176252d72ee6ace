"""Checkpoints that rebuild their model alone: the config travels inside.

Loading never executes code: `torch.load(weights_only=True)` admits tensors and plain
containers only.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from e3dpsm.errors import CheckpointError, ConfigError
from e3dpsm.models import E3DPSM, E3DPSMConfig
from e3dpsm.utils.io import atomic_path

CHECKPOINT_FORMAT = "e3dpsm-checkpoint/1"


def save_checkpoint(path: str | os.PathLike, model: E3DPSM, **extra: Any) -> Path:
    """Write {format, config, model state, **extra} atomically. `extra` must hold tensors,
    numbers, strings and containers of them (e.g. optimizer state, step, metrics)."""
    payload = {"format": CHECKPOINT_FORMAT, "config": model.config.to_dict(), "model": model.state_dict(), **extra}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return Path(path)


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for truncated / foreign files
        raise CheckpointError(f"checkpoint {path} cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0][:200]}); "
                              "is it an e3dpsm checkpoint, completely written?") from exc
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not an e3dpsm checkpoint (expected format {CHECKPOINT_FORMAT!r})")
    return payload


def load_checkpoint(
    path: str | os.PathLike, *, variant: str | None = None, map_location: str | torch.device = "cpu"
) -> tuple[E3DPSM, dict[str, Any]]:
    """Rebuild the model of a checkpoint; `variant`, when given, must match its config."""
    payload = read_checkpoint(path)
    try:
        config = E3DPSMConfig.from_dict(payload["config"])
    except (ConfigError, KeyError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {path} carries an invalid config: {exc}") from exc
    if config.variant == "released" and "kalman_p0" not in payload["config"]:
        raise CheckpointError(f"{path} was imported before released checkpoints were converted to millimetres "
                              "(its poses are metres labelled mm); re-run e3dpsm import --released on the "
                              "original checkpoint")
    if variant is not None and config.variant != variant:
        raise CheckpointError(f"checkpoint {path} holds variant {config.variant!r}, not {variant!r}")
    model = E3DPSM(config)
    try:
        model.load_state_dict(payload["model"], strict=True)
    except (RuntimeError, KeyError) as exc:
        first = str(exc).splitlines()[0][:300]
        raise CheckpointError(f"checkpoint {path} does not match its {config.variant!r} config: {first}") from exc
    return model.to(map_location).eval(), payload
