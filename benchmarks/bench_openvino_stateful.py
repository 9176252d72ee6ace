"""Benchmark: per-step latency of the stateful OpenVINO IR vs explicit-state OpenVINO.

    python benchmarks/bench_openvino_stateful.py [--variants tiny small] [--steps 200] [--threads 2] \
        [--out benchmarks/results/openvino_stateful]

Per variant (initial weights; latency does not depend on training), the fp32 step graph is
exported once and run four ways on the OpenVINO CPU device, all with the same frames
(moving edges, 20 ms windows), thread count and f32 precision hint:

- explicit     profiles.latency.OpenVinoRunner: states fed in and read back every step
- stateful     profiles.latency.OpenVinoStatefulRunner: the stateful IR, frame + window only
- explicit-session / stateful-session: the same through e3dpsm.runtime's sessions (input
  checks, output copies, and for the stateful one the variables left inside)

Timing is interleaved (rounds of --chunk steps per runner in turn); medians per runner and
ratios measured in the same run. Writes OUT.json and OUT.md.
"""
from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np


class ExplicitSessionRunner:
    def __init__(self, path: str, threads: int, window_ms: float) -> None:
        from e3dpsm.runtime.openvino_session import OpenVINOStepSession

        self.session, self.window_ms = OpenVINOStepSession(path, threads=threads), window_ms
        self.reset()

    def reset(self) -> None:
        self.state = self.session.init_state(1)

    def step(self, lnes: np.ndarray) -> None:
        _, self.state = self.session.step(lnes, self.state, self.window_ms)


class StatefulSessionRunner:
    def __init__(self, xml: str, threads: int, window_ms: float) -> None:
        from e3dpsm.runtime.openvino_stateful import OpenVINOStatefulSession

        self.session, self.window_ms = OpenVINOStatefulSession(xml, threads=threads), window_ms

    def reset(self) -> None:
        self.session.reset()

    def step(self, lnes: np.ndarray) -> None:
        self.session.step(lnes, self.window_ms)


def bench_variant(variant: str, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    import torch

    import e3dpsm
    from e3dpsm.export import export_step
    from e3dpsm.export.openvino_ir import convert_step_graph, save_ir
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.latency import OpenVinoRunner, OpenVinoStatefulRunner, latency_summary, measure_side_by_side
    from e3dpsm.profiles.targets import load_targets

    torch.set_num_threads(args.threads)
    model = e3dpsm.create_model(variant).eval()
    graph = export_step(model, work / f"{variant}.onnx")
    xml = save_ir(convert_step_graph(graph, stateful=True, batch=1)[0], work / f"{variant}_stateful.xml")[0]
    targets = load_targets()
    plain = replace(targets["openvino-cpu-fp32"], threads=args.threads)
    stateful = replace(targets["openvino-cpu-stateful-fp32"], threads=args.threads)
    runners = {
        "explicit": OpenVinoRunner(str(graph), plain, args.window_ms),
        "stateful": OpenVinoStatefulRunner(str(graph), stateful, args.window_ms),
        "explicit-session": ExplicitSessionRunner(str(graph), args.threads, args.window_ms),
        "stateful-session": StatefulSessionRunner(str(xml), args.threads, args.window_ms),
    }
    cfg = model.config
    frames = moving_edge_frames(min(args.steps + args.warmup, 400), cfg.height, cfg.width, args.window_ms).lnes
    times = measure_side_by_side(runners, frames, args.steps, args.warmup, args.chunk)
    summary = {name: latency_summary(t) for name, t in times.items()}
    ratios = {"explicit / stateful": summary["explicit"]["p50"] / summary["stateful"]["p50"],
              "explicit-session / stateful-session":
                  summary["explicit-session"]["p50"] / summary["stateful-session"]["p50"]}
    states = model.state_spec()
    return {"variant": variant, "params": model.num_parameters(),
            "state_values": int(sum(np.prod(s.shape) for s in states)), "latency_ms": summary, "ratios": ratios}


def markdown(report: dict[str, Any]) -> str:
    lines = ["# Stateful vs explicit-state OpenVINO (CPU, fp32)", "",
             f"{report['config']['threads']} threads, {report['config']['steps']} timed steps per runner, "
             f"interleaved in chunks of {report['config']['chunk']}; machine shared with other jobs "
             f"({report['machine'].get('cpu_model', '?')}, {report['machine'].get('cpu_count')} cores); "
             f"OpenVINO {report['versions'].get('openvino')}.", "",
             "| variant | state values | runner | p50 ms | p90 ms | min ms |", "|---|---:|---|---:|---:|---:|"]
    for entry in report["variants"]:
        for name, lat in entry["latency_ms"].items():
            lines.append(f"| {entry['variant']} | {entry['state_values']} | {name} | {lat['p50']:.2f} | "
                         f"{lat['p90']:.2f} | {lat['min']:.2f} |")
    lines.append("")
    for entry in report["variants"]:
        for name, ratio in entry["ratios"].items():
            lines.append(f"- {entry['variant']}: {name} p50 = {ratio:.3f}")
    return "\n".join(lines) + "\n"


def main() -> int:
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=["tiny", "small"])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--chunk", type=int, default=25)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--window-ms", type=float, default=20.0)
    parser.add_argument("--out", default="benchmarks/results/openvino_stateful")
    args = parser.parse_args()
    report = report_header("bench_openvino_stateful", vars(args))
    with tempfile.TemporaryDirectory(prefix="e3dpsm-bench-ov-") as tmp:
        report["variants"] = [bench_variant(v, args, Path(tmp)) for v in args.variants]
    out = Path(args.out)
    write_json_atomic(out.with_suffix(".json"), report)
    write_text_atomic(out.with_suffix(".md"), markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
