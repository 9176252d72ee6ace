"""Benchmark: an INT8 graph of `quantize` on OpenVINO against ONNX Runtime, with and without
the Reshape guards of export/openvino_compat.py (accuracy, not speed).

    python benchmarks/bench_openvino_int8.py --model q/step_int8.onnx --fp32 exp/step.onnx \
        --data P [--frames 100] [--threads 2] [--out benchmarks/results/openvino_int8_paper]

One continuous stream over the first --frames frames of the data's first `test` sequence:
- the graph with its guards taken out: whether OpenVINO's CPU plugin compiles it (the error
  line where not), and ONNX Runtime's poses of it against the guarded graph's (a Reshape
  moves no value: they must be the same bits);
- the guarded graph on OpenVINO (f32 float parts, e3dpsm's compile options) against ONNX
  Runtime on the same graph, beside the spread ONNX Runtime's own fused integer kernels
  show against its unfused arithmetic (`exact_arithmetic_options`): the rounding noise a
  runtime may add to this graph;
- each against the fp32 graph, for scale.
Distances are per-joint Euclidean, in mm, over every pose output. Writes OUT.json and OUT.md.
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


def _distance(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    from e3dpsm.metrics import joint_errors

    errors = {name: joint_errors(a[name], b[name]) for name in a}
    return {name: {"max_mm": float(e.max()), "mean_mm": float(e.mean())} for name, e in errors.items()}


def _unguarded_copy(model_path: Path, work: Path) -> tuple[Path, list[str]]:
    import onnx

    from e3dpsm.export.openvino_compat import remove_guards

    model = onnx.load(str(model_path))
    removed = remove_guards(model)
    path = work / "unguarded.onnx"
    onnx.save(model, str(path))
    return path, removed


def _compile_error(path: Path, threads: int) -> str | None:
    from e3dpsm.runtime.openvino_session import compile_config, openvino_core

    try:
        openvino_core().compile_model(str(path), "CPU", compile_config(threads))
    except RuntimeError as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        return next((line for line in lines if "Requested output shape" in line), lines[-1])[:300]
    return None


def measure(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.runtime import StepSession
    from e3dpsm.runtime.openvino_session import OpenVINOStepSession
    from e3dpsm.runtime.session import exact_arithmetic_options
    from e3dpsm.validation.streams import onnx_stream_outputs

    data = PreparedData.open(args.data)
    sequence = data.split("test")[0]
    lnes = np.asarray(sequence.lnes[:args.frames], dtype=np.float32)

    def stream(session) -> dict[str, np.ndarray]:
        return onnx_stream_outputs(session, lnes, data.window_ms)

    unguarded, removed = _unguarded_copy(Path(args.model), work)
    fp32 = stream(StepSession(args.fp32, threads=args.threads))
    ort = stream(StepSession(args.model, threads=args.threads))
    ort_unguarded = stream(StepSession(unguarded, threads=args.threads))
    ort_exact = stream(StepSession(args.model, threads=args.threads, options=exact_arithmetic_options()))
    openvino = stream(OpenVINOStepSession(args.model, threads=args.threads))
    return {
        "sequence": sequence.name, "frames": len(lnes), "guards": removed,
        "unguarded_compile_error": _compile_error(unguarded, args.threads),
        "guarded_compile_error": _compile_error(Path(args.model), args.threads),
        "ort_same_bits_with_and_without_guards": all(np.array_equal(ort[k], ort_unguarded[k]) for k in ort),
        "distance_mm": {
            "openvino vs onnxruntime": _distance(openvino, ort),
            "onnxruntime fused vs unfused": _distance(ort, ort_exact),
            "onnxruntime vs fp32": _distance(ort, fp32),
            "openvino vs fp32": _distance(openvino, fp32),
        },
    }


def markdown(report: dict[str, Any]) -> str:
    r, machine = report["result"], report["machine"]

    def compiles(error: str | None) -> str:
        return f"no: {error}" if error else "yes"

    lines = ["# An INT8 graph on OpenVINO and ONNX Runtime, with and without the Reshape guards", "",
             f"`{report['config']['model']}`, {r['frames']} frames of {r['sequence']}, {report['config']['threads']} "
             f"threads; OpenVINO {report['versions'].get('openvino')}, ONNX Runtime "
             f"{report['versions'].get('onnxruntime')}; {machine.get('cpu_model', '?')} "
             f"({machine['isa']['kind']}), shared with other jobs.", "",
             f"- guards: {', '.join(f'`{g}`' for g in r['guards']) or 'none'}",
             f"- without them OpenVINO compiles: {compiles(r['unguarded_compile_error'])}",
             f"- with them: {compiles(r['guarded_compile_error'])}",
             f"- ONNX Runtime's poses the same bits with and without: {r['ort_same_bits_with_and_without_guards']}", "",
             "| poses | output | max mm | mean mm |", "|---|---|---:|---:|"]
    for pair, outputs in r["distance_mm"].items():
        for name, d in outputs.items():
            lines.append(f"| {pair} | {name} | {d['max_mm']:.3f} | {d['mean_mm']:.3f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="INT8 graph of `e3dpsm quantize` (with its guards)")
    parser.add_argument("--fp32", required=True, help="the fp32 graph it was quantised from")
    parser.add_argument("--data", required=True, help="prepared folder with a `test` sequence")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/results/openvino_int8")
    args = parser.parse_args()
    report = report_header("bench_openvino_int8", vars(args))
    with tempfile.TemporaryDirectory(prefix="e3dpsm-bench-ov-int8-") as tmp:
        report["result"] = measure(args, Path(tmp))
    out = Path(args.out)
    write_json_atomic(out.with_suffix(".json"), report)
    write_text_atomic(out.with_suffix(".md"), markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
