"""`e3dpsm synth`: generate a synthetic egocentric event data set."""
from __future__ import annotations

import argparse
import json
import os
from e3dpsm.cli._common import add_force


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "synth", help="generate a synthetic egocentric event data set",
        description="Render an articulated body acting out the ten EE3D action classes, seen by "
        "the head-mounted fisheye, and simulate its events; writes the synthetic layout, "
        "DIR/report.json with realism figures, and optional previews.")
    p.add_argument("--out", required=True, help="output data set folder (must not exist unless --force)")
    p.add_argument("--sequences", type=int, default=6, help="number of sequences (default 6)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of each sequence (default 10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pose-hz", type=int, default=50, help="ground-truth pose rate (default 50)")
    p.add_argument("--render-hz", type=int, default=250,
                   help="internal render rate, a multiple of the pose rate (default 250)")
    p.add_argument("--render-scale", type=float, default=0.5,
                   help="render resolution relative to the 640x480 sensor: 1, 0.5 or 0.25 (default 0.5)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="parallel processes (default: up to 2)")
    p.add_argument("--preview", action="store_true", help="write preview PNGs into DIR/preview/")
    add_force(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.data.synth.dataset import write_dataset
    from e3dpsm.data.synth.generator import SynthConfig

    config = SynthConfig(seed=args.seed, seconds=args.seconds, pose_hz=args.pose_hz,
                         render_hz=args.render_hz, render_scale=args.render_scale)
    report = write_dataset(args.out, config, args.sequences, workers=args.workers,
                           preview=args.preview, force=args.force, progress=not args.no_progress)
    r = report["realism"]
    print(json.dumps({
        "out": args.out, "events_per_20ms": r["events_per_20ms"], "background_share": round(r["background_share"], 3),
        "joints_in_image": round(r["joints_in_image"], 3), "wall_s": round(report["timing"]["wall_s"], 1),
    }))
    return 0
