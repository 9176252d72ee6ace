"""`e3dpsm quantize`: INT8 static (state-aware calibration), INT8 dynamic or FP16."""
from __future__ import annotations

import argparse
import json

from e3dpsm.cli._common import positive_float, positive_int
from e3dpsm.utils.isa import ISA_KINDS


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "quantize", help="quantise an exported step graph (int8, int8-dynamic, fp16)",
        description="Quantise the step graph. INT8 static calibrates on frames of real sequences "
        "paired with the states a continuous FP32 rollout carried into them; the S5 recurrences "
        "and the Kalman fusion stay in float; --exclude auto searches which compute nodes to keep in float "
        "(int8: nodes ranked by their solo error, the fewest top-ranked; fp16: whole groups) until the "
        "held-out error is within --budget-pct and, by default, picks the fastest such graph "
        "(--objective). Writes DIR/step_<mode>.onnx, DIR/report.json, DIR/report.md and DIR/front.png.")
    p.add_argument("--model", required=True, help="fp32 step graph from `e3dpsm export`")
    p.add_argument("--data", required=True, help="prepared folder (`e3dpsm prepare`) at the graph's window and size")
    p.add_argument("--out", required=True, help="output folder (must not exist unless --force)")
    p.add_argument("--mode", choices=("int8", "int8-dynamic", "fp16"), default="int8")
    p.add_argument("--calibration", choices=("minmax", "entropy", "percentile", "mse"), default="minmax",
                   help="activation ranges: minmax, entropy and percentile apply one ONNX Runtime rule to every "
                   "tensor; mse gives each tensor the range with the lowest expected quantisation error on its "
                   "calibration histogram (min-max, percentiles or narrower; default minmax)")
    p.add_argument("--frames", type=positive_int, default=200, help="calibration frames (default 200, minimum 16)")
    p.add_argument("--exclude", default="auto",
                   help="float-kept nodes: auto (search), none, recurrent, or comma-separated group/node "
                   "names added to the recurrent groups (default auto)")
    p.add_argument("--budget-pct", type=positive_float, default=None,
                   help="--exclude auto: allowed held-out error (mean distance to the fp32 poses) relative to "
                   "fp32 MPJPE, in %% (default 1.0 for int8, 0.1 for fp16)")
    p.add_argument("--search-margin", type=float, default=None,
                   help="--exclude auto: share of the budget the search leaves unspent, so that the budget "
                   "holds on sequences the search never saw (default 0.25 for int8, 0 for fp16; the graph "
                   "is still held to the whole budget)")
    p.add_argument("--budget-reference", choices=("holdout", "lowest"), default="holdout",
                   help="what the budget is relative to: the fp32 MPJPE over the held-out frames (holdout, "
                   "default) or the lowest fp32 MPJPE of any one held-out or calibration sequence (lowest: for a "
                   "model whose error differs widely between sequences, so that the budget holds on an easy one)")
    p.add_argument("--runtimes", nargs="+", choices=("onnxruntime", "openvino"), default=["onnxruntime"],
                   help="the runtimes the budget is checked on: each trial graph of the search and the written "
                   "graph are measured on every one, the worst distance counting (default onnxruntime; add "
                   "openvino for a graph that must hold its budget there too: it fuses and rounds QDQ its own way)")
    p.add_argument("--search", choices=("nodes", "groups"), default=None,
                   help="--exclude auto: 'nodes' quantises each Conv/MatMul/Gemm alone to rank them by held-out "
                   "error, then keeps the fewest top-ranked in float that meet the budget (int8 default; one "
                   "trial per node); 'groups' adds whole module / op-type groups greedily (fp16 default)")
    p.add_argument("--objective", choices=("size", "latency", "accuracy"), default=None,  # quantize.front.OBJECTIVES
                   help="--exclude auto: among the candidate graphs within the budget pick the smallest (size, "
                   "the int8 default: the fewest nodes out of 8 bits whose nodes all fit at 16-bit activations "
                   "with 8-bit weights, one trial each), the fastest (latency, the default without int16; "
                   "candidates are timed side by side with the fp32 graph, with the nodes they keep out of 8 bits "
                   "in float) or the search's own choice, the fewest nodes out of 8 bits (accuracy). The graph "
                   "written is timed beside fp32 either way: report.md's verdict")
    p.add_argument("--timing-steps", type=positive_int, default=30,
                   help="--exclude auto: timed steps per candidate graph (default 30)")
    p.add_argument("--artifact-timing-steps", type=positive_int, default=200,
                   help="steps the written graph is timed beside fp32 for report.md's verdict, which gives the "
                   "speed-up with an 80%% interval, and a --objective latency pick beside the search's own choice "
                   "before it ships (default 200)")
    p.add_argument("--target-isa", choices=ISA_KINDS, default=None,
                   help="int8, int8-dynamic: the CPU kind the graph is for (default: this host's; see "
                   "machine.isa in any report); avx2 and other targets without int8 dot-product units get 7-bit "
                   "weights (int8-dynamic: U8 weights), as ONNX Runtime recommends for non-VNNI CPUs")
    p.add_argument("--equalize", action="store_true",
                   help="int8: fold SmoothQuant scales into the GEGLU feed-forwards' weights and into the LayerNorms "
                   "before the projections that read them, before calibrating (the fp32 function is unchanged; "
                   "only the INT8 graph moves)")
    p.add_argument("--ranges-from-checkpoint", default=None, metavar="CKPT",
                   help="int8: write the learned activation ranges of a QAT checkpoint (`train --qat`) into the "
                   "graph as they are (the graph must be that checkpoint's export); tensors it has no range for "
                   "are calibrated")
    p.add_argument("--no-int16", dest="int16", action="store_false",
                   help="int8 --search nodes: give nodes that must leave 8 bits straight to float instead of "
                   "trying 16-bit activations first (int16 converts the graph to opset 21)")
    p.add_argument("--weight-rounding", choices=("nearest", "adaround"), default=None,
                   help="int8: round 8-bit weights to nearest or choose up or down per element by AdaRound, against "
                   "each layer's output on the calibration frames (about 2.5 minutes for `small` on 2 cores). Default: "
                   "adaround under --exclude auto with int16 (where activations may stay at 16 bits and the weights' "
                   "rounding is most of the error left), nearest otherwise (docs/quantize.md)")
    p.add_argument("--float-outputs", choices=("none", "matmul", "all"), default=None,
                   help="int8: leave the outputs of these Conv/MatMul/Gemm in float where no quantised op reads them "
                   "(every node still reads 8-bit weights and activations): matmul (MatMul and Gemm; no speed "
                   "cost on ONNX Runtime), all (Conv too: more accurate, slower on ONNX Runtime, whose QLinearConv "
                   "needs an 8-bit output), none. Default: matmul with a fixed --exclude; none with --exclude auto; "
                   "with --ranges-from-checkpoint the graph its fine-tune simulated (recorded in it)")
    p.add_argument("--int8-elementwise", action="store_true",
                   help="int8: also quantise Add/Mul/Sigmoid and run BatchNorm as a depthwise Conv, so CNN "
                   "blocks stay 8-bit between convolutions (faster on `paper`; may cost accuracy: check the report)")
    p.add_argument("--split", default="train", help="split the calibration frames come from (default train)")
    p.add_argument("--holdout-split", default="val", help="split for the accuracy check (default val)")
    p.add_argument("--holdout-frames", type=positive_int, default=200, help="frames per held-out sequence (default 200)")
    p.add_argument("--rank-frames", type=int, default=64,
                   help="--search nodes: frames per held-out sequence for the one-node-at-a-time trials that only "
                        "rank the nodes (default 64; 0: all --holdout-frames); the choice uses them all")
    p.add_argument("--threads", type=positive_int, default=None, help="ORT threads (default: all)")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.quantize import QuantizeOptions, quantize_graph
    from e3dpsm.quantize.front_report import artifact_within_budget
    from e3dpsm.quantize.static import ELEMENTWISE_OP_TYPES

    options = QuantizeOptions(
        mode=args.mode, calibration=args.calibration, frames=args.frames, exclude=args.exclude,
        budget_pct=args.budget_pct, search_margin=args.search_margin, budget_reference=args.budget_reference,
        split=args.split, holdout_split=args.holdout_split,
        holdout_frames=args.holdout_frames, rank_frames=args.rank_frames, threads=args.threads,
        objective=args.objective,
        timing_steps=args.timing_steps, artifact_timing_steps=args.artifact_timing_steps, search=args.search,
        target_isa=args.target_isa,
        equalize=args.equalize, ranges_from_checkpoint=args.ranges_from_checkpoint, int16=args.int16,
        weight_rounding=args.weight_rounding, float_outputs=args.float_outputs,
        runtimes=tuple(dict.fromkeys(args.runtimes)),
        **({"op_types": ELEMENTWISE_OP_TYPES, "batchnorm_as_conv": True} if args.int8_elementwise else {}))
    report = quantize_graph(args.model, args.data, args.out, options, force=args.force)
    h = report["holdout"]
    timed = report.get("artifact_timing") or (report.get("search") or {}).get("chosen") or {}
    print(json.dumps({"out": args.out, "artifact": report["artifact"], "mpjpe_mm": round(h["mpjpe_mm"], 3),
                      "fp32_mpjpe_mm": round(h["fp32_mpjpe_mm"], 3), "loss_pct": round(h["loss_pct"], 4),
                      "distance_pct": round(h["bound_pct"], 4), "budget_mpjpe_mm": round(h["budget_mpjpe_mm"], 3),
                      "within_budget": artifact_within_budget(report), "p50_ms": timed.get("p50_ms"),
                      "bytes": report["sizes"]["output_bytes"]}))
    return 0
