"""Benchmark: the committed trained `small` as ExecuTorch (.pte) and LiteRT (.tflite) artifacts
against its ONNX graph on ONNX Runtime, fp32, on held-out data.

    python benchmarks/bench_edge.py --data PREP [--checkpoint benchmarks/checkpoints/small/checkpoint.pt]
        [--forms grid_sample gather] [--steps 1000] [--timed-steps 300] [--threads 2]
        [--work DIR] [--out benchmarks/results/edge_small]

PREP: `e3dpsm synth --out D --sequences 1 --seconds 25 --seed 7 --render-scale 0.25` then
`e3dpsm prepare --data D --out PREP --window-ms 20 --height 96 --width 128` (1,250 frames no
training or calibration saw). For every attention form the checkpoint is converted to both
artifacts (conversion seconds and sizes kept); a golden record of the ONNX graph over
`--steps` frames is checked on each artifact with the fp32 profile (every pose within 0.01 mm
of the ONNX graph's at every step, states carried by the artifact's runtime); MPJPE and
PA-MPJPE against ground truth give dMPJPE; then every runner steps the same frames side by
side (`profiles.latency.measure_side_by_side`, rounds of 25 steps in turn) for the medians
and the ratio to ONNX Runtime fp32. The load average before and after is recorded (a shared
host). Writes OUT_<isa kind>.json and .md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

RUNTIME_OF = {".pte": "executorch", ".tflite": "litert", ".onnx": "onnxruntime"}


def convert_all(checkpoint: str, forms: list[str], work: Path) -> dict[str, dict[str, Any]]:
    """{label: {path, bytes, seconds, details}} for the ONNX graph and every artifact."""
    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.export import export_step
    from e3dpsm.export.executorch_export import ExecuTorchOptions, convert_executorch
    from e3dpsm.export.litert_export import LiteRTOptions, convert_litert

    model, _ = load_checkpoint(checkpoint)
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    onnx_path = export_step(model, work / "step.onnx")
    artifacts = {"onnxruntime-fp32": {"path": str(onnx_path), "bytes": onnx_path.stat().st_size,
                                      "seconds": round(time.perf_counter() - started, 1)}}
    for form in forms:
        for label, convert in ((f"executorch-fp32-{form}", lambda p: convert_executorch(model, p, ExecuTorchOptions(form))),
                               (f"litert-fp32-{form}", lambda p: convert_litert(model, p, LiteRTOptions(form)))):
            suffix = ".pte" if label.startswith("executorch") else ".tflite"
            record = work / f"{label}.convert.json"  # a rerun reuses the conversions a slow host finished
            if record.exists():
                artifacts[label] = json.loads(record.read_text())
                continue
            result = convert(work / f"{label}{suffix}").to_dict()
            artifacts[label] = {"path": result["path"], "bytes": result["bytes"], "seconds": result["seconds"]["total"],
                                "details": {k: result.get(k) for k in ("delegation", "ops", "seconds")}}
            record.write_text(json.dumps(artifacts[label]))
            print(f"converted {label}: {result['bytes'] / 1e6:.2f} MB in {result['seconds']['total']:.0f} s", flush=True)
    return artifacts


def check_all(artifacts: dict[str, dict[str, Any]], data: str, steps: int, threads: int, work: Path) -> dict[str, Any]:
    """Golden check of every artifact against the ONNX graph's rollout, and its accuracy."""
    from e3dpsm.golden.check import check_golden
    from e3dpsm.golden.record import onnx_reference, record_golden
    from e3dpsm.golden.store import load_golden
    from e3dpsm.golden.tolerances import PROFILES
    from e3dpsm.metrics import mpjpe, pa_mpjpe
    from e3dpsm.runtime.stepping import open_stepper

    golden_dir = work / "golden"
    if not golden_dir.exists():
        record_golden(onnx_reference(artifacts["onnxruntime-fp32"]["path"], threads=threads), data, golden_dir,
                      steps=steps, window_ms=20.0, split="all")
    golden = load_golden(golden_dir)
    gt = golden.gt_mm
    results = {}
    for label, entry in artifacts.items():
        runner = _PoseRecorder(open_stepper(entry["path"], threads=threads))
        check = check_golden(runner, golden, PROFILES["fp32"])
        pose = next(t for t in check.tensors if t.name == "pose")
        poses = np.concatenate(runner.poses)
        results[label] = {"passed": check.passed, "steps": check.steps, "pose_max_mm": float(pose.errors.max()),
                          "pose_mean_mm": pose.mean, "first_failure": check.first_failure,
                          "mpjpe_mm": mpjpe(poses, gt) if gt is not None else None,
                          "pa_mpjpe_mm": pa_mpjpe(poses, gt) if gt is not None else None}
        print(f"{label}: golden check {'PASSED' if check.passed else 'FAILED'}, pose max "
              f"{results[label]['pose_max_mm']:.2e} mm", flush=True)
    return results


