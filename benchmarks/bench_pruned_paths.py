"""Benchmark: pruned checkpoints against their unpruned model on every fast CPU path, all in
one process, side by side (the speed-ups of a pruning run are ratios measured together).

    python benchmarks/bench_pruned_paths.py --unpruned benchmarks/checkpoints/paper/checkpoint.pt \\
        --pruned NAME=CK [NAME=CK ...] --data PREP [--targets T1,T2] [--steps 300] [--threads 2] \\
        [--out benchmarks/results/pruned_paths_paper]

Each checkpoint is exported with `--static-batch` (batch fixed to 1, what the *-static targets
load); every (checkpoint, target) runner then steps the same frames of PREP's test split with
states carried, in rounds of 25 steps per runner (profiles/latency.measure_side_by_side), so a
change of load on a shared host reaches every runner alike. Reports the median per runner, its
Hz, and per target each pruned model's speed-up over the unpruned one; the fastest path of
each model is named. Writes OUT_<isa kind>.json and .md.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_TARGETS = ("ort-cpu-fp32-static,openvino-cpu-fp32-static,openvino-cpu-stateful-fp32-static,"
                   "openvino-cpu-bf16-static")


def export_static(checkpoint: str, out: Path) -> Path:
    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.export.onnx_export import export_step_with_report

    model, _ = load_checkpoint(checkpoint)
    return Path(export_step_with_report(model, out, static_batch=True).path)


def measure(graphs: dict[str, Path], targets: list[Any], frames: np.ndarray, window_ms: float, steps: int,
            warmup: int) -> dict[str, dict[str, float]]:
    from e3dpsm.profiles.latency import latency_summary, measure_side_by_side
    from e3dpsm.profiles.profiler import build_runner
    from e3dpsm.profiles.targets import STATIC_FP32

    runners = {f"{name}|{target.name}": build_runner(target, {STATIC_FP32: graph, "fp32": graph}, None, window_ms)
               for name, graph in graphs.items() for target in targets}
    seconds = measure_side_by_side(runners, frames, steps, warmup)
    return {key: latency_summary(t) for key, t in seconds.items()}  # ms


def summarise(figures: dict[str, dict[str, float]], names: list[str], targets: list[str]) -> dict[str, Any]:
    table = {name: {t: {"p50_ms": figures[f"{name}|{t}"]["p50"], "hz": 1e3 / figures[f"{name}|{t}"]["p50"]}
                    for t in targets} for name in names}
    for name in names[1:]:
        for t in targets:
            table[name][t]["speedup_vs_unpruned"] = table[names[0]][t]["p50_ms"] / table[name][t]["p50_ms"]
    fastest = {name: min(targets, key=lambda t: table[name][t]["p50_ms"]) for name in names}
    return {"p50": table, "fastest": {name: {"target": t, **table[name][t]} for name, t in fastest.items()}}


def markdown(report: dict[str, Any]) -> str:
    names, targets = report["models"], report["targets"]
    table = report["summary"]["p50"]
    lines = [f"# Pruned against unpruned, side by side ({report['isa']['kind']})", "",
             f"{report['steps']} timed steps per runner after {report['warmup']} warm-up, {report['threads']} threads, "
             f"every (model, target) runner interleaved in rounds of 25 steps in one process; static-batch graphs; "
             f"frames of `{report['config']['data']}` (test split); load average {report['load_before']:.1f} before, "
             f"{report['load_after']:.1f} after. CPU: {report['machine'].get('cpu_model', '?')}.", "",
             "| target | " + " | ".join(f"{n} ms (Hz)" for n in names) + " | "
             + " | ".join(f"{n} speed-up" for n in names[1:]) + " |",
             "|---|" + "---:|" * (2 * len(names) - 1)]
    for t in targets:
        cells = [f"{table[n][t]['p50_ms']:.2f} ({table[n][t]['hz']:.1f})" for n in names]
        ups = [f"{table[n][t]['speedup_vs_unpruned']:.2f}x" for n in names[1:]]
        lines.append(f"| {t} | " + " | ".join(cells + ups) + " |")
    lines += ["", "Fastest path per model: " + "; ".join(
        f"{n}: {f['target']} {f['p50_ms']:.2f} ms ({f['hz']:.1f} Hz)" for n, f in report["summary"]["fastest"].items()),
        ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--unpruned", required=True, help="the unpruned checkpoint")
    parser.add_argument("--pruned", required=True, nargs="+", metavar="NAME=CK", help="pruned checkpoints, named")
    parser.add_argument("--data", required=True, help="prepared folder at the models' frame size (test split)")
    parser.add_argument("--targets", default=DEFAULT_TARGETS)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/results/pruned_paths_paper")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.profiles.targets import availability, load_targets, select_targets
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_benchmark_report
    from e3dpsm.utils.isa import detect_isa

    if any("=" not in spec for spec in args.pruned):
        parser.error("--pruned takes NAME=CHECKPOINT pairs")
    pruned = dict(spec.split("=", 1) for spec in args.pruned)
    if "unpruned" in pruned or any(not Path(ck).is_file() for ck in pruned.values()):
        parser.error("--pruned takes NAME=CHECKPOINT pairs of existing files, no NAME 'unpruned'")
    checkpoints = {"unpruned": args.unpruned, **pruned}
    targets = select_targets(load_targets(), args.targets, args.threads)
    data = PreparedData.open(args.data)
    frames = np.asarray(data.split("test")[0].lnes[: max(args.steps, 50)], dtype=np.float32)
    report = report_header("bench_pruned_paths", vars(args))
    report.update(isa=detect_isa().to_dict(), threads=args.threads, steps=args.steps, warmup=args.warmup,
                  models=list(checkpoints), load_before=os.getloadavg()[0])
    with tempfile.TemporaryDirectory(prefix="e3dpsm-pruned-paths-") as work:
        graphs = {name: export_static(ck, Path(work) / name / "step.onnx") for name, ck in checkpoints.items()}
        usable = [t for t in targets
                  if availability(t, {"fp32-static": graphs["unpruned"], "fp32": graphs["unpruned"]}, False).available]
        report["unavailable"] = sorted({t.name for t in targets} - {t.name for t in usable})
        if not usable:
            parser.error(f"none of the targets runs here: {', '.join(report['unavailable'])}")
        report["targets"] = [t.name for t in usable]
        figures = measure(graphs, usable, frames, data.window_ms, args.steps, args.warmup)
    report["load_after"] = os.getloadavg()[0]
    report["runners"] = figures
    report["summary"] = summarise(figures, list(checkpoints), report["targets"])
    write_benchmark_report(args.out, report, markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
