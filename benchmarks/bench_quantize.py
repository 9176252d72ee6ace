"""Step latency and accuracy of fp32 / fp16 / int8-dynamic / int8 static, side by side.

    python benchmarks/bench_quantize.py --data PREPARED [--checkpoint CKPT | --variant paper]
        [--accuracy-checkpoint CKPT_SMALL [--accuracy-data PREPARED]] [--threads 2] [--steps 100] [--frames 200]
    python benchmarks/bench_quantize.py --changes --data PREPARED [--graph STEP.onnx] [--repeats 3] [--with-search]

Latency: one graph per variant, real LNES frames of the test split, states carried,
median (and p90) over `--steps` steps after `--warmup`; the variants are measured
interleaved, round by round, so machine load hits all of them alike. Accuracy: the
quantise command's held-out check (MPJPE of each variant vs the fp32 graph). Writes
benchmarks/results/quantize.json (and prints a table).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from e3dpsm.data.prepared import PreparedData
from e3dpsm.quantize import QuantizeOptions, artifact_name, quantize_graph
from e3dpsm.quantize.static import ELEMENTWISE_OP_TYPES as ELEMENTWISE_OPS
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic

MODES = ("int8", "fp16", "int8-dynamic")
RESULTS = Path(__file__).resolve().parent / "results" / "quantize.json"
RESULTS_CHANGES = RESULTS.with_name("quantize.changes.json")


def export_graph(args: argparse.Namespace, checkpoint: str | None, variant: str, out: Path, data: str) -> Path:
    import e3dpsm
    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.export import export_step

    if checkpoint:
        model, _ = load_checkpoint(checkpoint)
    else:
        mean = np.concatenate([s.j3d_mm for s in PreparedData.open(data).split("train")]).mean(axis=0)
        import torch

        model = e3dpsm.create_model(variant).eval()
        model.set_pose_prior(torch.from_numpy(mean.astype(np.float32)))
    return export_step(model, out)


def quantise_all(graph: Path, args: argparse.Namespace, work: Path, label: str, data: str) -> dict[str, dict]:
    reports = {}
    for mode in MODES:
        options = QuantizeOptions(mode=mode, frames=args.frames, holdout_frames=args.holdout_frames,
                                  budget_pct=args.budget_pct, threads=args.threads)
        reports[mode] = quantize_graph(graph, data, work / f"{label}_{mode}", options)
        h = reports[mode]["holdout"]
        print(f"[{label}] {mode}: MPJPE {h['mpjpe_mm']:.3f} vs fp32 {h['fp32_mpjpe_mm']:.3f} mm "
              f"({h['loss_pct']:+.4f} %), distance to fp32 {h['deviation_from_fp32_mm']:.4f} mm", flush=True)
    return reports


def _runner(path: Path, threads: int, window_ms: float, profile_prefix: str | None = None):
    """The profiler's ONNX Runtime step runner for one graph (CPU provider)."""
    from e3dpsm.profiles.latency import OrtRunner
    from e3dpsm.profiles.targets import Target

    target = Target(name=path.stem, runtime="onnxruntime", provider="CPUExecutionProvider",
                    precision="as-graph", graph=path.stem, threads=threads)
    return OrtRunner(str(path), target, window_ms, profile_prefix=profile_prefix)


def latency(paths: dict[str, Path], lnes: np.ndarray, window_ms: float, threads: int, steps: int,
            warmup: int) -> dict[str, dict]:
    """Measured the way `e3dpsm profile` measures: rounds of 25 consecutive steps per
    variant, so load drifts hit every variant alike while each runs with its worker
    threads warm (alternating single steps between sessions whose idle threads spin
    measured every variant up to 2x slower)."""
    from e3dpsm.profiles.latency import measure_side_by_side

    runners = {name: _runner(p, threads, window_ms) for name, p in paths.items()}
    times = measure_side_by_side(runners, np.asarray(lnes, dtype=np.float32), steps, warmup)
    base = float(np.median(times["fp32"]))
    return {name: {"median_ms": 1e3 * float(np.median(t)), "p90_ms": 1e3 * float(np.percentile(t, 90)),
                   "speedup_vs_fp32": base / float(np.median(t)), "bytes": paths[name].stat().st_size}
            for name, t in times.items()}


def op_profile(path: Path, lnes: np.ndarray, window_ms: float, threads: int, steps: int, work: Path) -> dict:
    """Where the step's time goes (ORT profiling, a separate session from the timed one),
    with Amdahl's bound on what INT8 can gain when only Conv / MatMul / Gemm are quantised."""
    from e3dpsm.profiles.ort_profile import summarize_trace

    runner = _runner(path, threads, window_ms, profile_prefix=str(work / path.stem))
    for i in range(steps):
        runner.step(np.asarray(lnes[i % len(lnes)][None], dtype=np.float32))
    summary = summarize_trace(runner.end_profiling())
    summary["by_op_type_ms"] = dict(list(summary["by_op_type_ms"].items())[:15])
    return summary


