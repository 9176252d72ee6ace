"""`e3dpsm convert executorch|litert --quantize int8 --data PREP`: the INT8 artifact (PT2E with
XNNPACK's quantizer for the .pte, ai-edge-quantizer on the .tflite), calibrated on PREP's train
split and judged on its test split against the fp32 ONNX graph with the task budget `e3dpsm
quantize` uses (docs/edge.md#int8). Exit 1 when the artifact is over budget (written, with
convert.json saying so), as a failed `golden check`."""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any, Callable

from e3dpsm.cli._common import add_threads, positive_float, positive_int
from e3dpsm.runtime.artifact_metadata import CONVERT_RECORD as REPORT_NAME, CONVERTED_NAMES


def add_int8_options(p: argparse.ArgumentParser) -> None:
    group = p.add_argument_group("INT8", "8-bit quantisation (static, or of the weights alone), checked on held-out data")
    group.add_argument("--quantize", choices=("int8", "int8-weights"), default=None,
                       help="int8: an INT8 program (needs --data), the S5 layers and the Kalman fusion float; "
                            "int8-weights (litert): weights in 8 bits, float arithmetic, the same poses on ARM "
                            "as here (docs/edge.md#int8-for-arm)")
    group.add_argument("--data", default=None, metavar="PREP",
                       help="prepared folder at the model's window and frame size: the budget on its test split "
                            "(int8 also calibrates on its train split and searches on its val split)")
    group.add_argument("--frames", type=positive_int, default=200, help="calibration frames (default 200, minimum 16)")
    group.add_argument("--holdout-frames", type=int, default=0,
                       help="frames per held-out sequence of the budget check (default 0: all)")
    group.add_argument("--search-rounds", type=int, default=4,
                       help="blocks the return-to-float search may keep float when the 8-bit program is over "
                            "budget on the val split (default 4; 0: no search, everything quantisable in 8 bits)")
    group.add_argument("--search-frames", type=int, default=0,
                       help="frames per val sequence each search and narrowing trial streams (default 0: all); "
                            "fewer trade the trials' precision for time")
    group.add_argument("--narrow-trials", type=int, default=None,
                       help="narrowing trials at most, largest operators first (default: every operator of the "
                            "blocks the search kept float; 0: keep those blocks float whole); the untried stay float")
    group.add_argument("--budget-pct", type=positive_float, default=1.0,
                       help="allowed rise of MPJPE and PA-MPJPE over fp32, %% (default 1)")
    add_threads(group)


def check_int8_args(args: argparse.Namespace) -> None:
    """Before anything loads: --data goes with --quantize, both ways (ConfigError: exit 2)."""
    from e3dpsm.errors import ConfigError

    if args.quantize and not args.data:
        raise ConfigError(f"--quantize {args.quantize} needs --data PREP (a prepared folder at the model's frame "
                          "size: the budget check on its test split)")
    if args.data and not args.quantize:
        raise ConfigError("--data is read only with --quantize; drop it for an fp32 program")


def options_from_args(args: argparse.Namespace) -> Any:
    from e3dpsm.budget import TaskBudget
    from e3dpsm.export.edge_int8 import EdgeInt8Options

    return EdgeInt8Options(frames=args.frames, holdout_frames=args.holdout_frames, search_rounds=args.search_rounds,
                           search_frames=args.search_frames, narrow_trials=args.narrow_trials, threads=args.threads,
                           budget=TaskBudget(mpjpe_pct=args.budget_pct, pa_mpjpe_pct=args.budget_pct))


def refuse_weights_only_pte(args: argparse.Namespace) -> None:
    """Before anything else (ConfigError: exit 2): ExecuTorch's XNNPACK has no weight-only form."""
    from e3dpsm.errors import ConfigError

    if args.quantize == "int8-weights":
        raise ConfigError("--quantize int8-weights is written for litert only; for a .pte use --quantize int8 "
                          "(docs/edge.md#int8-for-arm says why the .pte has no weight-only form)")


