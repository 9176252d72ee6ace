"""Benchmark: the `paper` variant profiled side by side on CPU targets, at the paper's
192 x 256 input.

    python benchmarks/bench_profile_paper.py [--data PREPARED] [--int8-model G] [--fp16-model G]
        [--out runs/profile_paper] [--steps 300] [--threads 2]

With --data and no --int8-model / --fp16-model, the graphs are made here with
`e3dpsm quantize` (fp32 graph exported once, reused on later runs). Runs `e3dpsm profile` and
prints the headline figures against the bars set for the `paper` variant on CPU:
- ONNX Runtime fp32 >= 1.5x faster than PyTorch eager and >= 80 Hz (p50), 2 threads;
- INT8 >= 2x faster than fp32 (when an int8 graph exists);
- PyTorch and ONNX MAC counts within 2%.
The bars are reported, not asserted: timings on a shared machine are noisy.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

TARGETS = ("torch-eager-cpu,ort-cpu-fp32,ort-cpu-fp32-static,ort-cpu-int8,ort-cpu-fp16,openvino-cpu-fp32,"
           "openvino-cpu-fp32-static,openvino-cpu-stateful-fp32-static,openvino-cpu-int8,openvino-cpu-bf16-static,"
           "ort-cuda-fp32,ort-tensorrt-fp16")
RUNS = Path(__file__).resolve().parents[1] / "runs"  # git-ignored scratch of the repository


def e3dpsm(*args: str) -> None:
    print("$ e3dpsm " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "e3dpsm", *args], check=True)


def quantised(work: Path, data: str, mode: str, threads: int) -> Path:
    """The `mode` graph of the paper variant, made once under `work`."""
    fp32 = work / "export" / "step.onnx"
    if not fp32.is_file():
        e3dpsm("export", "--variant", "paper", "--out", str(fp32.parent), "--force")
    out = work / f"quantize_{mode}"
    graph = out / f"step_{mode}.onnx"
    if not graph.is_file():
        # Initial weights: an accuracy-driven exclusion search means nothing here, so the
        # default float set (S5 recurrences, Kalman fusion) is kept and calibration is short.
        options = ["--frames", "64", "--exclude", "recurrent"] if mode == "int8" else []
        e3dpsm("quantize", "--model", str(fp32), "--data", data, "--out", str(out), "--mode", mode,
               "--threads", str(threads), "--force", *options)
    return graph


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(RUNS / "profile_paper"),
                        help="folder for the profile report; the graphs go beside it in OUT_graphs (kept "
                             "and reused by later runs); default: runs/profile_paper in the repository "
                             "(git-ignored)")
    parser.add_argument("--data", help="prepared folder: feeds the runs and calibrates the int8 graph")
    parser.add_argument("--int8-model")
    parser.add_argument("--fp16-model")
    parser.add_argument("--steps", default="300")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--targets", default=TARGETS)
    args = parser.parse_args()

    work = Path(args.out).with_name(Path(args.out).name + "_graphs")
    extra: list[str] = []
    if args.data:
        extra += ["--data", args.data]
    for mode, given in (("int8", args.int8_model), ("fp16", args.fp16_model)):
        graph = given or (str(quantised(work, args.data, mode, args.threads)) if args.data else None)
        if graph:
            extra += [f"--{mode}-model", str(graph)]
    e3dpsm("profile", "--variant", "paper", "--targets", args.targets, "--out", args.out, "--steps", args.steps,
           "--threads", str(args.threads), "--force", *extra)

    report = json.loads((Path(args.out) / "report.json").read_text())
    p50 = {t["name"]: t["latency_ms"]["p50"] for t in report["targets"] if t["available"]}
    verdict = report["verdict"]
    if verdict:
        print(f"\nFastest path on this host: {verdict['fastest']}, {verdict['p50_ms']:.2f} ms = {verdict['hz']:.1f} Hz "
              f"(bar: 80 Hz)")
    counting = report["counting"]
    print(f"\nMACs per pose update: PyTorch {counting['pytorch']['macs'] / 1e9:.4f} G, ONNX "
          f"{counting['onnx']['macs'] / 1e9:.4f} G, difference {100 * counting['relative_difference']:.3f}% (bar <= 2%)")
    if "ort-cpu-fp32" in p50 and "torch-eager-cpu" in p50:
        ratio = p50["torch-eager-cpu"] / p50["ort-cpu-fp32"]
        hz = 1e3 / p50["ort-cpu-fp32"]
        print(f"ORT fp32 vs PyTorch eager: {ratio:.2f}x (bar >= 1.5x); ORT fp32 {hz:.1f} Hz (bar >= 80 Hz)")
    for int8 in ("ort-cpu-int8", "openvino-cpu-int8"):
        if int8 in p50 and "ort-cpu-fp32" in p50:
            print(f"{int8} vs ORT fp32: {p50['ort-cpu-fp32'] / p50[int8]:.2f}x (bar >= 2x)")
    peak = report["machine_peak"]
    print(f"Dense float32 peak, best of {peak['by_library']}: {peak['gflops']:.0f} GFLOP/s; 80 Hz needs "
          f"{80 * report['counting']['onnx']['flops'] / 1e9:.0f} GFLOP/s")
    for name, prof in report.get("ort_profiles", {}).items():
        top = ", ".join(f"{op} {ms:.1f}" for op, ms in list(prof["by_op_type_ms"].items())[:6])
        mods = ", ".join(f"{m} {ms:.1f}" for m, ms in list((prof.get("by_module_ms") or {}).items())[:4])
        print(f"{name}: ms/step by op type: {top}; by module: {mods}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
