"""`e3dpsm prune`: structured pruning of a checkpoint to a MACs or measured latency target,
recovered by distillation from the unpruned model."""
from __future__ import annotations

import argparse
import os

from e3dpsm.cli._common import add_force, add_threads, positive_float, positive_int


def _latency(text: str) -> tuple[str, float]:
    """'7.5' (ms) or '60%' (of the unpruned step); range checks are PruneConfig's (one line)."""
    try:
        return ("pct", float(text[:-1])) if text.endswith("%") else ("ms", float(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected milliseconds (7.5) or a percentage (60%), got {text!r}") from None


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "prune", help="structured pruning to a MACs or latency target, recovered by distillation",
        description="Remove channels and blocks of a trained model (residual hidden widths, feed-forward "
        "widths, S5 state size, whole residual branches and deformable blocks) in rounds: each round "
        "plans its cuts by their measured damage per millisecond the latency model (a per-unit ONNX "
        "Runtime profile of the exported step) says they save, cuts them physically, recovers by "
        "distillation from the unpruned model, then exports and times the step side by side with the "
        "unpruned one. Writes DIR/checkpoint.pt (rebuilds alone), DIR/report.md, DIR/report.json, "
        "DIR/front.png and the round graphs DIR/graphs/round<k>.onnx.")
    p.add_argument("--checkpoint", required=True, help="trained checkpoint to prune (it is also the teacher)")
    p.add_argument("--data", help="prepared folder for the distillation (labels optional); required but with --replay")
    p.add_argument("--out", required=True, help="output folder (must not exist unless --force)")
    p.add_argument("--target-macs", type=float, default=None,
                   help="fraction of the unpruned MACs to reach, in (0, 1), e.g. 0.5")
    p.add_argument("--target-latency-ms", type=_latency, default=None, metavar="MS|PCT%",
                   help="fp32 step (ms, batch 1, --threads) to reach, met as measured on --target-runtime; "
                   "'60%%' means 60%% of the unpruned step measured at the start")
    p.add_argument("--target-runtime", choices=("onnxruntime", "openvino"), default="onnxruntime")
    p.add_argument("--replay", metavar="REPORT",
                   help="instead of pruning: rebuild the model of an earlier `prune --steps 0` run's report.json "
                        "from --checkpoint (the same cuts pick the same channels) and write DIR/checkpoint.pt "
                        "unrecovered, e.g. to distil it on another machine")
    p.add_argument("--steps", type=int, default=300, help="distillation steps per round (default 300; 0: none)")
    p.add_argument("--rounds", type=positive_int, default=3, help="planned rounds (default 3)")
    p.add_argument("--extra-rounds", type=int, default=2,
                   help="further rounds while a latency target is missed as measured (default 2)")
    p.add_argument("--budget-pct", type=positive_float, default=None,
                   help="stop once held-out MPJPE exceeds the unpruned model's by more than this (%%)")
    p.add_argument("--labels", choices=("none", "gt"), default="none",
                   help="distillation targets: the teacher's poses only (none), or plus the labels (gt)")
    p.add_argument("--lr", type=positive_float, default=5e-4, help="distillation peak learning rate (default 5e-4)")
    p.add_argument("--shrink", type=float, default=0.5, help="a narrowing candidate keeps this fraction (default 0.5)")
    p.add_argument("--eval-data", default=None, help="held-out prepared folder (default --data)")
    p.add_argument("--eval-split", default="all", help="split of --eval-data to evaluate (default all)")
    p.add_argument("--eval-frames", type=positive_int, default=1000, help="held-out frames per sequence (default 1000)")
    p.add_argument("--timing-steps", type=positive_int, default=200, help="timed steps per graph (default 200)")
    p.add_argument("--no-int8", action="store_true", help="skip the INT8 graphs of the unpruned and chosen models")
    add_threads(p, "torch and runtime threads")
    p.add_argument("--seed", type=int, default=0)
    add_force(p)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.compress.prune import PruneConfig
    from e3dpsm.compress.run import run_prune
    from e3dpsm.errors import ConfigError
    from e3dpsm.utils.io import refuse_existing_output

    if args.replay:
        return _replay(args)
    if not args.data:
        raise ConfigError("prune needs --data (the prepared folder to distil on), unless it replays a report (--replay)")
    config = PruneConfig(
        target_macs=args.target_macs, target_runtime=args.target_runtime,
        target_latency_ms=args.target_latency_ms[1] if args.target_latency_ms and args.target_latency_ms[0] == "ms" else None,
        target_latency_pct=args.target_latency_ms[1] if args.target_latency_ms and args.target_latency_ms[0] == "pct" else None,
        rounds=args.rounds, extra_rounds=args.extra_rounds, shrink=args.shrink, steps=args.steps,
        labels=args.labels, budget_pct=args.budget_pct, threads=args.threads or os.cpu_count() or 1, seed=args.seed,
        timing_steps=args.timing_steps, eval_frames=args.eval_frames, lr=args.lr,
    )
    refuse_existing_output(args.out, args.force)  # before the long run, not after it
    result = run_prune(args.checkpoint, args.data, args.out, config, eval_data=args.eval_data or args.data,
                       eval_split=args.eval_split, int8=not args.no_int8, force=args.force,
                       progress=not args.no_progress)
    rows = result["front"]
    best = rows[result["best"]]
    print(f"round {result['best']}: MACs {best['macs_fraction']:.3f} of unpruned, ORT fp32 step {best['ort_fp32']:.2f} ms "
          f"(unpruned {rows[0]['ort_fp32']:.2f} ms), held-out MPJPE {best['mpjpe_mm']:.2f} mm "
          f"({best['mpjpe_change_pct']:+.2f}%); target {'met' if result['met'] else 'NOT met'} -> {args.out}")
    return 0 if result["met"] else 1


def _replay(args: argparse.Namespace) -> int:
    from e3dpsm.compress.replay import replay_prune_report
    from e3dpsm.errors import ConfigError

    if args.target_macs is not None or args.target_latency_ms is not None:
        raise ConfigError("--replay rebuilds the report's model; it takes no --target-macs / --target-latency-ms")
    result = replay_prune_report(args.checkpoint, args.replay, args.out, force=args.force)
    print(f"replayed {result['rounds']} round(s) of {args.replay}: {result['params']:,} parameters, "
          f"{result['macs_fraction']:.3f} of the MACs, unrecovered -> {result['checkpoint']}")
    return 0
