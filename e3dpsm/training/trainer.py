"""The training loop behind `e3dpsm train` (single process or torchrun/DDP).

Run folder (written by rank 0 only):
    RUN_DIR/checkpoint.pt  latest checkpoint: model + config (rebuilds alone), optimizer,
                           scheduler, step, RNG state, training args, data window_ms
    RUN_DIR/log.jsonl      one JSON object per logged step (losses, lr, grad norm, speed)
    RUN_DIR/report.json    report header + args + final figures, at the end of a run
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from e3dpsm.camera import ee3d_default, sensor_to_frame_scale
from e3dpsm.checkpoint import load_checkpoint, save_checkpoint
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import CheckpointError, ConfigError, OutputExistsError
from e3dpsm.models import create_model
from e3dpsm.training.data import WindowDataset, epoch_size, mean_pose_mm, seeded_batches
from e3dpsm.training.distributed import DistContext, setup_distributed, teardown, wrap_model
from e3dpsm.training.losses import LossWeights, PoseLoss
from e3dpsm.training.projection import FisheyeProjection
from e3dpsm.training.qat import (CALIBRATION_WINDOWS, QATConfig, attach_fake_quant, calibrate_on_windows,
                                 check_qat_flags, freeze_batchnorm_stats)
from e3dpsm.training.schedule import WarmupCosine
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic


CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "log.jsonl"
REPORT_NAME = "report.json"
# Each rank writes the digest of its parameters into this folder at the end of a run;
# the distributed test compares them.
PARAM_DUMP_ENV = "E3DPSM_DUMP_PARAMS_DIR"


@dataclass
class TrainArgs:
    """Everything that defines a run; stored in the checkpoint and reused on --resume."""

    variant: str = "small"
    steps: int | None = None
    epochs: float | None = None
    seq_len: int = 40
    batch_size: int = 4
    lr: float = 1e-3
    warmup_steps: int = 50
    min_lr_ratio: float = 0.05
    clip_norm: float = 1.0
    seed: int = 0
    split: str = "train"
    overrides: dict[str, Any] = field(default_factory=dict)  # E3DPSMConfig fields (ablations)
    weights: dict[str, float] = field(default_factory=lambda: LossWeights().to_dict())
    supervise_direct: bool = True
    mask_invisible: bool = False
    log_every: int = 10
    save_every: int = 200
    # Fine-tuning: start from this checkpoint's weights (and pose prior) instead of a fresh init.
    init_from: str | None = None
    # Quantisation-aware: train with the INT8 graph's rounding simulated (training/qat.py).
    qat: bool = False
    # --qat: simulate the full-integer graph (`quantize --exclude none`) instead of the default
    # one, whose recurrent groups stay float (training/qat.py QATConfig.full_integer).
    qat_full_integer: bool = False

    def __post_init__(self) -> None:
        check_qat_flags(self.qat, self.qat_full_integer)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainArgs":
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


@dataclass(frozen=True)
class RunOptions:
    """How to run (not part of the run's identity)."""

    resume: bool = False
    force: bool = False
    stop_at: int | None = None  # leave after this step with a resumable checkpoint
    device: str = "auto"
    num_workers: int = 0
    progress: bool = True


def steps_per_epoch(dataset: WindowDataset, args: TrainArgs, world_size: int) -> tuple[int, int]:
    """(optimizer steps per epoch, windows per epoch): `epoch_size` at the run's batch size."""
    return epoch_size(dataset, args.batch_size, world_size)


def _total_steps(args: TrainArgs, epoch_steps: int) -> int:
    if args.steps is not None:
        return int(args.steps)
    if args.epochs is not None:
        return max(1, int(round(args.epochs * epoch_steps)))
    raise ConfigError("give --steps or --epochs")


def _prepare_run_dir(out: Path, opts: RunOptions, ctx: DistContext) -> None:
    ckpt = out / CHECKPOINT_NAME
    if opts.resume:
        if not ckpt.is_file():
            raise CheckpointError(f"--resume: {ckpt} does not exist; start without --resume")
        return
    if ckpt.exists() or (out / LOG_NAME).exists():
        if not opts.force:
            raise OutputExistsError(f"run folder {out} holds a run; pass --resume to continue it or --force to restart")
        if ctx.is_main:
            for name in (CHECKPOINT_NAME, LOG_NAME, REPORT_NAME):
                (out / name).unlink(missing_ok=True)
    if ctx.is_main:
        out.mkdir(parents=True, exist_ok=True)


def _trim_log(path: Path, step: int) -> None:
    """On resume, drop log lines from steps after the checkpoint (they will be redone)."""
    if not path.is_file():
        return
    kept = [line for line in path.read_text(encoding="utf-8").splitlines()
            if line.strip() and json.loads(line).get("step", 0) <= step]
    path.write_text("".join(line + "\n" for line in kept), encoding="utf-8")


def _param_digest(model: torch.nn.Module) -> dict[str, Any]:
    digest = hashlib.sha256()
    total = 0.0
    # Parameters only: on CPU each rank's BatchNorm running statistics follow its own batches.
    for name, p in sorted(model.named_parameters()):
        data = p.detach().cpu().contiguous()
        digest.update(name.encode())
        digest.update(data.numpy().tobytes())
        if data.is_floating_point():
            total += float(data.double().sum())
    return {"sha256": digest.hexdigest(), "sum": total}


def pose_criterion(data: PreparedData, weights: LossWeights = LossWeights(), *, supervise_direct: bool = True,
                   mask_invisible: bool = False) -> PoseLoss:
    """The paper's loss for a prepared folder: its 2D term projects through the EE3D fisheye
    scaled from the sensor to the folder's frame size."""
    frame_scale = sensor_to_frame_scale(tuple(data.meta.get("sensor_hw", (480, 640))), (data.height, data.width))
    return PoseLoss(FisheyeProjection(ee3d_default(), frame_scale), weights,
                    supervise_direct=supervise_direct, mask_invisible=mask_invisible)


def train(args: TrainArgs, data_dir: str | os.PathLike, out: str | os.PathLike, opts: RunOptions) -> dict[str, Any]:
    """Train (or resume) a run; returns the final report (rank 0's view)."""
    ctx = setup_distributed(opts.device)
    try:
        return _train(args, Path(data_dir), Path(out), opts, ctx)
    finally:
        teardown(ctx)


def _train(args: TrainArgs, data_dir: Path, out: Path, opts: RunOptions, ctx: DistContext) -> dict[str, Any]:
    _prepare_run_dir(out, opts, ctx)
    data = PreparedData.open(data_dir)
    payload: dict[str, Any] | None = None
    if opts.resume:
        model, payload = load_checkpoint(out / CHECKPOINT_NAME, variant=args.variant)
        stored = TrainArgs.from_dict(payload.get("train_args", {}))
        # The run's identity comes from the checkpoint; only its length may change.
        stored.steps, stored.epochs = (args.steps, args.epochs) if (args.steps or args.epochs) else (stored.steps, stored.epochs)
        args = stored
        data.check_compatible(window_ms=float(payload["window_ms"]))
    elif args.init_from:
        model, init_payload = load_checkpoint(args.init_from, variant=args.variant)
        if "window_ms" in init_payload:
            data.check_compatible(window_ms=float(init_payload["window_ms"]))
    else:
        overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in args.overrides.items()}
        # The model takes the frame size the data was prepared at.
        model = create_model(args.variant, **{**overrides, "train_window_ms": data.window_ms,
                                              "height": data.height, "width": data.width})
    data.check_compatible(height=model.config.height, width=model.config.width)
    sequences = data.split(args.split)
    dataset = WindowDataset(sequences, args.seq_len)
    if payload is None and not args.init_from:
        model.set_pose_prior(torch.from_numpy(mean_pose_mm(sequences)))
    # QAT: the graph's quantised tensors are found on the CPU model (it is exported once);
    # a resumed run takes its learned ranges back from the checkpoint.
    fake_quant = attach_fake_quant(model.train(), QATConfig(full_integer=args.qat_full_integer)) if args.qat else None
    if fake_quant and payload is not None and payload.get("qat_ranges"):
        fake_quant.load_ranges(payload["qat_ranges"])
    elif fake_quant and fake_quant.config.range_init != "first-batch":
        calibrate_on_windows(fake_quant, model, dataset, CALIBRATION_WINDOWS, data.window_ms, causal=False,
                             rule=fake_quant.config.range_init)  # as training runs them: bidirectional
    model.to(ctx.device).train()
    if fake_quant:
        # BatchNorm keeps the fine-tuned checkpoint's running statistics: small QAT batches
        # would otherwise re-estimate them from fake-quantised activations, and the graph
        # folds whatever they end at (Jacob et al. 2018 freeze them too).
        freeze_batchnorm_stats(model)
        fake_quant.quantizers.to(ctx.device)
    trained = wrap_model(model, ctx)

    epoch_steps, _ = steps_per_epoch(dataset, args, ctx.world_size)
    total_steps = _total_steps(args, epoch_steps)
    param_groups = [{"params": list(model.parameters())}]
    if fake_quant:
        param_groups.append({"params": fake_quant.parameters(), "lr": args.lr * fake_quant.config.range_lr_scale})
    optimizer = torch.optim.Adam(param_groups, lr=args.lr)
    schedule = WarmupCosine(total_steps, min(args.warmup_steps, max(1, total_steps // 10)), args.min_lr_ratio)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, schedule)
    start_step = 0
    if payload is not None:
        optimizer.load_state_dict(payload["optimizer"])
        scheduler.load_state_dict(payload["scheduler"])
        scheduler.lr_lambdas = [schedule] * len(optimizer.param_groups)  # a changed --steps stretches the schedule
        start_step = int(payload["step"])
        if ctx.is_main:
            torch.set_rng_state(payload["rng_torch"])
            _trim_log(out / LOG_NAME, start_step)
    if payload is None or not ctx.is_main:
        torch.manual_seed(args.seed * 1000 + ctx.rank + 7919 * start_step)

    criterion = pose_criterion(data, LossWeights(**args.weights), supervise_direct=args.supervise_direct,
                               mask_invisible=args.mask_invisible).to(ctx.device)

    def checkpoint(step: int) -> None:
        if ctx.is_main:
            qat = {"qat_ranges": fake_quant.ranges_payload()} if fake_quant else {}
            with fake_quant.removed() if fake_quant else contextlib.nullcontext():
                save_checkpoint(out / CHECKPOINT_NAME, model, **qat, optimizer=optimizer.state_dict(),
                                scheduler=scheduler.state_dict(), step=step, rng_torch=torch.get_rng_state(),
                                train_args=args.to_dict(), window_ms=data.window_ms, data=str(data_dir))

    end_step = min(total_steps, opts.stop_at) if opts.stop_at is not None else total_steps
    bar = tqdm(total=total_steps, initial=start_step, desc=f"train {args.variant}", unit="step",
               disable=not (ctx.is_main and opts.progress), dynamic_ncols=True)
    started, last_terms, step = time.perf_counter(), {}, start_step
    window_start, window_steps = time.perf_counter(), 0
    if start_step < end_step:
        for step, batch in seeded_batches(dataset, args.batch_size, args.seed, start_step, rank=ctx.rank,
                                          world_size=ctx.world_size, num_workers=opts.num_workers):
            batch = {k: v.to(ctx.device, non_blocking=True) for k, v in batch.items()}
            outputs = trained(batch["lnes"], causal=False)
            loss, terms = criterion(outputs, batch["j3d_mm"], batch["j2d_px"], batch["visible"])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), args.clip_norm)
            optimizer.step()
            scheduler.step()
            step += 1
            window_steps += 1
            bar.update(1)
            if step % args.log_every == 0 or step == end_step:
                last_terms = _reduce_terms({"loss": loss.detach(), **{k: v.detach() for k, v in terms.items()}}, ctx)
                elapsed = time.perf_counter() - window_start
                record = {"step": step, "epoch": step / epoch_steps, "lr": scheduler.get_last_lr()[0],
                          "grad_norm": float(grad_norm), "steps_per_s": window_steps / max(elapsed, 1e-9), **last_terms}
                window_start, window_steps = time.perf_counter(), 0
                bar.set_postfix(loss=f"{last_terms['loss']:.3g}")
                if ctx.is_main:
                    with open(out / LOG_NAME, "a", encoding="utf-8") as fh:
                        fh.write(json.dumps(record) + "\n")
            if step % args.save_every == 0 and step != end_step:
                checkpoint(step)
            if step >= end_step:
                break
    bar.close()
    if fake_quant:
        fake_quant.remove()
    checkpoint(step)
    _dump_params(model, ctx)
    report = {
        **report_header("train", {"args": args.to_dict(), "data": str(data_dir), "world_size": ctx.world_size}),
        "step": step, "total_steps": total_steps, "finished": step >= total_steps, "steps_per_epoch": epoch_steps,
        "windows": len(dataset), "seconds": time.perf_counter() - started, "last": last_terms,
        "parameters": model.num_parameters(), "checkpoint": str(out / CHECKPOINT_NAME),
    }
    if ctx.is_main:
        write_json_atomic(out / REPORT_NAME, report)
    return {**report, "rank": ctx.rank}


def _reduce_terms(terms: dict[str, torch.Tensor], ctx: DistContext) -> dict[str, float]:
    """Mean over ranks of the logged loss terms (one all-reduce, on log steps only)."""
    names = sorted(terms)
    values = torch.stack([torch.as_tensor(terms[n], dtype=torch.float32, device=ctx.device) for n in names])
    if ctx.enabled:
        torch.distributed.all_reduce(values)
        values /= ctx.world_size
    return {n: float(v) for n, v in zip(names, values.cpu())}


def _dump_params(model: torch.nn.Module, ctx: DistContext) -> None:
    folder = os.environ.get(PARAM_DUMP_ENV)
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        write_json_atomic(Path(folder) / f"rank{ctx.rank}.json", _param_digest(model))
