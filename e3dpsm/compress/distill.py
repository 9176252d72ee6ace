"""Label-free distillation: train a student variant to reproduce a frozen teacher's poses.

The targets are the teacher's three outputs (fused, direct and delta pose, mm) on the same
prepared LNES windows the student sees, both run the way `train` runs: windows of `seq_len`
frames through `forward_sequence(causal=False)`. Non-causal by default because the student
trains non-causally anyway (bidirectional S5, as `train` does); matching the teacher in the
same mode makes the targets a function the student can represent exactly (a copy of the
teacher is a fixed point: zero loss, zero gradient), and the student's causal (streaming)
behaviour then follows the teacher's, since both modes are the same network. `causal=True`
runs both causally instead.

The loss per output is the mean over batch, frames and joints of a Charbonnier distance in
millimetres, sqrt(|s - t|^2 + eps^2) - eps: the per-joint Euclidean error (MPJPE, the metric
the student is judged on) beyond a few eps, smooth near zero so the gradient vanishes at a
perfect match. A distance (not a squared error) gives every output a gradient of unit scale
per joint whatever its magnitude, so the delta pose (a few mm per frame) is not drowned by the
poses (errors of ~100 mm, 1e4 times larger when squared): equal weights (1, 1, 1) then give the
three heads equal pull. The delta term skips each window's first frame, which the Kalman
fusion ignores (a stream starts from the direct pose), as `train`'s delta loss does.
`labels="gt"` adds `train`'s PoseLoss on the labels, times `weight_labels`.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import torch
from tqdm import tqdm

from e3dpsm.data.prepared import ALL_SPLITS, PreparedData
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.training.data import WindowDataset, seeded_batches, stream_batches
from e3dpsm.training.qat import CALIBRATION_WINDOWS, QATConfig, check_qat_flags, freeze_batchnorm_stats
from e3dpsm.training.schedule import WarmupCosine

if TYPE_CHECKING:
    from e3dpsm.models.e3dpsm import E3DPSM

log = logging.getLogger(__name__)

LABEL_MODES: tuple[str, ...] = ("none", "gt")
# How the student's pose prior (the direct head's offset) starts: left as it is (a trained or
# pruned student), the teacher's, or the mean of the teacher's poses on the data (a fresh
# variant on the user's recordings: no labels needed).
PRIOR_MODES: tuple[str, ...] = ("keep", "teacher", "data")
# The config fields two models must share for one to learn from the other.
_SHARED_FIELDS: tuple[str, ...] = ("in_channels", "height", "width", "num_joints")


@dataclass(frozen=True)
class DistillConfig:
    steps: int = 500
    seq_len: int = 16
    batch_size: int = 4
    lr: float = 1e-3
    warmup_steps: int = 20
    min_lr_ratio: float = 0.05
    clip_norm: float = 1.0
    labels: str = "none"  # "none": teacher targets only; "gt": teacher targets + the usual pose loss on labels
    seed: int = 0
    threads: int | None = None  # torch.set_num_threads when given
    # Weights of the three teacher terms (module docstring: why equal) and of PoseLoss with
    # labels="gt" (PoseLoss carries the paper's own weights inside).
    weight_fused: float = 1.0
    weight_direct: float = 1.0
    weight_delta: float = 1.0
    weight_labels: float = 1.0
    charbonnier_mm: float = 1.0  # eps of the distance: quadratic below ~1 mm, linear above
    causal: bool = False  # run teacher and student causally (streaming) instead of bidirectionally
    # BatchNorm of the student in eval mode: its running statistics neither used from nor
    # updated by the batches. Default off, as in `train`: a fresh or pruned student needs
    # statistics of its own. On, a copy of the teacher is an exact fixed point.
    freeze_norm_stats: bool = False
    # Quantisation-aware distillation: the student trains with the INT8 graph's rounding
    # simulated and learned ranges (training/qat.py), towards the float teacher, which is
    # the measure the INT8 budget holds a graph to (distance to the fp32 poses). `qat_full_integer`
    # simulates the `quantize --exclude none` graph. Either freezes the student's BatchNorm
    # statistics. The checkpoint carries the learned ranges (`quantize --ranges-from-checkpoint`).
    qat: bool = False
    qat_full_integer: bool = False
    # Where the learned ranges start (training/qat.py QATConfig.range_init), and on how many
    # windows of the data ("mse", "minmax"), spread evenly over it.
    qat_range_init: str = "mse"
    qat_calibration_windows: int = CALIBRATION_WINDOWS
    qat_float_outputs: str | None = None  # training/qat.py QATConfig.float_outputs
    qat_weight_bits: int | None = None  # training/qat.py QATConfig.weight_bits (None: this host's)
    # With `qat`: learn the ranges alone, the student's weights frozen (LSQ's step sizes fitted
    # to the end loss, a post-training calibration): the fp32 graph stays the teacher's, so the
    # INT8 graph is held to the budget's own reference.
    qat_ranges_only: bool = False
    # Truncated backpropagation through streams (with `causal`): each batch lane carries its
    # states (teacher's and student's, detached) over this many consecutive windows of one
    # recording before it starts another. 1: every window starts from the initial states.
    # The step graph runs streams of thousands of frames: the trained `small`'s stage-1 S5
    # state grows for ~64 frames before it levels (max |state| 3.6 at frame 16, 8.9 at 64),
    # so a student trained on 16-frame windows from zero never sees the states, nor learns the
    # ranges, that its graph meets (QAT ranges learned so clipped them: docs/quantize.md).
    stream_windows: int = 1
    prior: str = "keep"  # one of PRIOR_MODES
    prior_windows: int = 64  # windows of teacher poses averaged for prior="data"
    log_every: int = 10

    def __post_init__(self) -> None:
        for name in ("steps", "seq_len", "batch_size", "log_every", "prior_windows"):
            if getattr(self, name) < 1:
                raise ConfigError(f"distill {name} must be at least 1, got {getattr(self, name)}")
        if self.seq_len < 2:
            raise ConfigError(f"distill seq_len must be at least 2 (the delta term needs two frames), got {self.seq_len}")
        if self.labels not in LABEL_MODES:
            raise ConfigError(f"distill labels must be one of {list(LABEL_MODES)}, got {self.labels!r}")
        check_qat_flags(self.qat, self.qat_full_integer)
        self.qat_config  # QATConfig refuses an unknown range start, float-outputs graph or weight bits
        if self.stream_windows < 1:
            raise ConfigError(f"distill stream_windows must be at least 1, got {self.stream_windows}")
        if self.stream_windows > 1 and not self.causal:
            raise ConfigError("distill --stream-windows carries states from window to window, which only a causal "
                              "run has: add --causal")
        if self.qat_ranges_only and not self.qat:
            raise ConfigError("distill --qat-ranges-only learns the QAT ranges alone: add --qat")
        if self.qat_ranges_only and self.prior != "keep":
            raise ConfigError(f"distill --qat-ranges-only keeps the student's weights and pose prior as they are; "
                              f"--prior {self.prior} would change the prior: use --prior keep")
        if self.qat_calibration_windows < 1:
            raise ConfigError(f"distill qat_calibration_windows must be at least 1, got {self.qat_calibration_windows}")
        if self.prior not in PRIOR_MODES:
            raise ConfigError(f"distill prior must be one of {list(PRIOR_MODES)}, got {self.prior!r}")
        if not self.lr > 0 or not self.charbonnier_mm > 0 or not self.clip_norm > 0:
            raise ConfigError("distill lr, charbonnier_mm and clip_norm must be positive")
        weights = (self.weight_fused, self.weight_direct, self.weight_delta, self.weight_labels)
        if any(not w >= 0 for w in weights) or not any(weights[:3]):
            raise ConfigError("distill weights must be non-negative, with at least one teacher term positive")

    @property
    def qat_config(self) -> QATConfig:
        """What `qat` fake-quantises (training/qat.py)."""
        return QATConfig(full_integer=self.qat_full_integer, range_init=self.qat_range_init,
                         float_outputs=self.qat_float_outputs, weight_bits=self.qat_weight_bits)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def check_pair(teacher: "E3DPSM", student: "E3DPSM") -> None:
    """ConfigError (one line) unless `student` can learn from `teacher`: a separate module
    with the same input (channels, height, width) and joints."""
    if student is teacher:
        raise ConfigError("the student is the teacher itself; distil into a copy (copy.deepcopy) or another variant")
    differ = [f"{f} {getattr(teacher.config, f)} vs {getattr(student.config, f)}" for f in _SHARED_FIELDS
              if getattr(teacher.config, f) != getattr(student.config, f)]
    if differ:
        raise ConfigError(f"teacher and student must share input size and joints (teacher vs student: "
                          f"{', '.join(differ)}); build the student at the teacher's input size")


def _charbonnier(pred: torch.Tensor, target: torch.Tensor, eps: float) -> torch.Tensor:
    """Mean over every leading axis of sqrt(|pred - target|^2 + eps^2) - eps, [..., 3] poses."""
    sq = ((pred - target) ** 2).sum(-1)
    return ((sq + eps * eps).sqrt() - eps).mean()


def distill_terms(student: Mapping[str, torch.Tensor], teacher: Mapping[str, torch.Tensor],
                  eps_mm: float = 1.0) -> dict[str, torch.Tensor]:
    """Unweighted terms (mm) between outputs [B, T, J, 3]: fused, direct, delta (frames >= 1)."""
    return {
        "fused": _charbonnier(student["pose"], teacher["pose"], eps_mm),
        "direct": _charbonnier(student["pose_direct"], teacher["pose_direct"], eps_mm),
        "delta": _charbonnier(student["pose_delta"][:, 1:], teacher["pose_delta"][:, 1:], eps_mm),
    }


def distill_loss(student: Mapping[str, torch.Tensor], teacher: Mapping[str, torch.Tensor],
                 config: DistillConfig) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """(weighted total, unweighted terms) of the teacher terms."""
    terms = distill_terms(student, teacher, config.charbonnier_mm)
    total = (config.weight_fused * terms["fused"] + config.weight_direct * terms["direct"]
             + config.weight_delta * terms["delta"])
    return total, terms


def _device(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device


@torch.no_grad()
def teacher_mean_pose(teacher: "E3DPSM", dataset: WindowDataset, config: DistillConfig,
                      window_ms: float | None = None) -> torch.Tensor:
    """Mean fused teacher pose [J, 3] (mm) over the first `prior_windows` windows the run draws:
    the label-free stand-in for `train`'s mean ground-truth pose."""
    total, count = torch.zeros(teacher.config.num_joints, 3, dtype=torch.float64), 0
    for _, batch in seeded_batches(dataset, config.batch_size, config.seed):
        pose = teacher.forward_sequence(batch["lnes"].to(_device(teacher)), causal=config.causal,
                                        window_ms=window_ms)["pose"]
        total += pose.double().sum(dim=(0, 1)).cpu()
        count += pose.shape[0] * pose.shape[1]
        if count >= config.prior_windows * config.seq_len:
            break
    return (total / count).float()


