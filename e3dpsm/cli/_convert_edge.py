"""`e3dpsm convert executorch|litert|coreml`: a checkpoint as an edge-runtime artifact
(ExecuTorch .pte, LiteRT .tflite, Core ML .mlpackage) with the state layout inside, and
OUT/convert.json (sizes, timings, what the backend runs, versions). docs/edge.md."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Callable

from e3dpsm.cli._common import add_force, add_model_source
from e3dpsm.cli._convert_int8 import add_int8_options, check_int8_args
from e3dpsm.runtime.artifact_metadata import CONVERT_RECORD as REPORT_NAME, CONVERTED_NAMES

# format -> (artifact name, module needed to convert)
ARTIFACTS = {fmt: (CONVERTED_NAMES[fmt], module)
             for fmt, module in (("executorch", "executorch"), ("litert", "litert_torch"), ("coreml", "coremltools"))}


def _common(p: argparse.ArgumentParser, default_form: str) -> None:
    add_model_source(p)
    p.add_argument("--out", required=True, help="output folder (refused if it exists, unless --force)")
    p.add_argument("--attention-form", choices=("grid_sample", "gather"), default=default_form,
                   help=f"deformable attention formulation (default {default_form}; docs/edge.md has the figures)")
    add_force(p)


def register(formats: argparse._SubParsersAction) -> None:
    et = formats.add_parser("executorch", help="ExecuTorch program (.pte, XNNPACK)",
                            description="Write OUT/step.pte (torch.export -> XNNPACK partitioner) and OUT/convert.json.")
    _common(et, "grid_sample")
    et.add_argument("--native-norms", action="store_true",
                    help="keep LayerNorm / GroupNorm as they are (portable kernels) instead of as matmuls XNNPACK runs")
    add_int8_options(et)
    et.add_argument("--taps", action="store_true",
                    help="with --quantize int8: also OUT/step_taps.pte, the same program returning every quantised "
                         "activation's codes, for `python -m e3dpsm.golden.pte_taps` on a device whose ExecuTorch "
                         "has no event tracer (docs/edge.md#where-a-pte-parts-without-an-event-tracer)")
    et.set_defaults(func=run_executorch)

    lt = formats.add_parser("litert", help="LiteRT model (.tflite, XNNPACK delegate)",
                            description="Write OUT/step.tflite (litert-torch; --quantize int8: ai-edge-quantizer) and OUT/convert.json.")
    _common(lt, "gather")
    lt.add_argument("--keep-tensor-names", action="store_true",
                    help="keep litert-torch's tensor names (module paths, for Model Explorer; about 0.25 MB more on "
                         "small) instead of short ones; the signature's input and output names stay either way")
    add_int8_options(lt)
    lt.set_defaults(func=run_litert)

    cm = formats.add_parser("coreml", help="Core ML ML program (.mlpackage)",
                            description="Write OUT/step.mlpackage (coremltools ML program, states as explicit inputs "
                                        "and outputs) and OUT/convert.json with the checks Linux can run.")
    _common(cm, "grid_sample")
    cm.add_argument("--precision", choices=("fp16", "fp32"), default="fp16", help="compute precision (default fp16)")
    cm.set_defaults(func=run_coreml)


def _convert(args: argparse.Namespace, fmt: str, convert: Callable[[Any, Path], Any]) -> int:
    from e3dpsm.cli._common import load_model_from_args
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.extras import require
    from e3dpsm.utils.io import atomic_dir, refuse_existing_output, write_json_atomic

    name, module = ARTIFACTS[fmt]
    require(module, f"to convert for {fmt}")  # a missing extra fails before the model loads
    refuse_existing_output(args.out, args.force)
    model = load_model_from_args(args)
    with atomic_dir(args.out, force=args.force) as tmp:
        result = convert(model, tmp / name)
        report = report_header("convert", {k: v for k, v in vars(args).items() if k != "func"})
        report.update(format=fmt, file=name, variant=model.config.variant, **result.to_dict())
        report["path"] = str(Path(args.out) / name)
        write_json_atomic(tmp / REPORT_NAME, report)
    print(summary_line(fmt, Path(args.out) / name, report))
    return 0


def summary_line(fmt: str, path: Path, report: dict) -> str:
    size = f"{report['bytes'] / 1e6:.2f} MB"
    seconds = f"{report['seconds']['total']:.0f} s"
    if fmt == "executorch":
        share = report["delegation"]["delegated_share"]
        left = ", ".join(f"{k} x{v}" for k, v in report["delegation"]["portable_ops"].items()) or "none"
        return f"wrote {path} ({size}, {seconds}); XNNPACK runs {share:.1%} of the MACs; portable ops: {left}"
    if fmt == "litert":
        ops = report["ops"]
        return (f"wrote {path} ({size}, {seconds}); {sum(ops['histogram'].values())} operators, "
                f"{ops['xnnpack_partitions']} XNNPACK partitions")
    return f"wrote {path} ({size}, {seconds})"


def run_executorch(args: argparse.Namespace) -> int:
    from e3dpsm.cli._convert_int8 import refuse_weights_only_pte
    from e3dpsm.errors import ConfigError
    from e3dpsm.export.executorch_export import ExecuTorchOptions, convert_executorch

    refuse_weights_only_pte(args)
    check_int8_args(args)
    if args.taps and args.quantize != "int8":
        raise ConfigError("--taps taps the quantised activations of an INT8 program: add --quantize int8 --data PREP")
    if args.quantize:
        from e3dpsm.cli._convert_int8 import run_executorch_int8

        return run_executorch_int8(args)
    options = ExecuTorchOptions(attention_form=args.attention_form, decompose_norms=not args.native_norms)
    return _convert(args, "executorch", lambda model, path: convert_executorch(model, path, options))


def run_litert(args: argparse.Namespace) -> int:
    from e3dpsm.export.litert_export import LiteRTOptions, convert_litert

    check_int8_args(args)
    if args.quantize:
        from e3dpsm.cli._convert_int8 import run_litert_int8

        return run_litert_int8(args)
    options = LiteRTOptions(attention_form=args.attention_form, keep_tensor_names=args.keep_tensor_names)
    return _convert(args, "litert", lambda model, path: convert_litert(model, path, options))


def run_coreml(args: argparse.Namespace) -> int:
    from e3dpsm.export.coreml_export import CoreMLOptions, convert_coreml

    options = CoreMLOptions(attention_form=args.attention_form, precision=args.precision)
    return _convert(args, "coreml", lambda model, path: convert_coreml(model, path, options))
