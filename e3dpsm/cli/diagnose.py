"""`e3dpsm diagnose`: which module group makes a compressed graph depart from its reference,
and whether the error grows as the states carry it (torch-free)."""
from __future__ import annotations

import argparse
from pathlib import Path

from e3dpsm.cli._common import add_force, add_threads, positive_float, positive_int


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("diagnose", help="per-group, per-state divergence of a compressed graph over a rollout",
                       description="Runs the reference (fp32) and the compressed graph side by side over prepared "
                                   "frames, each carrying its own states, with intermediate tensors exposed and "
                                   "matched by name across Q/DQ pairs. Ranks module groups by their quantisation "
                                   "noise (or, without Q/DQ pairs, by the error they add) and reports every "
                                   "state's error at steps 1, 10, 100 and N.")
    p.add_argument("--reference", required=True, help="fp32 step graph (the graph the compressed one came from)")
    p.add_argument("--model", required=True, help="compressed step graph (INT8 QDQ, FP16, dynamic INT8)")
    p.add_argument("--data", required=True, help="prepared folder for the frames")
    p.add_argument("--split", default=None, help="split of --data (default: all sequences)")
    p.add_argument("--steps", type=positive_int, default=200)
    p.add_argument("--window-ms", type=positive_float, default=None, help="default: the graph's training window")
    add_threads(p)
    p.add_argument("--out", required=True, help="folder for report.json, report.md and diagnose.png")
    add_force(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.data.streams import prepared_frames
    from e3dpsm.golden.diagnose import diagnose, markdown, plot_diagnosis
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.runtime import StepSession
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, refuse_existing_output, write_json_atomic

    out = refuse_existing_output(args.out, args.force)  # before the rollout, not after it
    meta: GraphMetadata = StepSession(args.reference, threads=1).meta  # checks both files before the rollout
    StepSession(args.model, threads=1)
    window_ms = args.window_ms or meta.train_window_ms
    frames = prepared_frames(args.data, args.steps, args.split)
    result = diagnose(args.reference, args.model, frames, window_ms, threads=args.threads, progress=True)
    title = f"diagnose {Path(args.model).name} against {Path(args.reference).name}"
    report = report_header("diagnose", {k: v for k, v in vars(args).items() if k != "func"})
    report.update({k: v for k, v in result.items() if not k.startswith("_")})
    with atomic_dir(out, force=args.force) as tmp:
        plot_diagnosis(result, tmp / "diagnose.png")
        (tmp / "report.md").write_text(markdown(result, title), encoding="utf-8")
        write_json_atomic(tmp / "report.json", report)
    print(f"{title}: {result['steps']} steps, culprits ranked by {result['ranked_by'].replace('_', ' ')}")
    for rank, group in enumerate(result["groups"][:5], 1):
        at = group["error_at_step"]
        noise = f"QDQ noise {group['qdq_noise']:.2e}, " if group.get("qdq_noise") is not None else ""
        print(f"  {rank}. {group['name']:14s} {noise}adds {group['mean_added_error']:.2e}, output error "
              + ", ".join(f"{v:.1e} @{k}" for k, v in at.items()) + (" (grows)" if group["grows"] else ""))
    growing = [s["name"] for s in result["states"] if s["grows"]]
    print(f"  states whose error grows: {', '.join(growing) if growing else 'none'}; wrote {out / 'report.md'}")
    return 0
