"""`e3dpsm profile`: parameters, MACs per module, memory and side-by-side latency per target
(options only; the body is e3dpsm.profiles.command)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from e3dpsm.cli._common import add_force, add_threads, positive_int
from e3dpsm.errors import ConfigError
from e3dpsm.profiles.outside import DEFAULT_TURNS


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "profile", help="FLOPs, memory and latency per deployment target (report.json, report.md, plots)",
        description="Count parameters and MACs per module (PyTorch and ONNX counters), then measure "
                    "latency, Hz and peak memory of every target side by side in one process with the same "
                    "inputs and thread count. Targets live in profiles/targets.toml; a target this machine "
                    "cannot run is reported unavailable with the reason. Writes OUT/report.json, "
                    "OUT/report.md, OUT/latency.png, OUT/macs_per_module.png (and OUT/step_fp32.onnx, "
                    "OUT/step_fp32_static.onnx when the graphs are exported here). Each CPU target's median is "
                    "reported beside the runtime's own timer (OpenVINO benchmark_app; onnxruntime_perf_test or "
                    "ONNX Runtime's profiler), its Python overhead apart, and the report opens with the fastest "
                    "path on this host.")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--model", help="exported fp32 step graph (STEP.onnx); no PyTorch target then")
    source.add_argument("--variant", help="registered variant with initial weights (paper, released, small, tiny)")
    source.add_argument("--checkpoint", help="trained checkpoint (config inside)")
    p.add_argument("--seed", type=int, default=0, help="weight seed with --variant (default 0)")
    p.add_argument("--targets", default="torch-eager-cpu,ort-cpu-fp32",
                   help="comma-separated target names or 'all' (default torch-eager-cpu,ort-cpu-fp32)")
    p.add_argument("--targets-file", help="TOML with [[target]] entries (default: the packaged targets.toml)")
    p.add_argument("--out", required=True, help="output folder (refused if it exists, unless --force)")
    p.add_argument("--steps", type=positive_int, default=300, help="timed steps per target (default 300)")
    p.add_argument("--warmup", type=int, default=20, help="untimed warm-up steps per target (default 20)")
    add_threads(p, "intra-op threads for every target", "each target's own, 2 in targets.toml")
    p.add_argument("--data", help="prepared folder whose test frames feed the runs (default: built-in synthetic events)")
    p.add_argument("--int8-model", help="INT8 step graph for int8 targets (from e3dpsm quantize)")
    p.add_argument("--fp16-model", help="FP16 step graph for fp16 targets (from e3dpsm quantize)")
    p.add_argument("--static-model",
                   help="static-batch fp32 step graph (e3dpsm export --static-batch) for the *-static targets; "
                        "exported here with --variant / --checkpoint")
    p.add_argument("--outside-seconds", type=float, default=5.0,
                   help="seconds of each CPU target's outside timer (benchmark_app ...; 0: none; default 5)")
    p.add_argument("--outside-turns", type=positive_int, default=DEFAULT_TURNS,
                   help="turns the outside timer and the target's own runner take (its seconds split among "
                        f"them), so both are timed over the same minutes (default {DEFAULT_TURNS})")
    p.add_argument("--edge-models", nargs="+", default=[], metavar="ARTIFACT",
                   help="converted artifacts (.pte, .tflite from e3dpsm convert) for the executorch-* / litert-* "
                        "targets; each goes to the targets of its runtime and precision")
    p.add_argument("--profile-steps", type=int, default=50,
                   help="steps of the separate onnxruntime profiling run per ORT target (0: none; default 50)")
    add_force(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.profiles.command import ProfileRequest, run_profile, summary_lines
    from e3dpsm.profiles.graphs import edge_graphs, given_graphs
    from e3dpsm.profiles.profiler import ProfileSettings
    from e3dpsm.profiles.targets import load_targets, select_targets

    if args.warmup < 0 or args.profile_steps < 0 or args.outside_seconds < 0:
        raise ConfigError("--warmup, --profile-steps and --outside-seconds must be >= 0")
    # Cheap checks first: a bad target name or graph fails before any export or measurement.
    targets = select_targets(load_targets(args.targets_file), args.targets, args.threads)
    graphs = given_graphs(args.model, args.int8_model, args.fp16_model, args.static_model)
    graphs.update(edge_graphs(args.edge_models))
    model = None
    if not args.model:
        import torch

        from e3dpsm.cli._common import load_model_from_args

        torch.set_num_threads(targets[0].threads)
        model = load_model_from_args(args)
    request = ProfileRequest(
        targets=tuple(targets), graphs=graphs, out=Path(args.out), force=args.force, data=args.data,
        settings=ProfileSettings(steps=args.steps, warmup=args.warmup, ort_profile_steps=args.profile_steps,
                                 outside_seconds=args.outside_seconds, outside_turns=args.outside_turns),
        source=args.model or args.checkpoint or f"variant {args.variant}", checkpoint=args.checkpoint,
        config={k: v for k, v in vars(args).items() if k != "func"},
        progress=not args.no_progress and sys.stderr.isatty(),
    )
    report = run_profile(request, model)
    for line in summary_lines(report):
        print(line)
    print(f"wrote {args.out}/report.json and report.md")
    return 0