# Graph-level INT8 changes, each measured against fp32 and the base INT8 graph (--changes).
# (label, QuantizeOptions overrides); every one keeps only the recurrent groups in float so
# the graph change, not the exclusion search, is what differs.
ALL_INT8_OPS = (*ELEMENTWISE_OPS, "Softmax", "Concat", "Transpose", "Reshape", "GridSample",
                "LayerNormalization", "InstanceNormalization")
CHANGES: tuple[tuple[str, dict], ...] = (
    ("int8 Conv/MatMul/Gemm (before)", {"op_types": ("Conv", "MatMul", "Gemm"), "batchnorm_as_conv": False}),
    ("+ Add/Mul/Sigmoid in int8", {"op_types": ELEMENTWISE_OPS}),
    ("+ BatchNorm as depthwise Conv", {"op_types": ELEMENTWISE_OPS, "batchnorm_as_conv": True}),
    ("+ Softmax/Concat/Transpose/Reshape/GridSample/norms", {"op_types": ALL_INT8_OPS, "batchnorm_as_conv": True}),
)


def bench_changes(args: argparse.Namespace) -> int:
    """INT8 p50, fp32 p50, their ratio and the held-out distance per graph change, all graphs
    timed side by side (interleaved chunks, same frames and threads), `--repeats` fresh
    sessions, medians of the per-repeat medians. Writes RESULTS_CHANGES(.json, .md)."""
    from e3dpsm.profiles.latency import measure_side_by_side
    from e3dpsm.quantize.step_timer import _StepRunner

    result = report_header("bench_quantize_changes", vars(args))
    with tempfile.TemporaryDirectory(prefix="bench-quant-changes-") as tmp:
        work = Path(tmp)
        graph = Path(args.graph) if args.graph else export_graph(args, args.checkpoint, args.variant,
                                                                 work / "fp32.onnx", args.data)
        data = PreparedData.open(args.data)
        paths, rows = {"fp32": graph}, {}
        for i, (label, overrides) in enumerate(CHANGES):
            options = QuantizeOptions(mode="int8", exclude="recurrent", frames=args.frames,
                                      holdout_frames=args.holdout_frames, threads=args.threads, **overrides)
            report = quantize_graph(graph, args.data, work / f"change{i}", options)
            paths[label] = work / f"change{i}" / artifact_name("int8")
            rows[label] = {"overrides": {k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items()},
                           "distance_pct": report["holdout"]["bound_pct"],
                           "quantize_linear": report["quantization"]["QuantizeLinear"],
                           "dequantize_linear": report["quantization"]["DequantizeLinear"]}
            print(f"{label}: distance {rows[label]['distance_pct']:.3f}%", flush=True)
        if args.with_search:
            label = "defaults (--exclude auto, the default objective)"
            report = quantize_graph(graph, args.data, work / "auto", QuantizeOptions(
                mode="int8", frames=args.frames, holdout_frames=args.holdout_frames, threads=args.threads))
            paths[label] = work / "auto" / artifact_name("int8")
            rows[label] = {"distance_pct": report["holdout"]["bound_pct"], "search": report["search"]}
        frames = np.asarray(data.split("test")[0].lnes, dtype=np.float32)
        per_repeat: dict[str, list[float]] = {k: [] for k in paths}
        for _ in range(args.repeats):
            runners = {k: _StepRunner(p, args.threads, data.window_ms) for k, p in paths.items()}
            times = measure_side_by_side(runners, frames, args.steps, args.warmup, chunk=10)
            for k, t in times.items():
                per_repeat[k].append(1e3 * float(np.median(t)))
            del runners
    fp32 = float(np.median(per_repeat["fp32"]))
    for k, row in rows.items():
        row.update({"int8_p50_ms": float(np.median(per_repeat[k])), "fp32_p50_ms": fp32,
                    "speedup_vs_fp32": fp32 / float(np.median(per_repeat[k])), "per_repeat_ms": per_repeat[k]})
    result.update({"graph": args.graph or f"{args.variant} (untrained, torch seed 0 weights)",
                   "fp32_per_repeat_ms": per_repeat["fp32"], "changes": rows})
    out = Path(args.out)
    write_json_atomic(out, result)
    lines = [f"# INT8 graph changes on `{args.variant}` ({result['machine'].get('cpu_model')}, "
             f"{args.threads} threads, shared machine)", "",
             f"Side by side in one process: {args.steps} steps after {args.warmup} warm-up per graph, interleaved "
             f"in chunks of 10, {args.repeats} repeats with fresh sessions; medians of the per-repeat medians. "
             "Held-out distance: mean joint distance to the fp32 poses / fp32 MPJPE (val split).", "",
             "| change | INT8 p50 ms | fp32 p50 ms | ratio | held-out distance to fp32 % |", "|---|---|---|---|---|"]
    for k, row in rows.items():
        lines.append(f"| {k} | {row['int8_p50_ms']:.2f} | {fp32:.2f} | {row['speedup_vs_fp32']:.2f} | "
                     f"{row['distance_pct']:.3f} |")
    write_text_atomic(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--checkpoint", help="speed model checkpoint (default: --variant weights)")
    parser.add_argument("--variant", default="paper")
    parser.add_argument("--accuracy-checkpoint", help="trained model for the accuracy figures (e.g. small)")
    parser.add_argument("--accuracy-variant", default="small")
    parser.add_argument("--accuracy-data", help="prepared data at the accuracy model's resolution (default --data)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--holdout-frames", type=int, default=200)
    parser.add_argument("--budget-pct", type=float, default=None, help="default: the mode's (int8 1.0, fp16 0.1)")
    parser.add_argument("--out", default=None, help=f"default {RESULTS} ({RESULTS_CHANGES} with --changes)")
    parser.add_argument("--changes", action="store_true",
                        help="measure the graph-level INT8 changes (CHANGES) instead of the mode comparison")
    parser.add_argument("--graph", help="--changes: an exported fp32 step graph instead of exporting --variant")
    parser.add_argument("--repeats", type=int, default=3, help="--changes: fresh-session repeats")
    parser.add_argument("--with-search", action="store_true", help="--changes: add the --exclude auto default")
    args = parser.parse_args(argv)
    if args.changes:
        args.out = args.out or str(RESULTS_CHANGES)
        return bench_changes(args)
    args.out = args.out or str(RESULTS)

    result = report_header("bench_quantize", vars(args))
    with tempfile.TemporaryDirectory(prefix="bench-quant-") as tmp:
        work = Path(tmp)
        acc_data = args.accuracy_data or args.data
        acc_graph = export_graph(args, args.accuracy_checkpoint, args.accuracy_variant, work / "acc_fp32.onnx", acc_data)
        acc = quantise_all(acc_graph, args, work, "accuracy", acc_data)
        result["accuracy"] = {
            "model": args.accuracy_checkpoint or f"{args.accuracy_variant} (untrained, mean-pose prior)",
            **{mode: {**r["holdout"], "calibration": r.get("calibration"),
                      "float_groups": r["quantization"].get("float_groups"),
                      "exclusion_search": r.get("exclusion_search")} for mode, r in acc.items()},
        }
        speed_graph = export_graph(args, args.checkpoint, args.variant, work / "speed_fp32.onnx", args.data)
        speed = quantise_all(speed_graph, args, work, "speed", args.data)
        paths = {"fp32": speed_graph, **{m: work / f"speed_{m}" / artifact_name(m) for m in MODES}}
        speed_data = PreparedData.open(args.data)
        lnes, window_ms = speed_data.split("test")[0].lnes, speed_data.window_ms
        result["latency"] = {
            "model": args.checkpoint or f"{args.variant} (untrained)", "threads": args.threads,
            "steps": args.steps, "warmup": args.warmup,
            **latency(paths, lnes, window_ms, args.threads, args.steps, args.warmup),
        }
        result["op_profile"] = {name: op_profile(paths[name], lnes, window_ms, args.threads, 40, work) for name in ("fp32", "int8")}
        result["speed_model_accuracy"] = {m: r["holdout"] for m, r in speed.items()}
        result["calibration"] = {m: r.get("calibration") for m, r in speed.items() if r.get("calibration")}
    write_json_atomic(args.out, result)
    print(f"{'variant':14s} {'median ms':>10s} {'speed-up':>9s} {'MPJPE loss %':>13s}")
    for name, row in result["latency"].items():
        if isinstance(row, dict):
            loss = result["accuracy"].get(name, {}).get("loss_pct", 0.0)
            print(f"{name:14s} {row['median_ms']:10.2f} {row['speedup_vs_fp32']:9.2f} {loss:13.4f}")
    bound = result["op_profile"]["fp32"]["int8_speedup_bound"]
    print(f"fp32 kernel time {bound['kernel_ms']:.2f} ms/step, Conv/MatMul/Gemm {bound['quantisable_ms']:.2f} ms "
          f"({100 * bound['quantisable_share']:.0f}%): INT8 speed-up bound {bound['max_speedup']:.2f}x")
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
