"""`e3dpsm distill`: train a variant (fresh or a checkpoint, e.g. a pruned model) to reproduce a
trained teacher on prepared recordings, without labels."""
from __future__ import annotations

import argparse
import sys
from e3dpsm.cli._common import add_threads, add_force
from e3dpsm.utils.env import DEVICE_CHOICES


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "distill", help="distil a trained checkpoint into any variant, label-free",
        description="Train --student to reproduce --teacher's fused, direct and delta poses (mm) on "
        "windows of prepared LNES frames; the teacher is frozen, no labels are read unless --labels gt. "
        "Writes OUT/checkpoint.pt (rebuilds alone; teacher path and sha256 inside), OUT/report.json "
        "and OUT/report.md.",
    )
    p.add_argument("--teacher", required=True, metavar="CKPT", help="trained checkpoint to imitate")
    p.add_argument("--student", required=True, metavar="VARIANT|CKPT",
                   help="a registered variant (built fresh at the teacher's input size) or a checkpoint "
                        "(e.g. a pruned model) with the teacher's input size")
    p.add_argument("--data", required=True, help="prepared folder (e3dpsm prepare) at the teacher's frame size")
    p.add_argument("--out", required=True, help="run folder (refused if it holds a run, unless --force)")
    p.add_argument("--steps", type=int, default=500, help="optimizer steps (default 500)")
    p.add_argument("--labels", choices=("none", "gt"), default="none",
                   help="none: teacher targets only (default); gt: also the paper's loss on the labels")
    p.add_argument("--split", default="all", help="split to read, or 'all' (default all: no labels are read)")
    p.add_argument("--seq-len", type=int, default=16, help="frames per window (default 16)")
    p.add_argument("--batch-size", type=int, default=4, help="windows per step (default 4)")
    p.add_argument("--lr", type=float, default=1e-3, help="peak Adam learning rate (default 1e-3)")
    p.add_argument("--warmup-steps", type=int, default=20, help="linear warm-up steps before the cosine decay")
    p.add_argument("--seed", type=int, default=0, help="window sampling seed (default 0)")
    p.add_argument("--prior", choices=("keep", "teacher", "data"),
                   help="student pose prior: data = mean teacher pose on the data (default for a variant), "
                        "keep = the checkpoint's (default for a checkpoint), teacher = the teacher's")
    p.add_argument("--causal", action="store_true", help="run teacher and student causally (default: "
                   "bidirectional, as train does)")
    p.add_argument("--stream-windows", type=int, default=1, metavar="N",
                   help="with --causal: each batch lane carries its states over N consecutive windows of one "
                        "recording (truncated backpropagation through a stream; default 1: every window from "
                        "the initial states). The step graph runs long streams: e.g. --stream-windows 16")
    p.add_argument("--freeze-norm-stats", action="store_true",
                   help="keep the student's BatchNorm running statistics fixed (e.g. a pruned student)")
    p.add_argument("--qat", action="store_true",
                   help="quantisation-aware: the student trains with the INT8 graph's rounding simulated and "
                        "learned ranges, towards the float teacher (e.g. --student = --teacher, --lr 1e-4); the "
                        "checkpoint carries the ranges for quantize --ranges-from-checkpoint")
    p.add_argument("--qat-full-integer", action="store_true",
                   help="with --qat: simulate the full-integer graph (quantize --exclude none)")
    p.add_argument("--qat-range-init", choices=("mse", "minmax", "first-batch"), default="mse",
                   help="with --qat: where the learned ranges start: calibrated on windows of the data as "
                        "quantize --calibration mse|minmax would (default mse), or the first training batch's "
                        "min-max (first-batch; how the committed small_qat started)")
    p.add_argument("--qat-calibration-windows", type=int, default=32, metavar="N",
                   help="with --qat: windows of the data the ranges are calibrated on (default 32)")
    p.add_argument("--qat-float-outputs", choices=("none", "matmul", "all"),
                   help="with --qat: the quantize --float-outputs graph to simulate (default matmul with "
                        "--qat-full-integer, as quantize builds it, else none); recorded in the checkpoint")
    p.add_argument("--qat-weight-bits", type=int, choices=(7, 8),
                   help="with --qat: the weights' bits to simulate: those of the graph quantize builds for the "
                        "target (8; 7 for a CPU without int8 dot-product units, e.g. AVX2 only). Default: this host's")
    p.add_argument("--qat-ranges-only", action="store_true",
                   help="with --qat: learn the ranges alone, the student's weights frozen (use --student = "
                        "--teacher): its fp32 graph stays the teacher's, so the INT8 graph is held to the budget's "
                        "own reference")
    p.add_argument("--device", default="auto", choices=DEVICE_CHOICES,
                   help="where teacher and student run: auto (CUDA if available, default), cpu or cuda; "
                        "the checkpoint is written for the CPU either way")
    add_threads(p, "torch CPU threads")
    add_force(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.compress.distill import DistillConfig
    from e3dpsm.compress.distill_run import run_distill
    from e3dpsm.models import list_models

    fresh = args.student in list_models()
    config = DistillConfig(
        steps=args.steps, seq_len=args.seq_len, batch_size=args.batch_size, lr=args.lr,
        warmup_steps=args.warmup_steps, labels=args.labels, seed=args.seed, threads=args.threads,
        causal=args.causal, stream_windows=args.stream_windows, freeze_norm_stats=args.freeze_norm_stats, qat=args.qat,
        qat_full_integer=args.qat_full_integer, qat_range_init=args.qat_range_init,
        qat_calibration_windows=args.qat_calibration_windows, qat_float_outputs=args.qat_float_outputs,
        qat_weight_bits=args.qat_weight_bits, qat_ranges_only=args.qat_ranges_only,
        prior=args.prior or ("data" if fresh and not args.qat_ranges_only else "keep"),
    )
    report = run_distill(args.teacher, args.student, args.data, args.out, config, split=args.split,
                         force=args.force, progress=not args.no_progress and sys.stderr.isatty(), device=args.device)
    first, last = report["initial"], report["final"]
    print(f"distilled {report['teacher']['variant']} -> {report['student']['variant']} in {report['steps']} steps "
          f"({report['seconds']:.0f} s): fused {first['fused']:.1f} -> {last['fused']:.1f} mm from the teacher "
          f"-> {args.out}")
    return 0