def run_executorch_int8(args: argparse.Namespace) -> int:
    from e3dpsm.export.executorch_export import ExecuTorchOptions
    from e3dpsm.export.executorch_int8 import convert_executorch_int8

    program = ExecuTorchOptions(attention_form=args.attention_form, decompose_norms=not args.native_norms)

    def coverage(result: Any) -> str:
        counts = result.delegation["int8"]["xnnpack_int8"]
        return "XNNPACK INT8: " + (", ".join(f"{k} x{v}" for k, v in counts.items()) or "none")

    def coverage_and_taps(result: Any) -> str:
        taps = result.taps
        return coverage(result) + (f"; wrote {taps['file']} ({taps['taps']} taps, the same poses and states as "
                                   f"step.pte at all {taps['identical_steps']} steps checked)" if taps else "")

    return _run_edge_int8(args, "executorch", CONVERTED_NAMES["executorch"], ("executorch",),
                          lambda model, data, path, options, work: convert_executorch_int8(
                              model, data, path, options, work, program, taps=args.taps), coverage_and_taps)


def run_litert_int8(args: argparse.Namespace) -> int:
    from e3dpsm.export.litert_export import LiteRTOptions
    from e3dpsm.export.litert_int8 import convert_litert_int8
    from e3dpsm.export.litert_weights8 import convert_litert_weights8

    litert = LiteRTOptions(attention_form=args.attention_form, keep_tensor_names=args.keep_tensor_names)
    weights_only = args.quantize == "int8-weights"
    convert = convert_litert_weights8 if weights_only else convert_litert_int8

    def coverage(result: Any) -> str:
        counted = (f"{result.artifact['int8_operators']} of {sum(result.ops['mac_ops'].values())} "
                   "CONV_2D / FULLY_CONNECTED / BATCH_MATMUL")
        return f"the weights of {counted} in 8 bits, float arithmetic" if weights_only else f"{counted} in 8 bits"

    return _run_edge_int8(args, "litert", CONVERTED_NAMES["litert"], ("litert_torch", "ai_edge_quantizer"),
                          lambda model, data, path, options, work: convert(
                              model, data, path, options, work, litert), coverage)


def _run_edge_int8(args: argparse.Namespace, fmt: str, name: str, modules: tuple[str, ...],
                   convert: Callable[..., tuple[Any, Any, Any]], coverage: Callable[[Any], str]) -> int:
    """The INT8 artifact of `fmt` in OUT (atomically), convert.json beside it; exit 1 when it is
    over budget on the held-out split (written, convert.json saying so)."""
    from e3dpsm.cli._common import load_model_from_args
    from e3dpsm.export.edge_int8 import budget_line, budget_record, open_data
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.extras import require
    from e3dpsm.utils.io import atomic_dir, refuse_existing_output, write_json_atomic

    for module in modules:  # a missing extra fails before anything loads
        require(module, f"to write INT8 {fmt} artifacts")
    refuse_existing_output(args.out, args.force)
    options = options_from_args(args)
    model = load_model_from_args(args)
    # a folder at another size fails here, nothing written
    data = open_data(args.data, model, options, weights_only=args.quantize == "int8-weights")
    with atomic_dir(args.out, force=args.force) as tmp, tempfile.TemporaryDirectory(prefix="e3dpsm-int8-") as work:
        result, check, held = convert(model, data, tmp / name, options, Path(work))
        fp32_bytes = (Path(work) / "fp32.onnx").stat().st_size
        report = report_header("convert", {k: v for k, v in vars(args).items() if k != "func"})
        report.update(format=fmt, file=name, variant=model.config.variant, **result.to_dict(),
                      int8=options.to_dict(), budget=budget_record(check, held, fmt),
                      size={"int8_bytes": result.bytes, "fp32_onnx_bytes": fp32_bytes,
                            "ratio_vs_fp32_onnx": result.bytes / fp32_bytes})
        report["path"] = str(Path(args.out) / name)
        write_json_atomic(tmp / REPORT_NAME, report)
    print(f"wrote {report['path']} ({result.bytes / 1e6:.2f} MB, {result.bytes / fp32_bytes:.2f}x the fp32 graph, "
          f"{result.seconds['total']:.0f} s); {coverage(result)}")
    search = report["artifact"].get("search")  # absent with --search-rounds 0
    if search:
        kept = search["kept_float"]
        narrowed = search.get("narrowing")
        print(f"search on {search['frames']} {search['split']} frames, {len(search['trials'])} trial(s)"
              + (f" and {len(narrowed)} narrowing {', '.join(search['blocks_kept_float'])} to operators" if narrowed else "")
              + (f" ({len(search['narrowing_untried'])} operator(s) past --narrow-trials left float)"
                 if search.get("narrowing_untried") else "")
              + ": " + (f"kept float {', '.join(kept)}" if kept else "every block in 8 bits")
              + ("" if search["within"] else " (still over budget there)"))
    print(budget_line(check))
    return 0 if check.within else 1
