"""`e3dpsm quantize`: INT8 static (state-aware calibration), INT8 dynamic, INT8 weights only
(float arithmetic) or FP16."""
from __future__ import annotations

import argparse
import json

from e3dpsm.cli._common import add_force, add_threads, positive_float, positive_int


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    from e3dpsm.quantize.options import CALIBRATIONS, CHECK_RUNTIMES, MODES, TARGETS

    p = subparsers.add_parser(
        "quantize", help="quantise an exported step graph (int8, int8-dynamic, int8-weights, fp16)",
        description="Quantise the step graph. INT8 calibrates on frames paired with the states a continuous fp32 "
        "rollout carried into them; the S5 recurrences and the Kalman fusion stay float. --exclude auto tries the "
        "full-integer graph first and returns the fewest Conv/MatMul/Gemm to float until the task budget holds on "
        "the search split: MPJPE and PA-MPJPE at most +1%% and jitter +5%% over fp32; the written graph is then "
        "checked on the held-out split, which neither calibration nor search saw, and timed beside fp32. "
        "Writes DIR/step_<mode>.onnx, DIR/report.json and DIR/report.md (its first line is the verdict).")
    p.add_argument("--model", required=True, help="fp32 step graph from `e3dpsm export`")
    p.add_argument("--data", required=True, help="prepared folder (`e3dpsm prepare`) at the graph's window and size")
    p.add_argument("--out", required=True, help="output folder (must not exist unless --force)")
    p.add_argument("--mode", choices=MODES, default="int8")
    p.add_argument("--exclude", default="auto", help="nodes kept float: auto (full integer first, then the fewest "
                   "nodes back to float for the budget), none (every Conv/MatMul/Gemm 8-bit, recurrent ones too), "
                   "recurrent, or comma-separated group/node names added to the recurrent groups (default auto)")
    p.add_argument("--target", choices=TARGETS, default="auto", help="what the graph is for: a CPU kind (default "
                   "auto: this host's; avx2 and other hosts without int8 dot-product units get 7-bit weights) or npu "
                   "(16-bit activations allowed for nodes that leave 8 bits, as integer accelerators run them)")
    p.add_argument("--calibration", choices=CALIBRATIONS, default="minmax",
                   help="activation ranges: minmax, entropy, percentile (ONNX Runtime's rules) or mse (each tensor "
                   "the range with the lowest expected error on its histogram; default minmax)")
    p.add_argument("--frames", type=positive_int, default=200, help="calibration frames (default 200, minimum 16)")
    p.add_argument("--split", default="train", help="split the calibration frames come from (default train)")
    p.add_argument("--search-split", default="val", help="split the --exclude auto search measures on (default val)")
    p.add_argument("--holdout-split", default="test",
                   help="split of the final budget check, unseen by calibration and search (default test)")
    p.add_argument("--holdout-data", default=None, metavar="PREP",
                   help="another prepared folder for the final check (default: --data)")
    p.add_argument("--runtimes", nargs="+", choices=CHECK_RUNTIMES, default=["onnxruntime"],
                   help="runtimes the budget is checked and the graph timed on, the worst counting (default "
                   "onnxruntime; add openvino for a graph that must hold there too)")
    add_threads(p)
    add_force(p)
    _register_advanced(p.add_argument_group("advanced", "experiments; the defaults are the measured best"))
    p.set_defaults(func=run)
    return p


def _register_advanced(group: argparse._ArgumentGroup) -> None:
    from e3dpsm.quantize.options import FLOAT_OUTPUT_CHOICES, WEIGHT_ROUNDINGS

    group.add_argument("--budget-pct", type=positive_float, default=1.0,
                       help="allowed rise of MPJPE and PA-MPJPE over fp32, %% (default 1)")
    group.add_argument("--jitter-budget-pct", type=positive_float, default=5.0,
                       help="allowed rise of the fused pose's jitter over fp32, %% (default 5)")
    group.add_argument("--holdout-frames", type=int, default=0,
                       help="frames per held-out sequence of the final check (default 0: all)")
    group.add_argument("--search-frames", type=int, default=0,
                       help="frames per search sequence for each trial (default 0: all; fewer frames widen the "
                       "budget's interval, and the search returns more nodes to float than the budget needs)")
    group.add_argument("--rank-frames", type=positive_int, default=64,
                       help="frames per search sequence for the one-node trials that rank the nodes (default 64)")
    group.add_argument("--weight-rounding", choices=WEIGHT_ROUNDINGS, default="nearest",
                       help="8-bit weights to nearest, or up or down by AdaRound against each layer's output "
                       "(default nearest)")
    group.add_argument("--float-outputs", choices=FLOAT_OUTPUT_CHOICES, default="matmul",
                       help="Conv/MatMul/Gemm outputs left float where no quantised op reads them (default matmul: "
                       "free on ONNX Runtime; all: Conv too, slower there)")
    group.add_argument("--ranges-from-checkpoint", default=None, metavar="CKPT",
                       help="activation ranges learned by `distill --qat-ranges-only` (the graph must be CKPT's export)")
    group.add_argument("--timing-steps", type=positive_int, default=200,
                       help="steps the graph is timed beside fp32 for the verdict (default 200)")


def options_from_args(args: argparse.Namespace):
    from e3dpsm.quantize import Advanced, QuantizeOptions, TaskBudget

    budget = TaskBudget(mpjpe_pct=args.budget_pct, pa_mpjpe_pct=args.budget_pct, jitter_pct=args.jitter_budget_pct)
    advanced = Advanced(holdout_frames=args.holdout_frames, search_frames=args.search_frames,
                        rank_frames=args.rank_frames, weight_rounding=args.weight_rounding,
                        float_outputs=args.float_outputs, ranges_from_checkpoint=args.ranges_from_checkpoint,
                        timing_steps=args.timing_steps, budget=budget)
    return QuantizeOptions(mode=args.mode, exclude=args.exclude, target=args.target, calibration=args.calibration,
                           frames=args.frames, split=args.split, search_split=args.search_split,
                           holdout_split=args.holdout_split, holdout_data=args.holdout_data,
                           runtimes=tuple(dict.fromkeys(args.runtimes)), threads=args.threads, advanced=advanced)


def run(args: argparse.Namespace) -> int:
    from e3dpsm.quantize import quantize_graph

    report = quantize_graph(args.model, args.data, args.out, options_from_args(args), force=args.force)
    print(report["verdict"]["headline"])
    print(json.dumps({"out": args.out, "artifact": report["artifact"], "within_budget": report["verdict"]["within_budget"],
                      "bytes": report["written"]["bytes"], "size_ratio": round(report["written"]["size_ratio"], 4)}))
    return 0
