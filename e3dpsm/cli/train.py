"""`e3dpsm train`: train a variant (or one of the paper's ablations) on a prepared folder.
Runs alone or under `torchrun --nproc_per_node=K` (DistributedDataParallel)."""
from __future__ import annotations

import argparse
import sys

from e3dpsm.training.ablations import ABLATIONS
from e3dpsm.cli._common import add_threads, add_force
from e3dpsm.utils.env import DEVICE_CHOICES


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "train", help="train E-3DPSM on a prepared folder (bidirectional, the paper's losses)",
        description="Train a model variant with the paper's losses (3D, delta, 2D through the fisheye, "
        "bone length, bone orientation) on windows of N consecutive frames, bidirectional S5. "
        "Writes RUN_DIR/checkpoint.pt, RUN_DIR/log.jsonl and RUN_DIR/report.json. Under torchrun "
        "every rank trains a share of each batch; rank 0 writes.",
    )
    p.add_argument("--variant", default="small", help="model variant: paper, released, small, tiny (default small); "
                   "on --resume it must match the checkpoint")
    p.add_argument("--ablation", default="full", choices=list(ABLATIONS), help="paper ablation (default full)")
    p.add_argument("--data", required=True, help="prepared folder (e3dpsm prepare)")
    p.add_argument("--out", required=True, help="run folder")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="optimizer steps in total")
    length.add_argument("--epochs", type=float, help="epochs in total (an epoch covers every training frame once)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    add_force(p)
    p.add_argument("--init-from", metavar="CKPT",
                   help="fine-tune: start from this checkpoint's weights (same variant and frame size)")
    p.add_argument("--qat", action="store_true",
                   help="quantisation-aware: simulate the INT8 graph's rounding while training (with --init-from "
                        "and a small --lr, e.g. 1e-4, for a few hundred steps); the checkpoint stays float; "
                        "BatchNorm statistics stay the checkpoint's")
    p.add_argument("--qat-full-integer", action="store_true",
                   help="with --qat: simulate the full-integer graph (quantize --exclude none), recurrent "
                        "groups included, instead of the default graph that keeps them in float")
    p.add_argument("--seq-len", type=int, default=40, help="frames per training window N (default 40)")
    p.add_argument("--batch-size", type=int, default=4, help="windows per step and rank (default 4)")
    p.add_argument("--lr", type=float, default=1e-3, help="peak Adam learning rate (default 1e-3)")
    p.add_argument("--warmup-steps", type=int, default=50, help="linear warm-up steps before the cosine decay")
    p.add_argument("--clip-norm", type=float, default=1.0, help="gradient-norm clip (default 1.0)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", default="train", help="split to train on, or 'all' (default train)")
    p.add_argument("--mask-invisible", action="store_true", help="skip occluded joints in the 2D loss")
    p.add_argument("--no-direct-supervision", action="store_true",
                   help="supervise only the fused pose (paper) instead of fused + direct")
    p.add_argument("--log-every", type=int, default=10)
    p.add_argument("--save-every", type=int, default=200)
    p.add_argument("--stop-at", type=int, help="stop after this step, leaving a resumable checkpoint")
    p.add_argument("--device", default="auto", choices=DEVICE_CHOICES)
    add_threads(p, "torch CPU threads per process")
    p.add_argument("--num-workers", type=int, default=0, help="data-loader worker processes (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import torch

    from e3dpsm.errors import ConfigError
    from e3dpsm.training.ablations import ablation_overrides
    from e3dpsm.training.trainer import RunOptions, TrainArgs, train

    for name in ("seq_len", "batch_size", "log_every", "save_every"):
        if getattr(args, name) < 1:
            raise ConfigError(f"--{name.replace('_', '-')} must be at least 1")
    if args.steps is not None and args.steps < 1:
        raise ConfigError("--steps must be at least 1")
    if not args.resume and args.steps is None and args.epochs is None:
        raise ConfigError("give --steps or --epochs for a new run")
    if args.init_from and args.resume:
        raise ConfigError("--init-from starts a new run; drop it with --resume (the run continues from its own checkpoint)")
    if args.init_from and args.ablation != "full":
        raise ConfigError("--init-from takes the checkpoint's architecture; drop --ablation")
    if args.threads:
        torch.set_num_threads(args.threads)
    from e3dpsm.models import list_models

    if args.variant not in list_models():
        raise ConfigError(f"unknown variant {args.variant!r}; choose from {list_models()}")
    train_args = TrainArgs(
        variant=args.variant, steps=args.steps, epochs=args.epochs, seq_len=args.seq_len,
        batch_size=args.batch_size, lr=args.lr, warmup_steps=args.warmup_steps, clip_norm=args.clip_norm,
        seed=args.seed, split=args.split, overrides=ablation_overrides(args.ablation),
        supervise_direct=not args.no_direct_supervision, mask_invisible=args.mask_invisible,
        log_every=args.log_every, save_every=args.save_every, init_from=args.init_from, qat=args.qat,
        qat_full_integer=args.qat_full_integer,
    )
    opts = RunOptions(resume=args.resume, force=args.force, stop_at=args.stop_at, device=args.device,
                      num_workers=args.num_workers, progress=not args.no_progress and sys.stderr.isatty())
    report = train(train_args, args.data, args.out, opts)
    if report.get("rank", 0) != 0:  # under torchrun, rank 0 speaks
        return 0
    last = report.get("last", {})
    loss = f", loss {last['loss']:.4g}" if "loss" in last else ""
    print(f"trained {args.variant} to step {report['step']}/{report['total_steps']}{loss} "
          f"in {report['seconds']:.0f} s -> {args.out}")
    return 0
