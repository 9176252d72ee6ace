"""`e3dpsm ablation`: train the paper's ablations on the same data and tabulate them, each
evaluated causal and non-causal (one JSON + one Markdown table)."""
from __future__ import annotations

import argparse
import sys

from e3dpsm.training.ablations import ABLATIONS
from e3dpsm.cli._common import add_threads, add_force


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "ablation", help="train and evaluate the paper's ablations (fusion, SSM) on the same data",
        description="Train one run per ablation (full, naive fusion, direct pose only, static fusion, "
        "no SSM) with identical settings, evaluate each causal and non-causal on --test-data, and "
        "write OUT/ablation.json and OUT/ablation.md. Runs live in OUT/runs/<name>/.",
    )
    p.add_argument("--data", required=True, help="prepared training folder")
    p.add_argument("--test-data", required=True, help="prepared held-out folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--variant", default="small")
    p.add_argument("--ablations", nargs="+", default=list(ABLATIONS), choices=list(ABLATIONS))
    p.add_argument("--steps", type=int, default=300, help="training steps per ablation (default 300)")
    p.add_argument("--seq-len", type=int, default=40)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--split", default="train", help="training split, or 'all'")
    p.add_argument("--test-split", default="all", help="held-out split, or 'all' (default all)")
    p.add_argument("--seed", type=int, default=0)
    add_threads(p)
    add_force(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import torch

    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.evaluation.ablation import run_ablations

    if args.threads:
        torch.set_num_threads(args.threads)
    test_data = PreparedData.open(args.test_data)
    table = run_ablations(args, Path(args.out), test_data, progress=sys.stderr.isatty())
    for name, row in table["rows"].items():
        print(f"{name:14s} causal MPJPE {row['causal']['mpjpe']:.1f}  non-causal {row['non_causal']['mpjpe']:.1f}  "
              f"e_smooth {row['causal']['e_smooth']:.2f}")
    print(f"-> {Path(args.out) / 'ablation.md'}")
    return 0
