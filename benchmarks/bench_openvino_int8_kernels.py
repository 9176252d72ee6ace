"""Benchmark: which kernels OpenVINO runs an INT8 step graph with, read each way, and what it costs.

    python benchmarks/bench_openvino_int8_kernels.py --graph runs/pipeline/quantize/int8/step_int8.onnx \
        [--steps 200] [--threads 2] [--out benchmarks/results/openvino_int8_kernels]

The INT8 QDQ graph of `e3dpsm quantize`, compiled on the CPU device with the profile's
properties, read six ways:

- onnx-read-model / onnx-e3dpsm: the ONNX graph read by `read_model` alone, and as e3dpsm
  reads it (`runtime.openvino_session.protect_dequantization`: OpenVINO's common
  transformations without constant folding, as its own converter runs them);
- prepostprocessor-read-model / prepostprocessor-e3dpsm: the same behind a PrePostProcessor
  built with nothing asked of it (as benchmark_app and many applications do);
- stateful-read-model / stateful-e3dpsm: the stateful IR at batch 1 (`fix_batch`, then
  `make_stateful`) built from each.

For each: the heavy layers by run-time precision (`executed_layers`). The explicit-state and
stateful forms are timed side by side (interleaved rounds, the same frames and thread
count); medians and the ratios of each pair come from one run. Writes OUT_<isa kind>.json
and .md.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Callable

import numpy as np


class ExplicitRunner:
    """States fed in and read back by the metadata's names: the profile's explicit step."""

    def __init__(self, compiled: Any, meta: Any, window_ms: float) -> None:
        self.request, self.meta = compiled.create_infer_request(), meta
        self.window = np.full((1,), window_ms, np.float32)
        self.reset()

    def reset(self) -> None:
        self.state = {s.input_name: s.initial_value(1) for s in self.meta.states}

    def step(self, lnes: np.ndarray) -> None:
        feeds = {self.meta.frame_input["name"]: lnes, self.meta.window_input["name"]: self.window, **self.state}
        out = self.request.infer(feeds)
        named = {name: value for port, value in out.items() for name in port.get_names()}
        self.state = {s.input_name: np.array(named[s.output_name]) for s in self.meta.states}


class StatefulRunner:
    def __init__(self, compiled: Any, meta: Any, window_ms: float) -> None:
        self.request, self.meta = compiled.create_infer_request(), meta
        self.window = np.full((1,), window_ms, np.float32)

    def reset(self) -> None:
        self.request.reset_state()

    def step(self, lnes: np.ndarray) -> None:
        self.request.infer({self.meta.frame_input["name"]: lnes, self.meta.window_input["name"]: self.window})


def read_forms(graph: Path, meta: Any) -> dict[str, Callable[[], Any]]:
    """Each form's openvino.Model, built on call."""
    from openvino.preprocess import PrePostProcessor

    from e3dpsm.export.openvino_ir import fix_batch, make_stateful
    from e3dpsm.runtime.openvino_session import openvino_core, protect_dequantization

    def read(protect: bool) -> Any:
        model = openvino_core().read_model(str(graph))
        if protect:
            protect_dequantization(model)
        return model

    def stateful(protect: bool) -> Any:
        model = read(protect)
        fix_batch(model, meta, 1, states=False)
        make_stateful(model, meta, 1)
        return model

    forms: dict[str, Callable[[], Any]] = {}
    for suffix, protect in (("read-model", False), ("e3dpsm", True)):
        forms[f"onnx-{suffix}"] = lambda protect=protect: read(protect)
        forms[f"prepostprocessor-{suffix}"] = lambda protect=protect: PrePostProcessor(read(protect)).build()
        forms[f"stateful-{suffix}"] = lambda protect=protect: stateful(protect)
    return forms


def run(args: argparse.Namespace) -> dict[str, Any]:
    import onnx

    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.latency import latency_summary, measure_side_by_side
    from e3dpsm.runtime.openvino_session import compile_config, executed_layers, openvino_core

    graph = Path(args.graph)
    meta = GraphMetadata.from_onnx(onnx.load(str(graph), load_external_data=False), source=str(graph))
    config = {**compile_config(args.threads), "PERFORMANCE_HINT": "LATENCY"}  # the profile's properties
    compiled = {name: openvino_core().compile_model(build(), "CPU", config) for name, build in read_forms(graph, meta).items()}
    layers = {name: executed_layers(model) for name, model in compiled.items()}
    runners = {name: (StatefulRunner if name.startswith("stateful") else ExplicitRunner)(model, meta, args.window_ms)
               for name, model in compiled.items() if not name.startswith("prepostprocessor")}
    height, width = meta.frame_input["shape"][2:]
    frames = moving_edge_frames(min(args.steps + args.warmup, 400), int(height), int(width), args.window_ms).lnes
    times = measure_side_by_side(runners, frames, args.steps, args.warmup, args.chunk)
    summary = {name: latency_summary(t) for name, t in times.items()}
    ratios = {f"{kind}: read-model / e3dpsm": summary[f"{kind}-read-model"]["p50"] / summary[f"{kind}-e3dpsm"]["p50"]
              for kind in ("onnx", "stateful")}
    return {"graph": str(graph), "executed_layers": layers, "latency_ms": summary, "ratios": ratios}


def markdown(report: dict[str, Any]) -> str:
    machine, result = report["machine"], report["result"]
    lines = ["# OpenVINO on an INT8 step graph: executed kernels by how the graph is read", "",
             f"`{result['graph']}`; {report['config']['threads']} threads, {report['config']['steps']} timed steps "
             f"per runner, interleaved in chunks of {report['config']['chunk']}; {machine.get('cpu_model', '?')}, "
             f"{machine.get('cpu_count')} cores, ISA kind `{report['isa']['kind']}`; OpenVINO "
             f"{report['versions'].get('openvino')}.", "",
             "| form | heavy layers by run-time precision | p50 ms | min ms |", "|---|---|---:|---:|"]
    for name, counts in result["executed_layers"].items():
        lat = result["latency_ms"].get(name)
        timing = f"{lat['p50']:.2f} | {lat['min']:.2f}" if lat else "- | -"
        lines.append(f"| {name} | {', '.join(f'{k} x{v}' for k, v in counts.items())} | {timing} |")
    lines.append("")
    lines += [f"- {name} p50 = {ratio:.3f}" for name, ratio in result["ratios"].items()]
    return "\n".join(lines) + "\n"


def main() -> int:
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_benchmark_report
    from e3dpsm.utils.isa import detect_isa

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--graph", required=True, help="INT8 QDQ step graph (e3dpsm quantize)")
    for flag, kind, default in (("--steps", int, 200), ("--warmup", int, 20), ("--chunk", int, 25),
                                ("--threads", int, 2), ("--window-ms", float, 20.0)):
        parser.add_argument(flag, type=kind, default=default)
    parser.add_argument("--out", default="benchmarks/results/openvino_int8_kernels")
    args = parser.parse_args()
    report = {**report_header("bench_openvino_int8_kernels", vars(args)), "isa": detect_isa().to_dict()}
    report["result"] = run(args)
    write_benchmark_report(args.out, report, markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
