"""The ablation benchmark: one training run per ablation, each evaluated both ways."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from e3dpsm.data.prepared import PreparedData
from e3dpsm.evaluation.core import METRICS
from e3dpsm.evaluation.pipeline import evaluate_checkpoint
from e3dpsm.evaluation.tables import markdown_table
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic


def run_ablations(args: argparse.Namespace, out: Path, test_data: PreparedData, progress: bool) -> dict[str, Any]:
    from e3dpsm.training.ablations import ablation_overrides
    from e3dpsm.training.trainer import CHECKPOINT_NAME, RunOptions, TrainArgs, train

    rows: dict[str, Any] = {}
    for name in args.ablations:
        run_dir = out / "runs" / name
        train_args = TrainArgs(variant=args.variant, steps=args.steps, seq_len=args.seq_len,
                               batch_size=args.batch_size, seed=args.seed, split=args.split,
                               overrides=ablation_overrides(name))
        # A finished run is reused, so an interrupted benchmark resumes where it stopped.
        finished = (run_dir / "report.json").is_file() and not args.force
        if not finished:
            resume = (run_dir / CHECKPOINT_NAME).is_file() and not args.force
            train(train_args, args.data, run_dir, RunOptions(resume=resume, force=args.force, progress=progress))
        row: dict[str, Any] = {"overrides": {k: list(v) if isinstance(v, tuple) else v
                                             for k, v in ablation_overrides(name).items()}}
        for key, causal in (("causal", True), ("non_causal", False)):
            results, _ = evaluate_checkpoint(run_dir / CHECKPOINT_NAME, test_data, args.test_split, causal)
            row[key] = {**results["totals"], "error_over_time": results["error_over_time"]["mpjpe"]}
        rows[name] = row
    table = {**report_header("ablation", {k: v for k, v in vars(args).items() if k != "func"}), "rows": rows}
    write_json_atomic(out / "ablation.json", table)
    flat = {f"{name} ({mode.replace('_', '-')})": row[mode] for name, row in rows.items()
            for mode in ("causal", "non_causal")}
    drift = {name: {f"{(i + 0.5) / 10:.2f}": v for i, v in enumerate(row["causal"]["error_over_time"])}
             for name, row in rows.items()}
    md = (f"# Ablations ({args.variant}, {args.steps} steps each)\n\nmm; totals = unweighted mean of per-action means.\n\n"
          + markdown_table(flat, METRICS, "ablation")
          + "\n## Causal MPJPE along the sequences (tenths of each sequence)\n\n"
          + markdown_table(drift, list(next(iter(drift.values()), {})), "ablation"))
    write_text_atomic(out / "ablation.md", md)
    return table
