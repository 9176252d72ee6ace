"""`e3dpsm profile`: parameters, MACs per module, memory and side-by-side latency per target."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from e3dpsm.cli._common import positive_int
from e3dpsm.errors import ConfigError, DataError

log = logging.getLogger(__name__)
GRAPH_NAME = "step_fp32.onnx"


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "profile", help="FLOPs, memory and latency per deployment target (report.json, report.md, plots)",
        description="Count parameters and MACs per module (PyTorch and ONNX counters), then measure "
                    "latency, Hz and peak memory of every target side by side in one process with the same "
                    "inputs and thread count. Targets live in profiles/targets.toml; a target this machine "
                    "cannot run is reported unavailable with the reason. Writes OUT/report.json, "
                    "OUT/report.md, OUT/latency.png, OUT/macs_per_module.png (and OUT/step_fp32.onnx when "
                    "the graph is exported here).")
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
    p.add_argument("--threads", type=positive_int, default=None,
                   help="intra-op threads for every target (default: each target's own, 2 in targets.toml)")
    p.add_argument("--data", help="prepared folder whose test frames feed the runs (default: built-in synthetic events)")
    p.add_argument("--int8-model", help="INT8 step graph for int8 targets (from e3dpsm quantize)")
    p.add_argument("--fp16-model", help="FP16 step graph for fp16 targets (from e3dpsm quantize)")
    p.add_argument("--edge-models", nargs="+", default=[], metavar="ARTIFACT",
                   help="converted artifacts (.pte, .tflite from e3dpsm convert) for the executorch-* / litert-* "
                        "targets; each goes to the targets of its runtime and precision")
    p.add_argument("--profile-steps", type=int, default=50,
                   help="steps of the separate onnxruntime profiling run per ORT target (0: none; default 50)")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def _existing(path: str | None, flag: str) -> Path | None:
    if path is None:
        return None
    if not Path(path).is_file():
        raise DataError(f"{flag} {path} does not exist")
    return Path(path)


def edge_graphs(paths: list[str]) -> dict[str, Path]:
    """{"<runtime>/<precision>": path} of the --edge-models artifacts whose runtime is installed
    (the targets of a missing one are reported unavailable with the install line)."""
    from e3dpsm.profiles.targets import EDGE_RUNTIMES
    from e3dpsm.runtime.stepping import artifact_runtime, open_stepper
    from e3dpsm.utils.extras import missing_reason

    found: dict[str, Path] = {}
    for path in paths:
        runtime = artifact_runtime(_existing(path, "--edge-models"))
        if runtime not in EDGE_RUNTIMES:
            raise ConfigError(f"--edge-models takes .pte and .tflite artifacts; {path} runs on {runtime}")
        if missing_reason(EDGE_RUNTIMES[runtime][0]) is None:
            found[f"{runtime}/{open_stepper(path).artifact['precision']}"] = Path(path)
    return found


def run(args: argparse.Namespace) -> int:
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.profiles.flops_onnx import load_graph
    from e3dpsm.profiles.inputs import prepared_frames, moving_edge_frames
    from e3dpsm.profiles.profiler import ProfileSettings, profile_targets
    from e3dpsm.profiles.report import plot_latency, plot_macs, profile_markdown
    from e3dpsm.profiles.targets import load_targets, select_targets
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, write_json_atomic, write_text_atomic

    if args.warmup < 0 or args.profile_steps < 0:
        raise ConfigError("--warmup and --profile-steps must be >= 0")
    # Cheap checks first: a bad target name or graph fails before any export or measurement.
    targets = select_targets(load_targets(args.targets_file), args.targets, args.threads)
    graphs: dict[str, Path | None] = {"fp32": _existing(args.model, "--model"),
                                      "int8": _existing(args.int8_model, "--int8-model"),
                                      "fp16": _existing(args.fp16_model, "--fp16-model")}
    for path in graphs.values():
        if path is not None:
            GraphMetadata.from_onnx(load_graph(path), source=str(path))  # MetadataError if it has none
    graphs.update(edge_graphs(args.edge_models))

    model = None
    if not args.model:
        import torch

        from e3dpsm.cli._common import load_model_from_args

        torch.set_num_threads(targets[0].threads)
        model = load_model_from_args(args)

    with atomic_dir(args.out, force=args.force) as tmp:
        if model is not None:
            from e3dpsm.export import export_step

            graphs["fp32"] = export_step(model, tmp / GRAPH_NAME)
        meta = GraphMetadata.from_onnx(load_graph(graphs["fp32"]), source=str(graphs["fp32"]))
        height, width = meta.frame_hw
        frames_needed = args.steps + args.warmup
        frames = (prepared_frames(args.data, frames_needed, height, width) if args.data
                  else moving_edge_frames(min(frames_needed, 400), height, width, meta.train_window_ms))
        settings = ProfileSettings(steps=args.steps, warmup=args.warmup, ort_profile_steps=args.profile_steps)
        log.info("profiling %d target(s) on %s", len(targets), frames.source)
        body, times = profile_targets(targets, graphs, model, frames, settings, checkpoint=args.checkpoint,
                                      progress=not args.no_progress and sys.stderr.isatty())

        variant = meta.config.get("variant", "?")
        report = report_header("profile", {k: v for k, v in vars(args).items() if k != "func"})
        report.update(
            model={"variant": variant, "source": args.model or args.checkpoint or f"variant {args.variant}",
                   "params": body["targets"][0]["params"] if body["targets"] else None,
                   "graph": GRAPH_NAME if model is not None else str(args.model)},
            inputs={"source": frames.source, "window_ms": frames.window_ms, "frames": int(len(frames.lnes)),
                    "steps": settings.steps, "warmup": settings.warmup, "chunk": settings.chunk,
                    "threads": targets[0].threads},
            **body,
        )
        write_json_atomic(tmp / "report.json", report)
        write_text_atomic(tmp / "report.md", profile_markdown(report))
        if times:
            plot_latency({name: t * 1e3 for name, t in times.items()}, tmp / "latency.png")
        plot_macs(report["counting"]["pytorch"] or report["counting"]["onnx"], tmp / "macs_per_module.png")

    for entry in report["targets"]:
        if entry["available"]:
            lat = entry["latency_ms"]
            print(f"{entry['name']:>20}: p50 {lat['p50']:.2f} ms, p90 {lat['p90']:.2f}, p99 {lat['p99']:.2f} "
                  f"-> {entry['hz']:.1f} Hz")
        else:
            print(f"{entry['name']:>20}: unavailable ({entry['reason']})")
    for name, ratio in report["ratios"].items():
        print(f"  {name}: {ratio:.2f}x")
    print(f"wrote {args.out}/report.json and report.md")
    return 0
