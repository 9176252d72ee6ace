"""`e3dpsm parity`: ONNX (or OpenVINO, plain or stateful) vs PyTorch, every output and state at every step."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from e3dpsm.cli._common import add_model_source, add_threads, load_model_from_args, positive_float, positive_int


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("parity", help="check an exported graph against PyTorch over a long rollout",
                       description="Runs the graph and the PyTorch step side by side, each carrying its own "
                                   "states; exits 1 when a tolerance is exceeded.")
    p.add_argument("--model", required=True,
                   help="exported step graph (step.onnx); with --runtime openvino-stateful also a stateful IR (.xml)")
    add_model_source(p)
    p.add_argument("--data", help="prepared folder for the frames (default: a synthetic sequence made on the fly)")
    p.add_argument("--split", default=None, help="split of --data to use (default: all sequences)")
    p.add_argument("--steps", type=positive_int, default=1000)
    p.add_argument("--window-ms", type=positive_float, nargs="+", default=[20.0],
                   help="one or more window lengths, e.g. 20 25 50")
    p.add_argument("--runtime", choices=("onnxruntime", "openvino", "openvino-stateful"), default="onnxruntime",
                   help="openvino-stateful converts an .onnx to a stateful IR in a temporary folder and compares "
                        "the states read back from its variables")
    add_threads(p)
    p.add_argument("--pose-atol-mm", type=positive_float, default=0.01)
    p.add_argument("--state-rtol", type=positive_float, default=1e-4)
    p.add_argument("--report", help="JSON report path (default: parity-<runtime>.json beside the model)")
    p.set_defaults(func=run)
    return p


def make_runner(path: str, runtime: str, threads: int, workdir: Path | None = None):
    if runtime == "openvino-stateful":
        from e3dpsm.runtime.openvino_stateful import ExplicitStateView, OpenVINOStatefulSession

        if Path(path).suffix != ".xml":
            from e3dpsm.export.openvino_ir import convert_step_graph, save_ir

            if workdir is None:
                raise ValueError("converting an ONNX graph needs a work folder")
            model, _ = convert_step_graph(path, stateful=True, batch=1)
            path = str(save_ir(model, workdir / f"{Path(path).stem}.xml")[0])
        return ExplicitStateView(OpenVINOStatefulSession(path, threads=threads))
    if runtime == "openvino":
        from e3dpsm.runtime.openvino_session import OpenVINOStepSession

        return OpenVINOStepSession(path, threads=threads)
    from e3dpsm.runtime import StepSession

    return StepSession(path, threads=threads, spin=False)  # PyTorch shares the cores between steps


def run(args: argparse.Namespace) -> int:
    import os
    import tempfile

    # PyTorch and the graph alternate on the same cores: OpenMP workers that busy-wait after
    # each PyTorch step would starve the other runtime (only effective before torch loads).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    # The stateful runtime reads an IR: an .onnx given is converted into this folder first.
    with tempfile.TemporaryDirectory(prefix="e3dpsm-parity-") as workdir:
        runner = make_runner(args.model, args.runtime, args.threads, Path(workdir))  # metadata is checked first
        return _run_checks(args, runner)


def _run_checks(args: argparse.Namespace, runner: Any) -> int:
    from e3dpsm.data.streams import prepared_frames, synthetic_frames
    from e3dpsm.errors import CheckpointError
    from e3dpsm.export.parity import Tolerances, run_parity
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic

    model = load_model_from_args(args)
    graph_variant = runner.meta.config.get("variant")
    if graph_variant != model.config.variant:
        raise CheckpointError(f"{args.model} was exported from variant {graph_variant!r}, the model given is "
                              f"{model.config.variant!r}")
    cfg = model.config
    tolerances = Tolerances(args.pose_atol_mm, args.state_rtol)
    reports = []
    for window_ms in args.window_ms:
        if args.data:
            frames = prepared_frames(args.data, args.steps, args.split)
        else:
            frames = synthetic_frames(args.steps, window_ms, cfg.height, cfg.width, seed=args.seed)
        result = run_parity(model, runner, frames, window_ms, tolerances, args.runtime, progress=True)
        reports.append(result)
        print(f"parity {args.runtime} vs PyTorch, {result.steps} steps at {window_ms:g} ms: "
              f"{'PASSED' if result.passed else 'FAILED'}")
        for line in result.lines():
            print("  " + line)
    report_path = Path(args.report) if args.report else Path(args.model).with_name(f"parity-{args.runtime}.json")
    report = report_header("parity", {k: v for k, v in vars(args).items() if k != "func"})
    report.update(passed=all(r.passed for r in reports), runs=[r.to_dict() for r in reports])
    write_json_atomic(report_path, report)
    print(f"wrote {report_path}")
    return 0 if report["passed"] else 1
