"""Benchmark (prepared for a GPU; UNTESTED until one runs it): TensorRT engines of the
trained `small` and of `paper` (initial weights), fp32 / fp16 / int8, each checked against a
golden rollout of its own ONNX graph and timed, in one run of under 5 minutes.

    pip install -e ".[tensorrt]"
    python benchmarks/bench_tensorrt.py --data PREP [--int8-small Q.onnx] [--steps 200]
        [--work runs/bench_tensorrt] [--out benchmarks/results/tensorrt]

PREP: prepared frames of the model's size (`small` takes 96 x 128; `paper` 192 x 256 frames
are made by `e3dpsm prepare` at its default size: pass --data-paper). For each model: export
the fp32 ONNX graph, record a golden from it (ONNX Runtime CPU, `--steps` steps), build the
engines with `e3dpsm convert tensorrt` (the timing cache shared between builds), run
`golden check` on each (fp32 profile for fp32; fp16 / int8 budget profiles otherwise) and
report its ms per step and Hz. int8 needs the QDQ graph `e3dpsm quantize` writes
(`--int8-small`); without it the int8 row says so. Writes OUT.json and OUT.md.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

PROFILE_OF = {"fp32": "fp32", "fp16": "fp16", "int8": "int8"}


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "e3dpsm", *args], capture_output=True, text=True)


def model_rows(name: str, source: list[str], data: str, work: Path, steps: int, int8: str | None) -> list[dict[str, Any]]:
    from e3dpsm.export import export_step
    from e3dpsm.cli._common import load_model_from_args

    args = argparse.Namespace(checkpoint=source[1] if source[0] == "--checkpoint" else None,
                              variant=source[1] if source[0] == "--variant" else None, seed=0)
    onnx_path = export_step(load_model_from_args(args), work / name / "step.onnx")
    golden = work / name / "golden"
    if not golden.exists():
        done = cli("golden", "record", "--model", str(onnx_path), "--data", data, "--steps", str(steps),
                   "--out", str(golden))
        if done.returncode:
            return [{"model": name, "error": done.stderr.strip().splitlines()[-1]}]
    rows = []
    for precision, graph in (("fp32", onnx_path), ("fp16", onnx_path), ("int8", int8)):
        row: dict[str, Any] = {"model": name, "precision": precision}
        if graph is None:
            rows.append({**row, "error": "no QDQ graph given (--int8-small, from e3dpsm quantize)"})
            continue
        out = work / name / f"trt_{precision}"
        started = time.perf_counter()
        flags = [] if precision == "fp32" else [f"--{precision}"]
        built = cli("convert", "tensorrt", "--model", str(graph), "--out", str(out), "--force",
                    "--timing-cache-dir", str(work), *flags)
        row["build_seconds"] = round(time.perf_counter() - started, 1)
        if built.returncode:
            rows.append({**row, "error": built.stderr.strip().splitlines()[-1] if built.stderr.strip() else "build failed"})
            continue
        check = cli("golden", "check", "--model", str(out / "step.engine"), "--golden", str(golden), "--out",
                    str(out / "check"), "--profile", PROFILE_OF[precision])
        report = json.loads((out / "check" / "check.json").read_text()) if (out / "check" / "check.json").exists() else {}
        row.update(passed=report.get("passed"), ms_per_step=report.get("ms_per_step"),
                   hz=1e3 / report["ms_per_step"] if report.get("ms_per_step") else None,
                   exit_code=check.returncode, engine_bytes=(out / "step.engine").stat().st_size)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="prepared 96 x 128 frames for small")
    parser.add_argument("--data-paper", default=None, help="prepared 192 x 256 frames for paper (skipped without)")
    parser.add_argument("--checkpoint", default="benchmarks/checkpoints/small/checkpoint.pt")
    parser.add_argument("--int8-small", default=None, help="QDQ graph of small from e3dpsm quantize")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--work", default="runs/bench_tensorrt")
    parser.add_argument("--out", default="benchmarks/results/tensorrt")
    args = parser.parse_args(argv)
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    work = Path(args.work)
    rows = model_rows("small", ["--checkpoint", args.checkpoint], args.data, work, args.steps, args.int8_small)
    if args.data_paper:
        rows += model_rows("paper", ["--variant", "paper"], args.data_paper, work, args.steps, None)
    report = {**report_header("bench_tensorrt", vars(args)), "rows": rows}
    lines = ["| model | precision | build s | golden check | ms/step | Hz |", "|---|---|---:|---|---:|---:|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['model']} | {r.get('precision', '-')} | - | {r['error']} | - | - |")
        else:
            lines.append(f"| {r['model']} | {r['precision']} | {r['build_seconds']} | "
                         f"{'passed' if r['passed'] else 'FAILED'} | {r['ms_per_step']} | {r['hz']:.0f} |")
    write_json_atomic(args.out + ".json", report)
    write_text_atomic(args.out + ".md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if all(r.get("passed") for r in rows if "error" not in r) else 1


if __name__ == "__main__":
    sys.exit(main())
