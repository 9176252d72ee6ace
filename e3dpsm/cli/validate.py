"""`e3dpsm validate`: accuracy of PyTorch and ONNX variants as continuous streams."""
from __future__ import annotations

import argparse

from e3dpsm.cli._common import add_force, add_threads, positive_float, positive_int


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "validate", help="compare the accuracy of model variants (PyTorch, ONNX fp32/fp16/int8)",
        description="Run every variant over held-out sequences as a continuous stream (states never "
        "reset); MPJPE, PA-MPJPE, e_smooth, per joint, occluded joints, and differences to the fp32 "
        "ONNX graph. Writes DIR/validation.{md,csv,png} and DIR/report.json.")
    p.add_argument("--models", nargs="+", required=True, help="ONNX step graphs (fp32 and quantised)")
    p.add_argument("--checkpoint", help="also run the PyTorch model of this checkpoint")
    p.add_argument("--data", required=True, help="prepared folder (`e3dpsm prepare`)")
    p.add_argument("--out", required=True, help="output folder (must not exist unless --force)")
    p.add_argument("--split", default="test", help="held-out split (default test)")
    p.add_argument("--window-ms", type=positive_float, default=None,
                   help="window length the data was prepared with (default: the data's)")
    p.add_argument("--frames", type=positive_int, default=None, help="frames per sequence (default: all)")
    add_threads(p)
    add_force(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir
    from e3dpsm.validation import validate_variants
    from e3dpsm.validation.report import markdown_table, write_outputs

    config = {k: v for k, v in vars(args).items() if k != "func"}
    with atomic_dir(args.out, force=args.force) as tmp:
        result = validate_variants(args.models, args.data, checkpoint=args.checkpoint, split=args.split,
                                   window_ms=args.window_ms, frames=args.frames, threads=args.threads)
        write_outputs(result, tmp, report_header("validate", config))
    print(markdown_table(result), end="")
    return 0
