"""Benchmark: an INT8 edge artifact (`e3dpsm convert executorch|litert --quantize int8`) timed
beside the fp32 artifact of the same checkpoint and format, on held-out frames, states carried.

    e3dpsm convert executorch --checkpoint CK --out INT8 --quantize int8 --data PREP --threads 2
    e3dpsm convert executorch --checkpoint CK --out FP32
    python benchmarks/bench_edge_int8.py --int8 INT8 --fp32 FP32/step.pte --data PREP \
        [--steps 300] [--threads 2] [--out benchmarks/results/edge_int8_small]

(the same with `litert` and FP32/step.tflite).

Both programs step the first frames of PREP's test split in turn (profiles/step_timing.time_beside:
chunks of 10 steps interleaved, a bootstrap interval of the speed-up; the ExecuTorch runner of
runtime/stepping with runtime/session.CarriedStateRunner). The budget, sizes and what XNNPACK
runs in INT8 come from INT8/convert.json (its `format` picks the runtime). The load average is recorded (a shared host).
Writes OUT_<isa kind>.json and .md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np


def time_programs(int8: Path, fp32: Path, data: str, steps: int, threads: int, runtime: str) -> dict[str, Any]:
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.verdict import time_beside_fp32

    prepared = PreparedData.open(data)
    frames = np.asarray(prepared.split("test")[0].lnes[:steps], dtype=np.float32)
    return time_beside_fp32(int8, fp32, frames, prepared.window_ms, (runtime,), threads, steps)[runtime]


def coverage_line(convert: dict[str, Any]) -> str:
    if convert["format"] == "executorch":
        coverage = convert["delegation"]["int8"]
        return (f"XNNPACK INT8: {coverage['xnnpack_int8']}; XNNPACK float: {coverage['xnnpack_float']}; "
                f"portable: {coverage['portable']}.")
    artifact = convert["artifact"]
    if artifact.get("arithmetic") == "float":  # --quantize int8-weights
        return (f"8-bit weights, float arithmetic: {artifact['int8_operators']} CONV_2D / FULLY_CONNECTED; "
                f"operators: {convert['ops']['mac_ops']}.")
    return (f"8-bit CONV_2D / FULLY_CONNECTED: {artifact['int8_operators']}; float by rule: {artifact['coverage']['float_by_rule']}; "
            f"groups kept float: {artifact['keep_float'] or 'none'}; operators: {convert['ops']['mac_ops']}.")


def markdown(report: dict[str, Any]) -> str:
    convert, timing = report["int8_convert"], report["timing"]
    budget = convert["budget"]
    rows = ["| metric | fp32 mm | INT8 mm | change % | upper bound % | limit % | within |",
            "|---|---:|---:|---:|---:|---:|---|"]
    for name, m in budget["metrics"].items():
        rows.append(f"| {name} | {m['fp32_mm']:.3f} | {m['int8_mm']:.3f} | {m['change_pct']:+.3f} | "
                    f"{m['upper_pct']:+.3f} | +{m['limit_pct']:g} | {'yes' if m['within'] else '**no**'} |")
    interval = timing["interval"]
    kind = {"executorch": "ExecuTorch program", "litert": "LiteRT model"}[convert["format"]]
    if convert["artifact"].get("arithmetic") == "float":
        kind += " (weights only)"
    return "\n".join([
        f"# INT8 {kind} of `{convert['variant']}` ({report['isa']['kind']})", "",
        f"Budget on {budget['frames']} held-out frames ({budget['data']}): "
        f"{'within' if budget['within'] else 'OVER'}; distance to the fp32 poses "
        f"{budget['distance_to_fp32_mm']:.3f} mm.", "", *rows, "",
        f"Size: INT8 {report['int8_bytes'] / 1e6:.2f} MB, fp32 {Path(report['config']['fp32']).suffix} "
        f"{report['fp32_bytes'] / 1e6:.2f} MB "
        f"({report['int8_bytes'] / report['fp32_bytes']:.3f}x).", "",
        f"Step p50 ({timing['timer']['steps']} steps side by side, {report['threads']} threads, load average "
        f"{report['load_before']:.1f} before, {timing['timer']['load_average']:.1f} after): INT8 "
        f"{timing['p50_ms']:.2f} ms, fp32 {timing['fp32_p50_ms']:.2f} ms, {timing['speedup_vs_fp32']:.2f}x "
        f"(80% interval {interval['low']:.2f}-{interval['high']:.2f}x).", "",
        coverage_line(convert), ""])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--int8", required=True, help="folder written by convert executorch|litert --quantize int8 (or litert --quantize int8-weights)")
    parser.add_argument("--fp32", required=True, help="the fp32 step.pte / step.tflite of the same checkpoint")
    parser.add_argument("--data", required=True, help="prepared folder (its test split's first sequence is timed)")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/results/edge_int8_small")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_benchmark_report
    from e3dpsm.utils.isa import detect_isa

    convert = json.loads((Path(args.int8) / "convert.json").read_text())
    int8 = Path(args.int8) / convert["file"]
    if Path(args.fp32).suffix != int8.suffix:
        parser.error(f"--fp32 {args.fp32} is not a {int8.suffix} artifact like {int8}")
    report = report_header("bench_edge_int8", vars(args))
    report.update(isa=detect_isa().to_dict(), threads=args.threads, load_before=os.getloadavg()[0],
                  int8_bytes=int8.stat().st_size, fp32_bytes=Path(args.fp32).stat().st_size, int8_convert=convert)
    report["timing"] = time_programs(int8, Path(args.fp32), args.data, args.steps, args.threads, convert["format"])
    write_benchmark_report(args.out, report, markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