def distill(teacher: "E3DPSM", student: "E3DPSM", data_dir: str | os.PathLike, config: DistillConfig,
            *, split: str | None = None, progress: bool = True) -> dict[str, Any]:
    """Train `student` in place to reproduce `teacher` on prepared LNES windows (teacher frozen,
    eval mode, no grad). Returns a summary dict: steps, seconds, seconds_per_step, final and
    initial loss terms, a short loss log (every k steps).

    `split`: the prepared split to read, None for every sequence ("all": label-free
    distillation reads no labels, so every recording may serve; pass "train" to keep held-out
    sequences out). Both models keep their train/eval mode on return; the teacher's weights
    are never changed.
    """
    check_pair(teacher, student)
    if config.threads:
        torch.set_num_threads(config.threads)
    data = PreparedData.open(data_dir)
    data.check_compatible(height=student.config.height, width=student.config.width)
    split = split or ALL_SPLITS
    dataset = WindowDataset(data.split(split), config.seq_len)
    # Both run at the data's window length (the S5 discretisation takes it), whatever window
    # either was trained at; the same as `train` when they match.
    window_ms = data.window_ms
    criterion = None
    if config.labels == "gt":
        from e3dpsm.training.trainer import pose_criterion

        criterion = pose_criterion(data).to(_device(student))

    teacher_was_training, student_was_training = teacher.training, student.training
    trainable = [p for p in student.parameters() if p.requires_grad]
    teacher.eval()
    try:
        if config.qat_ranges_only:
            student.requires_grad_(False)  # for the run only: restored below
        prior_started = time.perf_counter()
        if config.prior == "teacher":
            student.set_pose_prior(teacher.pose_prior_mm.detach().cpu())
        elif config.prior == "data":
            student.set_pose_prior(teacher_mean_pose(teacher, dataset, config, window_ms))
        prior_seconds = time.perf_counter() - prior_started
        fake_quant = None
        if config.qat:
            from e3dpsm.training.qat import attach_fake_quant, calibrate_on_windows

            fake_quant = attach_fake_quant(student.train(), config.qat_config)
            range_start = {"rule": config.qat_range_init, "quantizers": len(fake_quant.quantizers), "calibrated": 0,
                           "weight_bits": fake_quant.weight_bits}
            if config.qat_range_init != "first-batch":
                # Calibrated on whole streams as training runs them: windows of every lane's
                # stream length, from the initial states, as many frames as the windows given.
                streams = WindowDataset(dataset.sequences, config.seq_len * config.stream_windows)
                count = max(min(4, config.qat_calibration_windows), -(-config.qat_calibration_windows // config.stream_windows))
                range_start["calibrated"] = calibrate_on_windows(
                    fake_quant, student, streams, count, window_ms, config.causal, config.qat_range_init)
                range_start["windows"], range_start["frames_per_window"] = count, streams.seq_len
                log.info("QAT: %d of %d learned ranges start from %s calibration on %d windows of %d frames",
                         range_start["calibrated"], len(fake_quant.quantizers), config.qat_range_init, count,
                         streams.seq_len)
        try:
            summary = _run(teacher, student, dataset, config, window_ms, criterion, progress, fake_quant)
            if fake_quant is not None:
                summary["qat_ranges"] = fake_quant.ranges_payload()
                summary["qat_range_start"] = range_start
        finally:
            if fake_quant is not None:
                fake_quant.remove()  # the plain student, its learned ranges in the summary
    finally:
        teacher.train(teacher_was_training)
        student.train(student_was_training)
        for parameter in trainable:
            parameter.requires_grad_(True)
    return {**summary, "prior": config.prior, "prior_seconds": prior_seconds, "split": split,
            "windows": len(dataset), "frames": dataset.frames_total(), "window_ms": window_ms,
            "data": str(data_dir), "config": config.to_dict()}


def restart_lanes(model: "E3DPSM", state: Mapping[str, torch.Tensor] | None,
                  fresh: torch.Tensor) -> dict[str, torch.Tensor]:
    """The states a streamed batch starts from: the carried ones, the initial ones in the
    lanes that start a new stream (`fresh`), all initial when nothing is carried yet."""
    initial = model.init_state(len(fresh))
    if state is None:
        return initial
    lanes = fresh.to(next(iter(initial.values())).device)
    return {k: torch.where(lanes.view(-1, *[1] * (v.dim() - 1)), initial[k], state[k]) for k, v in initial.items()}


def _run(teacher: "E3DPSM", student: "E3DPSM", dataset: WindowDataset, config: DistillConfig, window_ms: float,
         criterion: torch.nn.Module | None, progress: bool, fake_quant: Any = None) -> dict[str, Any]:
    student.train()
    if config.freeze_norm_stats or fake_quant is not None:
        freeze_batchnorm_stats(student)
    device, teacher_device = _device(student), _device(teacher)
    groups = [] if config.qat_ranges_only else [{"params": list(student.parameters())}]
    if fake_quant is not None:
        fake_quant.quantizers.to(device)
        groups.append({"params": list(fake_quant.parameters()), "lr": config.lr * fake_quant.config.range_lr_scale})
    # The ranges' gradients go unclipped beside the weights' (as `train --qat`), clipped when alone.
    clipped = groups[0]["params"]
    optimizer = torch.optim.Adam(groups, lr=config.lr)
    schedule = WarmupCosine(config.steps, min(config.warmup_steps, max(1, config.steps // 10)), config.min_lr_ratio)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, schedule)
    torch.manual_seed(config.seed * 1000)  # as `train` seeds a fresh single-process run

    log: list[dict[str, float]] = []
    initial: dict[str, float] = {}
    record: dict[str, float] = {}
    bar = tqdm(total=config.steps, desc=f"distill {teacher.config.variant} -> {student.config.variant}",
               unit="step", disable=not progress, dynamic_ncols=True)
    started = time.perf_counter()
    streaming = config.stream_windows > 1
    batches = (stream_batches(dataset, config.batch_size, config.seed, config.stream_windows) if streaming
               else ((step, batch, None) for step, batch in seeded_batches(dataset, config.batch_size, config.seed)))
    teacher_state: dict[str, torch.Tensor] | None = None
    student_state: dict[str, torch.Tensor] | None = None
    for step, batch, fresh in batches:
        lnes = batch["lnes"]  # labels stay untouched unless labels="gt"
        if streaming:
            teacher_state = restart_lanes(teacher, teacher_state, fresh)
            student_state = restart_lanes(student, student_state, fresh)
            with torch.no_grad():
                target, teacher_state = teacher.forward_sequence(
                    lnes.to(teacher_device), causal=True, state=teacher_state, window_ms=window_ms, return_state=True)
            outputs, carried = student.forward_sequence(lnes.to(device), causal=True, state=student_state,
                                                        window_ms=window_ms, return_state=True)
            student_state = {k: v.detach() for k, v in carried.items()}  # truncated: no gradient into the past
        else:
            with torch.no_grad():
                target = teacher.forward_sequence(lnes.to(teacher_device), causal=config.causal, window_ms=window_ms)
            outputs = student.forward_sequence(lnes.to(device), causal=config.causal, window_ms=window_ms)
        target = {k: v.to(device) for k, v in target.items()}
        loss, terms = distill_loss(outputs, target, config)
        if criterion is not None:
            label_loss, _ = criterion(outputs, *(batch[k].to(device) for k in ("j3d_mm", "j2d_px", "visible")))
            loss = loss + config.weight_labels * label_loss
            terms = {**terms, "labels": label_loss}
        if not torch.isfinite(loss):
            bad = [k for k, v in terms.items() if not torch.isfinite(v)]
            raise DataError(f"distillation loss is not finite at step {step + 1} (terms {bad}): NaN or inf in the "
                            "data (labels with --labels gt) or a learning rate too high (lower --lr)")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(clipped, config.clip_norm)
        lr = config.lr * schedule(scheduler.last_epoch)  # --lr's schedule (the ranges train at a multiple)
        optimizer.step()
        scheduler.step()
        record = {"step": step + 1, "lr": lr, "grad_norm": float(grad_norm), "loss": float(loss.detach()),
                  **{k: float(v.detach()) for k, v in terms.items()}}
        if step == 0:
            initial = record
        if (step + 1) % config.log_every == 0 or step + 1 == config.steps or step == 0:
            log.append(record)
            bar.set_postfix(loss=f"{record['loss']:.3g}")
        bar.update(1)
        if step + 1 >= config.steps:
            break
    bar.close()
    seconds = time.perf_counter() - started
    return {"steps": config.steps, "seconds": seconds, "seconds_per_step": seconds / config.steps,
            "initial": initial, "final": record, "log": log,
            "teacher": {"variant": teacher.config.variant, "parameters": teacher.num_parameters()},
            "student": {"variant": student.config.variant, "parameters": student.num_parameters()}}


__all__ = ["DistillConfig", "LABEL_MODES", "PRIOR_MODES", "check_pair", "distill", "distill_loss", "distill_terms",
           "teacher_mean_pose"]
