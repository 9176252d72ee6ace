"""Benchmark: the PyTorch step on a CUDA GPU, states carried: how fast the step
runs where the paper measured it, beside the paper's figures.

    python benchmarks/bench_gpu.py [--variant paper] [--checkpoint CKPT] [--steps 500]
        [--modes eager cudagraph cudagraph-tf32 cudagraph-bf16 compile compile-cudagraph]
        [--stream-batch 16] [--budget-s 360] [--out-dir benchmarks/results]

One pose update is one call of `E3DPSM.step` on one LNES frame (synthetic moving edges,
20 ms windows), with the S5 and Kalman states carried from step to step, as a live stream
runs it. Modes:

- eager: the module as written, under `torch.inference_mode`.
- cudagraph: one `torch.cuda.CUDAGraph` holding the whole step and the copy of the new
  states into the input state buffers, so a step is one replay (no per-kernel launches).
- cudagraph-tf32 / cudagraph-bf16: the same graph with TF32 matrix units, or under bf16
  autocast: faster, not bit-faithful; their pose difference to fp32 is reported.
- compile: `torch.compile` (Inductor, default mode) of the step; compile-cudagraph: that
  compiled step captured in a CUDA graph as above.

fp32 modes run with TF32 off, so they compute what the CPU computes: each mode's first
`--parity-steps` poses are compared with the CPU fp32 module on the same frames (max |d| mm).

Per mode the report gives the latency of a live step (host frame in, pose back on the host:
copy in, step, copy out and synchronise; median and p90 of `--steps` steps, and the rate
that median allows), the GPU time per step when steps are queued back to back (CUDA events
over `--steps` steps), the peak GPU memory, and, for the graphed fp32 step, the throughput
of `--stream-batch` streams stepped as one batch. Every mode's result is written as soon as
it is measured, and a mode that fails records its error, so a run cut short keeps what it
measured. Modes that would start after `--budget-s` seconds are skipped and say so.

Writes OUT_DIR/gpu_<device>.json and .md beside the paper's figures (one A6000: 80 Hz,
6.64 M parameters, 8.16 GFLOPs, 74 MB GPU memory; the paper's Table 5, App. C).
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

PAPER_REFERENCE = {
    "gpu": "NVIDIA RTX A6000",
    "pose_update_hz": 80.0,
    "params_m": 6.64,
    "gflops": 8.16,
    "gpu_memory_mb": 74.0,
    "source": "paper, Table 5 (model efficiency comparison, one A6000), App. C",
}
ALL_MODES = ("eager", "cudagraph", "cudagraph-tf32", "cudagraph-bf16", "compile", "compile-cudagraph")
FP32_MODES = {"eager", "cudagraph", "compile", "compile-cudagraph"}

State = dict[str, torch.Tensor]
StepFn = Callable[[torch.Tensor, Mapping[str, torch.Tensor], torch.Tensor], tuple[dict[str, torch.Tensor], State]]


def slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_") or "device"


def set_tf32(enabled: bool) -> None:
    torch.backends.cuda.matmul.allow_tf32 = enabled
    torch.backends.cudnn.allow_tf32 = enabled


class EagerStepper:
    """Calls a step function, carrying its state in a dict of device tensors."""

    def __init__(self, fn: StepFn, initial: State, window: torch.Tensor) -> None:
        self.fn, self.initial, self.window = fn, initial, window
        self.reset()

    def reset(self) -> None:
        self.state = {k: v.clone() for k, v in self.initial.items()}

    def step(self, frame: torch.Tensor) -> torch.Tensor:
        outputs, self.state = self.fn(frame, self.state, self.window)
        return outputs["pose"]


class GraphedStepper:
    """One CUDA graph per step: static frame and state buffers; the captured work ends by
    copying the new states into the state buffers, so the next replay reads them."""

    def __init__(self, fn: StepFn, initial: State, window: torch.Tensor, example: torch.Tensor,
                 autocast: torch.dtype | None = None) -> None:
        self.initial = initial
        self.frame = example.clone()
        self.state = {k: v.clone() for k, v in initial.items()}

        def body() -> torch.Tensor:
            with torch.autocast("cuda", dtype=autocast, enabled=autocast is not None):
                outputs, new_state = fn(self.frame, self.state, window)
            for name, buffer in self.state.items():
                buffer.copy_(new_state[name])
            return outputs["pose"].float()

        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):  # warm-up off the capture stream (allocator, cuDNN plans)
            for _ in range(3):
                body()
        torch.cuda.current_stream().wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.pose = body()
        self.reset()

    def reset(self) -> None:
        for name, buffer in self.state.items():
            buffer.copy_(self.initial[name])

    def step(self, frame: torch.Tensor) -> torch.Tensor:
        self.frame.copy_(frame, non_blocking=True)
        self.graph.replay()
        return self.pose


def cpu_reference(model: torch.nn.Module, frames: torch.Tensor, window_ms: float, steps: int) -> np.ndarray:
    """Poses of the CPU fp32 module over the first `steps` frames, state carried."""
    cpu = model.to("cpu")
    state = cpu.init_state(1, "cpu")
    window = torch.tensor([window_ms])
    poses = []
    with torch.inference_mode():
        for k in range(steps):
            outputs, state = cpu.step(frames[k % len(frames)][None], state, window)
            poses.append(outputs["pose"][0].numpy().copy())
    return np.stack(poses)


def live_latency(stepper: Any, host_frames: torch.Tensor, device: torch.device, steps: int,
                 warmup: int) -> dict[str, float]:
    """Host frame in, pose out on the host, synchronised: what a live stream waits per step."""
    times = []
    for k in range(warmup + steps):
        frame = host_frames[k % len(host_frames)]
        t0 = time.perf_counter()
        pose = stepper.step(frame.to(device, non_blocking=True)[None]).to("cpu")
        times.append((time.perf_counter() - t0) * 1e3)
        del pose
    times = times[warmup:]
    median = statistics.median(times)
    return {"latency_median_ms": median, "latency_p90_ms": float(np.percentile(times, 90)),
            "latency_min_ms": min(times), "hz_at_median": 1e3 / median}


def queued_gpu_time(stepper: Any, inputs: torch.Tensor, steps: int) -> float:
    """GPU time per step, steps queued back to back (CUDA events around the whole run);
    inputs [K, B, 2, H, W] on the device, stepped in turn."""
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    torch.cuda.synchronize()
    start.record()
    for k in range(steps):
        stepper.step(inputs[k % len(inputs)])
    end.record()
    torch.cuda.synchronize()
    return start.elapsed_time(end) / steps


def parity(stepper: Any, device_frames: torch.Tensor, reference: np.ndarray) -> dict[str, float]:
    stepper.reset()
    poses = np.stack([stepper.step(device_frames[k % len(device_frames)][None])[0].float().cpu().numpy()
                      for k in range(len(reference))])
    diff = np.abs(poses.astype(np.float64) - reference)
    return {"parity_steps": len(reference), "max_abs_diff_mm": float(diff.max()),
            "last_step_max_abs_diff_mm": float(diff[-1].max()), "finite": bool(np.isfinite(poses).all())}


def build_stepper(mode: str, model: torch.nn.Module, initial: State, window: torch.Tensor,
                  example: torch.Tensor) -> Any:
    set_tf32(mode == "cudagraph-tf32")
    if mode == "eager":
        return EagerStepper(model.step, initial, window)
    if mode in ("cudagraph", "cudagraph-tf32"):
        return GraphedStepper(model.step, initial, window, example)
    if mode == "cudagraph-bf16":
        return GraphedStepper(model.step, initial, window, example, autocast=torch.bfloat16)
    compiled = torch.compile(model.step, mode="default", dynamic=False, fullgraph=False)
    if mode == "compile":
        stepper = EagerStepper(compiled, initial, window)
        for _ in range(3):  # compile and autotune outside the timed steps
            stepper.step(example)
        return stepper
    if mode == "compile-cudagraph":
        return GraphedStepper(compiled, initial, window, example)
    raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(ALL_MODES)}")


def stream_batch_throughput(model: torch.nn.Module, frames: torch.Tensor, window: torch.Tensor,
                            batch: int, steps: int) -> dict[str, float]:
    """`batch` streams stepped together in one graphed fp32 step: poses per second."""
    set_tf32(False)
    initial = model.init_state(batch, frames.device)
    example = frames[:batch] if len(frames) >= batch else frames[:1].expand(batch, -1, -1, -1).contiguous()
    stepper = GraphedStepper(model.step, initial, window, example)
    ms = queued_gpu_time(stepper, example[None], steps)
    return {"stream_batch": batch, "gpu_ms_per_batched_step": ms, "poses_per_s": batch * 1e3 / ms}


def render_markdown(report: dict[str, Any]) -> str:
    ref = report["paper_reference"]
    lines = [f"# `{report['config']['variant']}` step on {report['device']['name']} (PyTorch {report['versions']['torch']})",
             "",
             f"Paper: {ref['pose_update_hz']:.0f} Hz on one {ref['gpu']} ({ref['params_m']} M parameters, "
             f"{ref['gpu_memory_mb']:.0f} MB GPU memory). Here: {report['params_m']:.2f} M parameters. "
             f"Batch 1, states carried, {report['config']['steps']} timed steps per mode after "
             f"{report['config']['warmup']} warm-up steps; synthetic moving-edge frames, "
             f"{report['config']['window_ms']:g} ms windows.",
             "",
             "| mode | live step median (ms) | p90 (ms) | Hz at median | x paper's 80 Hz | GPU ms/step queued | peak GPU MB | max pose diff to CPU fp32 (mm) |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for mode, r in report["modes"].items():
        if "error" in r or "skipped" in r:
            lines.append(f"| {mode} | {r.get('error') or r.get('skipped')} | | | | | | |")
            continue
        lines.append(f"| {mode} | {r['latency_median_ms']:.2f} | {r['latency_p90_ms']:.2f} | {r['hz_at_median']:.0f} | "
                     f"{r['hz_at_median'] / ref['pose_update_hz']:.1f} | {r['gpu_ms_per_step_queued']:.2f} | "
                     f"{r['peak_gpu_memory_mb']:.0f} | {r['max_abs_diff_mm']:.2g} |")
    batch = report.get("stream_batch")
    if batch and "error" not in batch:
        lines += ["", f"{batch['stream_batch']} streams in one graphed fp32 step: {batch['gpu_ms_per_batched_step']:.2f} ms "
                      f"per step, {batch['poses_per_s']:.0f} poses/s."]
    elif batch:
        lines += ["", f"Stream batch: {batch['error']}"]
    lines += ["", "Live step: host frame copied in, step, pose copied back, synchronised. "
                  "fp32 modes run with TF32 off; the tf32 and bf16 rows trade exactness for speed."]
    return "\n".join(lines) + "\n"


def write_report(report: dict[str, Any], out_dirs: list[Path]) -> None:
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    name = f"gpu_{slug(report['device']['name'])}"
    for out in out_dirs:
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / f"{name}.json", report)
        write_text_atomic(out / f"{name}.md", render_markdown(report))


def error_line(exc: Exception) -> str:
    first = str(exc).splitlines()[0][:300] if str(exc) else ""
    return f"{type(exc).__name__}: {first}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", default="paper")
    parser.add_argument("--checkpoint", help="an e3dpsm checkpoint (default: the variant, seeded random weights)")
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--warmup", type=int, default=50)
    parser.add_argument("--parity-steps", type=int, default=100)
    parser.add_argument("--window-ms", type=float, default=20.0)
    parser.add_argument("--modes", nargs="+", default=list(ALL_MODES), choices=ALL_MODES)
    parser.add_argument("--stream-batch", type=int, default=16, help="0 skips the batched-streams throughput")
    parser.add_argument("--budget-s", type=float, default=360.0, help="start no mode after this many seconds")
    parser.add_argument("--out-dir", action="append", type=Path,
                        help="where gpu_<device>.json/.md go (repeatable; default benchmarks/results)")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("error: no CUDA device visible to PyTorch; run this on a machine with an NVIDIA GPU", file=sys.stderr)
        return 2
    began = time.perf_counter()
    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.models.registry import create_model
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.utils.env import report_header

    torch.manual_seed(0)
    if args.checkpoint:
        model, _ = load_checkpoint(args.checkpoint, variant=args.variant)
    else:
        model = create_model(args.variant).eval()
    cfg = model.config
    frames_np = moving_edge_frames(64, cfg.height, cfg.width, args.window_ms).lnes
    host_frames = torch.from_numpy(frames_np)
    reference = cpu_reference(model, host_frames, args.window_ms, args.parity_steps)

    device = torch.device("cuda")
    model = model.to(device).eval()
    host_frames = host_frames.pin_memory()
    device_frames = host_frames.to(device)
    window = torch.tensor([args.window_ms], device=device)
    initial = model.init_state(1, device)
    props = torch.cuda.get_device_properties(device)
    report = report_header("bench_gpu", {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                                         if k != "out_dir"})
    report.update(device={"name": torch.cuda.get_device_name(device), "capability": list(torch.cuda.get_device_capability(device)),
                          "multiprocessors": props.multi_processor_count, "memory_gb": round(props.total_memory / 2**30, 1),
                          "cuda": torch.version.cuda, "cudnn": torch.backends.cudnn.version()},
                  paper_reference=PAPER_REFERENCE, params_m=model.num_parameters() / 1e6,
                  frames="synthetic moving edges (e3dpsm.profiles.inputs.moving_edge_frames), 64 frames reused",
                  modes={})
    out_dirs = args.out_dir or [Path("benchmarks/results")]
    with torch.inference_mode():
        for mode in args.modes:
            elapsed = time.perf_counter() - began
            if elapsed > args.budget_s:
                report["modes"][mode] = {"skipped": f"not started: {elapsed:.0f} s > --budget-s {args.budget_s:g}"}
                write_report(report, out_dirs)
                continue
            print(f"[{elapsed:5.0f} s] {mode} ...", flush=True)
            try:
                torch.cuda.synchronize()
                torch.cuda.reset_peak_memory_stats(device)
                t0 = time.perf_counter()
                stepper = build_stepper(mode, model, initial, window, device_frames[:1])
                result: dict[str, Any] = {"build_s": time.perf_counter() - t0}
                result.update(parity(stepper, device_frames, reference))
                stepper.reset()
                result.update(live_latency(stepper, host_frames, device, args.steps, args.warmup))
                result["gpu_ms_per_step_queued"] = queued_gpu_time(stepper, device_frames[:, None], args.steps)
                result["peak_gpu_memory_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
                result["exact_fp32"] = mode in FP32_MODES
                del stepper
            except Exception as exc:  # record and go on: one mode's failure must not lose the others
                result = {"error": error_line(exc),
                          "traceback": traceback.format_exc()[-2000:]}
            report["modes"][mode] = result
            write_report(report, out_dirs)
            print(json.dumps({k: v for k, v in result.items() if k != "traceback"}), flush=True)
        if args.stream_batch > 0 and time.perf_counter() - began <= args.budget_s:
            try:
                report["stream_batch"] = stream_batch_throughput(model, device_frames, window, args.stream_batch, args.steps)
            except Exception as exc:
                report["stream_batch"] = {"error": error_line(exc)}
    report["wall_s"] = time.perf_counter() - began
    write_report(report, out_dirs)
    print(render_markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
