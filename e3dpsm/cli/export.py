"""`e3dpsm export`: the stateful single-step ONNX graph of a checkpoint or variant."""
from __future__ import annotations

import argparse
import logging

from e3dpsm.cli._common import add_model_source, load_model_from_args

log = logging.getLogger(__name__)
GRAPH_NAME = "step.onnx"


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("export", help="export the stateful single-step graph to ONNX",
                       description="Write OUT/step.onnx (states as explicit inputs/outputs, metadata "
                                   "inside) and OUT/export.json.")
    add_model_source(p)
    p.add_argument("--out", required=True, help="output folder (refused if it exists, unless --force)")
    p.add_argument("--opset", type=int, default=None, help="ONNX opset (default 17; 17-21 supported)")
    p.add_argument("--no-simplify", action="store_true", help="skip onnxsim simplification")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import torch

    from e3dpsm.export import export_step_with_report
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, write_json_atomic

    torch.set_num_threads(args.threads)
    model = load_model_from_args(args)
    source = {"checkpoint": args.checkpoint} if args.checkpoint else {"variant": args.variant, "seed": args.seed}
    with atomic_dir(args.out, force=args.force) as tmp:
        result = export_step_with_report(
            model, tmp / GRAPH_NAME, opset=args.opset, simplify=not args.no_simplify, metadata_extra={"source": source},
        )
        report = report_header("export", {**vars(args), "func": None})
        report.update(
            model=model.config.to_dict(),
            params=sum(p.numel() for p in model.parameters()),
            result={**result.to_dict(), "path": GRAPH_NAME},
            states=[s.to_metadata() for s in model.state_spec()],
        )
        write_json_atomic(tmp / "export.json", report)
    print(f"wrote {args.out}/{GRAPH_NAME}: {result.nodes_traced} nodes traced, {result.nodes_final} after "
          f"simplification, {result.bytes / 1e6:.2f} MB, opset {result.opset}, IR {result.ir_version}, "
          f"{result.seconds_export + result.seconds_simplify:.1f} s")
    return 0
