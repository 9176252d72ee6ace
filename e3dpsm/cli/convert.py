"""`e3dpsm convert openvino|executorch|litert|coreml|tensorrt`: a step graph for another runtime.

openvino: an exported ONNX graph as OpenVINO IR, optionally stateful (here); executorch,
litert, coreml: a checkpoint as an edge artifact (cli/_convert_edge.py); tensorrt: an ONNX
graph as a TensorRT engine (cli/_convert_tensorrt.py)."""
from __future__ import annotations

import argparse
from pathlib import Path

from e3dpsm.cli._common import add_force, positive_int
from e3dpsm.runtime.artifact_metadata import CONVERT_RECORD as REPORT_NAME


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("convert", help="convert for another runtime (OpenVINO, ExecuTorch, LiteRT, Core ML, TensorRT)",
                       description="openvino / tensorrt: convert a step graph written by `e3dpsm export` or "
                                   "`e3dpsm quantize`; executorch / litert / coreml: convert a checkpoint. Every "
                                   "artifact carries the graph's state layout (docs/edge.md).")
    formats = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    ov = formats.add_parser(
        "openvino", help="OpenVINO IR (xml + bin)",
        description="Write OUT/<stem>.xml + .bin and OUT/convert.json. With --stateful the recurrent states "
                    "become OpenVINO variables (ReadValue / Assign) with their initial values inside the IR, the "
                    "batch is fixed to 1 (one stream per infer request), and only the frame and window_ms remain "
                    "inputs: any OpenVINO application steps a stream with a plain infer request "
                    "(reset_state() starts a new one). The e3dpsm metadata travels in the IR's rt_info.")
    ov.add_argument("--model", required=True, help="step graph (.onnx) from e3dpsm export or e3dpsm quantize")
    ov.add_argument("--out", required=True, help="output folder (refused if it exists, unless --force)")
    ov.add_argument("--stateful", action="store_true", help="states inside the IR as variables (per-stream)")
    ov.add_argument("--batch", type=positive_int, default=None,
                    help="fix the batch to N streams (default: the graph's dynamic batch; a stateful IR is "
                         "batch 1, one stream per infer request)")
    add_force(ov)
    ov.set_defaults(func=run)
    from e3dpsm.cli import _convert_edge, _convert_tensorrt

    _convert_edge.register(formats)
    _convert_tensorrt.register(formats)
    return p


def run(args: argparse.Namespace) -> int:
    import time

    from e3dpsm.export.openvino_ir import convert_step_graph, save_ir
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, write_json_atomic

    started = time.perf_counter()
    model, info = convert_step_graph(args.model, stateful=args.stateful, batch=args.batch)  # checks input first
    stem = Path(args.model).stem
    with atomic_dir(args.out, force=args.force) as tmp:
        xml, weights = save_ir(model, tmp / f"{stem}.xml")
        report = report_header("convert", {k: v for k, v in vars(args).items() if k != "func"})
        report.update(
            format="openvino", source=str(args.model), xml=xml.name, bin=weights.name,
            bytes={"xml": xml.stat().st_size, "bin": weights.stat().st_size},
            seconds=time.perf_counter() - started, conversion=info.to_dict(),
        )
        write_json_atomic(tmp / REPORT_NAME, report)
    kind = f"stateful, batch {info.batch}, {len(info.variables)} variables" if info.stateful else "explicit states"
    print(f"wrote {Path(args.out) / xml.name} ({kind}, {info.precision}) and {REPORT_NAME}")
    return 0
