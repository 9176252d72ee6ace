"""`e3dpsm convert tensorrt --model step.onnx --out DIR [--fp16 | --int8]`: an ONNX step graph
as a TensorRT engine (export/tensorrt_build.py): OUT/step.engine, its sidecar
OUT/step.engine.json (the state layout), OUT/timing.cache and OUT/convert.json."""
from __future__ import annotations

import argparse
from pathlib import Path

from e3dpsm.cli._common import add_force, positive_int
from e3dpsm.runtime.artifact_metadata import CONVERT_RECORD

ENGINE_NAME = "step.engine"


def register(formats: argparse._SubParsersAction) -> None:
    p = formats.add_parser("tensorrt", help="TensorRT engine (NVIDIA GPU; untested without one)",
                           description="Build OUT/step.engine with the tensorrt Python API for batch 1; the state "
                                       "layout goes to the sidecar OUT/step.engine.json, the timing cache to "
                                       "OUT/timing.cache (pass --timing-cache-dir to share one between builds).")
    p.add_argument("--model", required=True, help="step graph (.onnx) from e3dpsm export, or the QDQ graph of quantize")
    p.add_argument("--out", required=True, help="output folder (refused if it exists, unless --force)")
    precision = p.add_mutually_exclusive_group()
    precision.add_argument("--fp16", action="store_true", help="fp16 kernels where TensorRT picks them")
    precision.add_argument("--int8", action="store_true", help="INT8 from the graph's Q/DQ nodes (a quantize graph)")
    p.add_argument("--workspace-mb", type=positive_int, default=1024, help="builder workspace (default 1024 MB)")
    p.add_argument("--timing-cache-dir", default=None, help="folder of timing.cache (default: OUT)")
    add_force(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from e3dpsm.export.tensorrt_build import TensorRTOptions, build_engine
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.extras import require
    from e3dpsm.utils.io import atomic_dir, write_json_atomic

    require("tensorrt", "to build TensorRT engines")
    precision = "int8" if args.int8 else "fp16" if args.fp16 else "fp32"
    options = TensorRTOptions(precision=precision, workspace_mb=args.workspace_mb)
    with atomic_dir(args.out, force=args.force) as tmp:
        result = build_engine(args.model, tmp / ENGINE_NAME, options,
                              cache_dir=args.timing_cache_dir or tmp)
        report = report_header("convert", {k: v for k, v in vars(args).items() if k != "func"})
        report.update(format="tensorrt", file=ENGINE_NAME, **result.to_dict())
        report["path"] = str(Path(args.out) / ENGINE_NAME)
        write_json_atomic(tmp / CONVERT_RECORD, report)
    print(f"wrote {Path(args.out) / ENGINE_NAME} ({precision}, {report['bytes'] / 1e6:.2f} MB, "
          f"{report['seconds']['total']:.0f} s) and its sidecar {ENGINE_NAME}.json")
    return 0
