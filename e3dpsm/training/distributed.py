"""torchrun support: the same `e3dpsm train` runs alone or as K processes.

torchrun exports RANK / WORLD_SIZE / LOCAL_RANK (and the rendezvous address); their
presence switches on DistributedDataParallel, with gloo on CPU and nccl on CUDA.

BatchNorm: on CUDA the model is converted to SyncBatchNorm. PyTorch's SyncBatchNorm has no
CPU kernel, so on CPU each rank normalises with its own batch statistics; the weights stay
identical across ranks (gradients are all-reduced) and DDP broadcasts rank 0's running
statistics at every forward, so checkpoints (written by rank 0) are consistent.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn

from e3dpsm.errors import ConfigError
from e3dpsm.utils.env import DEVICE_CHOICES


@dataclass(frozen=True)
class DistContext:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def resolve_device(device: str = "auto") -> torch.device:
    """The single-process device for `--device`: "auto" (CUDA if available), "cpu" or "cuda"
    (ConfigError where CUDA is not available)."""
    if device not in DEVICE_CHOICES:
        raise ConfigError(f"--device must be one of {list(DEVICE_CHOICES)}, got {device!r}")
    use_cuda = torch.cuda.is_available() if device == "auto" else device == "cuda"
    if use_cuda and not torch.cuda.is_available():
        raise ConfigError("--device cuda was asked for, but CUDA is not available (a CPU build of torch, or no GPU): "
                          "use --device cpu")
    return torch.device("cuda" if use_cuda else "cpu")


def setup_distributed(device: str = "auto") -> DistContext:
    """Initialise the process group when launched by torchrun; a single-process context
    otherwise. `device`: "auto" (CUDA if available), "cpu" or "cuda"."""
    use_cuda = resolve_device(device).type == "cuda"
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return DistContext(device=torch.device("cuda" if use_cuda else "cpu"))
    try:
        rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    except (KeyError, ValueError) as exc:
        raise ConfigError(f"WORLD_SIZE={world_size} but RANK is missing or invalid: launch with torchrun") from exc
    if use_cuda:
        torch.cuda.set_device(local_rank)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if use_cuda else "gloo")
    device_obj = torch.device("cuda", local_rank) if use_cuda else torch.device("cpu")
    return DistContext(rank=rank, world_size=world_size, local_rank=local_rank, device=device_obj)


def wrap_model(model: nn.Module, ctx: DistContext) -> nn.Module:
    """The module to call in the training step (DDP-wrapped when distributed)."""
    if not ctx.enabled:
        return model
    if ctx.device.type == "cuda":
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
        return nn.parallel.DistributedDataParallel(model, device_ids=[ctx.local_rank])
    return nn.parallel.DistributedDataParallel(model)


def teardown(ctx: DistContext) -> None:
    if ctx.enabled and dist.is_initialized():
        dist.destroy_process_group()