class _PoseRecorder:
    """A stepper that keeps the fused poses it returns (for MPJPE against ground truth)."""

    def __init__(self, runner: Any) -> None:
        self.runner, self.meta, self.poses = runner, runner.meta, []

    def init_state(self, batch: int = 1):
        return self.runner.init_state(batch)

    def step(self, lnes, state, window_ms):
        out, state = self.runner.step(lnes, state, window_ms)
        self.poses.append(np.asarray(out["pose"]))
        return out, state


def time_all(artifacts: dict[str, dict[str, Any]], data: str, timed: int, threads: int) -> dict[str, Any]:
    from e3dpsm.profiles.inputs import prepared_frames
    from e3dpsm.profiles.latency import latency_summary, measure_side_by_side
    from e3dpsm.runtime.session import CarriedStateRunner
    from e3dpsm.runtime.stepping import open_stepper

    runners = {label: CarriedStateRunner(open_stepper(entry["path"], threads=threads), 20.0)
               for label, entry in artifacts.items()}
    frames = prepared_frames(data, timed + 20, 96, 128).lnes
    times = measure_side_by_side(runners, frames, timed, warmup=20)
    summary = {label: latency_summary(t) for label, t in times.items()}
    base = summary["onnxruntime-fp32"]["p50"]
    for entry in summary.values():
        entry["speed_vs_onnxruntime_fp32"] = base / entry["p50"]
    return summary


def markdown(report: dict[str, Any]) -> str:
    lines = [f"# Edge artifacts of the trained small (fp32), {report['machine']['isa']['kind']} host",
             "", f"Command: `{report['command']}`; {report['checks_steps']} held-out steps; {report['threads']} threads; "
             f"load average {report['load_before'][0]:.1f} before, {report['load_after'][0]:.1f} after (shared 2-core host).",
             "", "| artifact | conversion s | size MB | max pose diff to ONNX (mm) | golden check | MPJPE mm | dMPJPE mm | "
                 "step ms (p50) | speed vs ORT fp32 | delegated MACs |",
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
    base = report["checks"]["onnxruntime-fp32"]["mpjpe_mm"]
    for label, entry in report["artifacts"].items():
        check, speed = report["checks"][label], report["timing"][label]
        delegation = (entry.get("details") or {}).get("delegation") or {}
        share = f"{delegation['delegated_share']:.1%}" if delegation.get("delegated_share") is not None else "-"
        d_mpjpe = check["mpjpe_mm"] - base if check["mpjpe_mm"] is not None and base is not None else float("nan")
        lines.append(f"| {label} | {entry['seconds']:.0f} | {entry['bytes'] / 1e6:.2f} | {check['pose_max_mm']:.2e} | "
                     f"{'passed' if check['passed'] else 'FAILED'} | {check['mpjpe_mm']:.2f} | {d_mpjpe:+.4f} | "
                     f"{speed['p50']:.2f} | {speed['speed_vs_onnxruntime_fp32']:.2f}x | {share} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--checkpoint", default="benchmarks/checkpoints/small/checkpoint.pt")
    parser.add_argument("--forms", nargs="+", default=["grid_sample", "gather"])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--timed-steps", type=int, default=300)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--work", default="runs/bench_edge")
    parser.add_argument("--out", default="benchmarks/results/edge_small")
    args = parser.parse_args(argv)
    import torch

    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    torch.set_num_threads(args.threads)
    report = report_header("bench_edge", vars(args))
    report.update(command="python benchmarks/bench_edge.py " + " ".join(sys.argv[1:] if argv is None else argv),
                  threads=args.threads, checks_steps=args.steps, load_before=list(os.getloadavg()))
    work = Path(args.work)
    report["artifacts"] = convert_all(args.checkpoint, args.forms, work)
    report["checks"] = check_all(report["artifacts"], args.data, args.steps, args.threads, work)
    report["timing"] = time_all(report["artifacts"], args.data, args.timed_steps, args.threads)
    report["load_after"] = list(os.getloadavg())
    out = f"{args.out}_{report['machine']['isa']['kind']}"
    write_json_atomic(out + ".json", report)
    write_text_atomic(out + ".md", markdown(report))
    print(markdown(report))
    return 0 if all(c["passed"] for c in report["checks"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
