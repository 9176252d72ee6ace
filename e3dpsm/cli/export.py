"""`e3dpsm export`: the stateful single-step ONNX graph of a checkpoint or variant."""
from __future__ import annotations

import argparse
import logging

from e3dpsm.cli._common import add_force, add_model_source, add_threads, load_model_from_args

log = logging.getLogger(__name__)
GRAPH_NAME = "step.onnx"
ORT_GRAPH_NAME = "step.ort.onnx"  # ONNX Runtime pre-optimised copy: version and provider specific


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("export", help="export the stateful single-step graph to ONNX",
                       description="Write OUT/step.onnx (states as explicit inputs/outputs, metadata "
                                   "inside), OUT/step.ort.onnx (ONNX Runtime's pre-optimised copy, for edge "
                                   "start-up) and OUT/export.json.")
    add_model_source(p)
    p.add_argument("--out", required=True, help="output folder (refused if it exists, unless --force)")
    p.add_argument("--opset", type=int, default=None,
                   help="ONNX opset (default: the lowest the attention form needs, 17, or 19 for "
                        "deform_conv; 17-21 supported)")
    p.add_argument("--no-simplify", action="store_true", help="skip onnxsim simplification")
    p.add_argument("--static-batch", action="store_true",
                   help="fix the batch axis to 1 (fewer shape operators; single-stream devices)")
    p.add_argument("--attention-form", choices=("grid_sample", "gather", "deform_conv"), default="grid_sample",
                   help="deformable attention in the graph: 'grid_sample' (the literal GridSample form; default), "
                        "'gather' (corner gathers, one weighted MatMul) or 'deform_conv' (one ONNX DeformConv per "
                        "block, opset >= 19); the last two fold the block's projections")
    p.add_argument("--ort-optimized", choices=("none", "basic", "extended", "all"), default="extended",
                   help=f"also write {ORT_GRAPH_NAME}, ONNX Runtime's CPU-optimised graph at this level "
                        "(default extended; 'all' adds the CPU's NCHWc layout: same-machine only; none: skip)")
    add_threads(p, "torch threads")
    add_force(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import torch

    from e3dpsm.export import export_step_with_report
    from e3dpsm.export.ort_optimized import write_ort_optimized
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, write_json_atomic

    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_model_from_args(args)
    source = {"checkpoint": args.checkpoint} if args.checkpoint else {"variant": args.variant, "seed": args.seed}
    with atomic_dir(args.out, force=args.force) as tmp:
        result = export_step_with_report(
            model, tmp / GRAPH_NAME, opset=args.opset, simplify=not args.no_simplify, metadata_extra={"source": source},
            attention_form=args.attention_form, static_batch=args.static_batch,
        )
        ort_graph = (write_ort_optimized(tmp / GRAPH_NAME, tmp / ORT_GRAPH_NAME, args.ort_optimized)
                     if args.ort_optimized != "none" else None)
        report = report_header("export", {**vars(args), "func": None})
        report.update(
            model=model.config.to_dict(),
            params=model.num_parameters(),
            result={**result.to_dict(), "path": GRAPH_NAME},
            states=[s.to_metadata() for s in model.state_spec()],
            ort_optimized=ort_graph,
        )
        write_json_atomic(tmp / "export.json", report)
    print(f"wrote {args.out}/{GRAPH_NAME}: {result.nodes_traced} nodes traced, {result.nodes_final} after "
          f"simplification, {result.bytes / 1e6:.2f} MB, opset {result.opset}, IR {result.ir_version}, "
          f"{result.seconds_export + result.seconds_simplify:.1f} s"
          + (f"; {ORT_GRAPH_NAME} (ONNX Runtime {ort_graph['onnxruntime']}, {ort_graph['level']})"
             if ort_graph else ""))
    return 0
