"""Benchmark for a Mac (Core ML predicts on macOS only): the trained `small` as a Core ML
ML program, fp16 and fp32, checked against a golden rollout of its ONNX graph and timed.

    pip install -e ".[coreml]"
    python benchmarks/bench_coreml.py --data PREP [--steps 300] [--work runs/bench_coreml]
        [--out benchmarks/results/coreml_small]

PREP as for bench_edge.py (96 x 128 frames). Each package goes through `golden check`
(fp32 profile for the fp32 package, the fp16 budget profile for fp16), which also reports ms
per step; Hz = 1000 / that. Off macOS it stops at once with the reason. Writes OUT.json/.md.
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "e3dpsm", *args], capture_output=True, text=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--checkpoint", default="benchmarks/checkpoints/small/checkpoint.pt")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--work", default="runs/bench_coreml")
    parser.add_argument("--out", default="benchmarks/results/coreml_small")
    args = parser.parse_args(argv)
    if platform.system() != "Darwin":
        print(f"bench_coreml: Core ML predicts on macOS only (this is {platform.system()})", file=sys.stderr)
        return 2
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    cli("export", "--checkpoint", args.checkpoint, "--out", str(work / "step.onnx"))
    cli("golden", "record", "--model", str(work / "step.onnx"), "--data", args.data, "--steps", str(args.steps),
        "--out", str(work / "golden"), "--force")
    rows = []
    for precision in ("fp32", "fp16"):
        out = work / f"coreml_{precision}"
        cli("convert", "coreml", "--checkpoint", args.checkpoint, "--out", str(out), "--precision", precision, "--force")
        cli("golden", "check", "--model", str(out / "step.mlpackage"), "--golden", str(work / "golden"), "--out",
            str(out / "check"), "--profile", precision)
        report = json.loads((out / "check" / "check.json").read_text())
        pose = next(t for t in report["tensors"] if t["name"] == "pose")
        rows.append({"precision": precision, "passed": report["passed"], "pose_max": pose["max"],
                     "ms_per_step": report["ms_per_step"], "hz": 1e3 / report["ms_per_step"]})
    lines = ["| precision | golden check | pose max diff | ms/step | Hz |", "|---|---|---:|---:|---:|"]
    lines += [f"| {r['precision']} | {'passed' if r['passed'] else 'FAILED'} | {r['pose_max']:.3g} | "
              f"{r['ms_per_step']:.2f} | {r['hz']:.0f} |" for r in rows]
    write_json_atomic(args.out + ".json", {**report_header("bench_coreml", vars(args)), "rows": rows})
    write_text_atomic(args.out + ".md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if all(r["passed"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
