"""Benchmark: deformable attention in the exported fp32 step graph, before vs after its
rewrite for CPU speed.

    python benchmarks/bench_deformable.py --graph before=runs/before_paper/step.onnx \
        --graph after=runs/after_paper/step.onnx [--graph NAME=PATH ...] \
        [--steps 200] [--threads 2] [--profile-steps 30] [--out benchmarks/results/deformable]

Every graph runs the same synthetic LNES frames (moving edges, 20 ms windows) with its states
carried, through e3dpsm.runtime.StepSession on the ONNX Runtime CPU provider. Timing is
interleaved: rounds of `--chunk` steps per graph in turn, medians per graph, and speed-up
ratios against the first graph. Then profiled sessions of all graphs, stepped in turn, give
kernel time per op type and per module group (profiles.graph_groups, the grouping of
`e3dpsm profile`), summing per node the median over steps (robust to descheduled threads on
a shared machine), and the share of deformable attention in the step's kernel time.
Writes OUT.json and OUT.md.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

ATTENTION_GROUP = "deformable_attention"
_KERNEL_SUFFIX = "_kernel_time"


def graph_runner(path: str, threads: int, window_ms: float, profile_prefix: str | None = None):
    """A CPU step session carrying its own state (e3dpsm.runtime.CarriedStateRunner)."""
    from e3dpsm.profiles.latency import ort_session_options
    from e3dpsm.runtime.session import CarriedStateRunner, StepSession

    session = StepSession(path, threads=threads, providers=["CPUExecutionProvider"],
                          options=ort_session_options(threads, profile_prefix))
    return CarriedStateRunner(session, window_ms)


def node_medians(trace_path: str) -> tuple[dict[str, float], dict[str, str], int]:
    """Per node: the median over steps of its kernel time (ms), its op type; and the step
    count. Medians per node, not means: on a shared machine a descheduled thread inflates
    single kernel calls, and a median over steps ignores those outliers."""
    events = json.loads(Path(trace_path).read_text(encoding="utf-8"))
    steps = sum(1 for e in events if e.get("cat") == "Session" and e.get("name") == "model_run")
    calls: dict[str, list[float]] = defaultdict(list)
    op_of: dict[str, str] = {}
    for e in events:
        if e.get("cat") == "Node" and str(e.get("name", "")).endswith(_KERNEL_SUFFIX):
            node = str(e["name"])[: -len(_KERNEL_SUFFIX)]
            calls[node].append(float(e.get("dur", 0)) / 1e3)
            op_of[node] = str(e.get("args", {}).get("op_name", "?"))
    # A node that runs k times per step (none here) would count k medians: sum per step first.
    per_step = {node: float(np.median(np.asarray(ms).reshape(-1, max(len(ms) // max(steps, 1), 1)).sum(axis=1)))
                for node, ms in calls.items()}
    return per_step, op_of, steps


def profile_interleaved(graphs: dict[str, str], frames: np.ndarray, threads: int, window_ms: float,
                        steps: int, tmp: Path) -> dict[str, dict[str, Any]]:
    """Profiled sessions of every graph, stepped in turn (one step each per round), then per
    node medians summed by op type and by module group (profiles.graph_groups)."""
    from e3dpsm.profiles.flops_onnx import load_graph, static_shapes
    from e3dpsm.profiles.graph_groups import assign_groups

    runners = {name: graph_runner(path, threads, window_ms, profile_prefix=str(tmp / name))
               for name, path in graphs.items()}
    for k in range(steps):
        for runner in runners.values():
            runner.step(frames[k % len(frames)][None])
    out = {}
    for name, runner in runners.items():
        graph = load_graph(graphs[name])
        groups = assign_groups(graph, static_shapes(graph)[1])
        per_node, op_of, counted = node_medians(runner.session.session.end_profiling())
        by_op: dict[str, float] = defaultdict(float)
        by_module: dict[str, float] = defaultdict(float)
        for node, ms in per_node.items():
            by_op[op_of[node]] += ms
            by_module[group_of_node(node, groups)] += ms
        kernel = sum(per_node.values())
        attention = by_module.get(ATTENTION_GROUP, 0.0)
        out[name] = {
            "steps": counted, "nodes": len(graph.graph.node), "kernel_ms_per_step": kernel,
            "by_op_type_ms": dict(sorted(by_op.items(), key=lambda kv: -kv[1])),
            "by_module_ms": dict(sorted(by_module.items(), key=lambda kv: -kv[1])),
            "attention_share": attention / kernel if kernel else 0.0,
            "attention_nodes_ms": dict(sorted(((n, ms) for n, ms in per_node.items()
                                               if group_of_node(n, groups) == ATTENTION_GROUP),
                                              key=lambda kv: -kv[1])[:40]),
        }
    return out


def group_of_node(node: str, groups: dict[str, str]) -> str:
    if node in groups:
        return groups[node]
    # ORT-fused nodes are named after the first node they absorb, plus a suffix.
    best = max((k for k in groups if node.startswith(k)), key=len, default=None)
    return groups[best] if best else "unmapped (ORT-created)"


def table(rows: list[str], columns: dict[str, dict[str, float]], title: str) -> list[str]:
    names = list(columns)
    lines = [f"| {title} | " + " | ".join(f"{n} ms" for n in names) + " |", "|---|" + "---|" * len(names)]
    for row in rows:
        lines.append(f"| {row} | " + " | ".join(f"{columns[n].get(row, 0.0):.3f}" for n in names) + " |")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--graph", action="append", required=True, help="NAME=PATH; the first is the baseline")
    parser.add_argument("--steps", type=int, default=200, help="timed steps per graph (0: profiles only)")
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--chunk", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--profile-steps", type=int, default=30)
    parser.add_argument("--profile-threads", type=int, default=None, help="threads of the profiled sessions "
                        "(default: --threads)")
    parser.add_argument("--window-ms", type=float, default=20.0)
    parser.add_argument("--out", default="benchmarks/results/deformable")
    parser.add_argument("--note", default="", help="free text recorded in the report (e.g. machine load)")
    args = parser.parse_args()

    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.latency import latency_summary, measure_side_by_side
    from e3dpsm.runtime.session import StepSession
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic

    graphs = dict(item.split("=", 1) for item in args.graph)
    first = StepSession(next(iter(graphs.values())), threads=1)
    height, width = first.meta.frame_hw
    frames = moving_edge_frames(64, height, width, args.window_ms).lnes

    base = next(iter(graphs))
    latency: dict[str, dict[str, float]] = {}
    ratios: dict[str, float] = {}
    if args.steps:
        runners = {name: graph_runner(path, args.threads, args.window_ms) for name, path in graphs.items()}
        times = measure_side_by_side(runners, frames, args.steps, args.warmup, chunk=args.chunk)
        latency = {name: latency_summary(t) for name, t in times.items()}
        ratios = {name: latency[base]["p50"] / latency[name]["p50"] for name in graphs}
    with tempfile.TemporaryDirectory(prefix="e3dpsm-bench-deform-") as tmp:
        profiles = profile_interleaved(graphs, frames, args.profile_threads or args.threads, args.window_ms,
                                       args.profile_steps, Path(tmp))

    report = report_header("bench_deformable", {**vars(args)})
    report.update(graphs=graphs, frames="synthetic moving edges, 64 frames reused", latency_ms=latency,
                  speedup_vs_first=ratios, ort_profiles=profiles,
                  method=f"interleaved rounds of {args.chunk} steps per graph, {args.steps} timed steps each after "
                         f"{args.warmup} warm-up steps, medians, {args.threads} threads; ORT profiles from "
                         f"separate sessions stepped in turn, {args.profile_steps} steps, "
                         f"{args.profile_threads or args.threads} threads, per node the median over steps")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    ops = sorted({op for p in profiles.values() for op in p["by_op_type_ms"]},
                 key=lambda op: -max(p["by_op_type_ms"].get(op, 0.0) for p in profiles.values()))
    modules = sorted({m for p in profiles.values() for m in p["by_module_ms"]},
                     key=lambda m: -max(p["by_module_ms"].get(m, 0.0) for p in profiles.values()))
    md = [f"# Deformable attention in the exported step graph ({', '.join(graphs)})", "",
          f"Created {report.get('created', '')}; {report['method']}. {args.note}", "",
          f"| graph | nodes | p50 ms | p90 ms | speed-up vs {base} (p50) | kernel ms / step | "
          "deformable attention ms | share |",
          "|---|---|---|---|---|---|---|---|"]
    kernel_ratio = {n: profiles[base]["kernel_ms_per_step"] / p["kernel_ms_per_step"] for n, p in profiles.items()}
    report["kernel_speedup_vs_first"] = kernel_ratio
    for name in graphs:
        p = profiles[name]
        lat = latency.get(name, {"p50": float("nan"), "p90": float("nan")})
        md.append(f"| {name} | {p['nodes']} | {lat['p50']:.2f} | {lat['p90']:.2f} | "
                  f"{ratios.get(name, float('nan')):.2f}x | {p['kernel_ms_per_step']:.2f} | "
                  f"{p['by_module_ms'].get(ATTENTION_GROUP, 0.0):.2f} | {100 * p['attention_share']:.1f}% |")
    md += ["", f"Kernel-time speed-up vs {base}: " + ", ".join(f"{n} {r:.2f}x" for n, r in kernel_ratio.items()), ""]
    md += ["", "## Kernel time per module group (ORT profile, ms per step)", ""]
    md += table(modules, {n: p["by_module_ms"] for n, p in profiles.items()}, "module")
    md += ["", "## Kernel time per op type (ORT profile, ms per step; top 25)", ""]
    md += table(ops[:25], {n: p["by_op_type_ms"] for n, p in profiles.items()}, "op type")
    write_json_atomic(out.with_suffix(".json"), report)
    out.with_suffix(".md").write_text("\n".join(md) + "\n", encoding="utf-8")
    print("\n".join(md[:4 + len(graphs) + 1]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
