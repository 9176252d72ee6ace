"""`e3dpsm pipeline`: the whole flow on the embedded default, resumable."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from e3dpsm.cli._common import add_threads, positive_float, positive_int


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "pipeline", help="run the whole flow on synthetic data (10-30 minutes on two cores)",
        description="synth -> prepare -> train -> evaluate -> export -> parity -> quantize -> validate -> "
                    "golden -> clip -> profile -> OUT/report/index.md, each stage in its own process. "
                    "Finished stages are skipped on a rerun.")
    p.add_argument("--out", default="runs/pipeline", help="output folder (default runs/pipeline)")
    p.add_argument("--variant", choices=("tiny", "small"), default="small")
    p.add_argument("--checkpoint", type=Path, help="use this trained or imported checkpoint (e3dpsm import) instead "
                                                     "of training; data are prepared at its resolution")
    steps = p.add_mutually_exclusive_group()
    steps.add_argument("--train-steps", type=positive_int,
                       help="training steps (default 120: the same model on every host and rerun)")
    steps.add_argument("--minutes", type=positive_float,
                       help="instead of a step count: a rough total budget, about half of it training, "
                            "the steps fitted to it by a short timing probe (the model then depends on "
                            "the host's speed)")
    p.add_argument("--seed", type=int, default=0)
    add_threads(p)
    p.add_argument("--only", nargs="+", metavar="STAGE", help="rerun only these stages (others untouched)")
    p.add_argument("--with", dest="with_stages", nargs="+", metavar="STAGE", default=[],
                   help="also run these optional stages (off by default): prune, executorch, litert, edge-check; "
                        "edge names the last three (fp32 .pte and .tflite, their golden checks, profiled)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.pipeline.runner import run_pipeline
    from e3dpsm.pipeline.stages import PipelineConfig

    cfg = PipelineConfig(out=Path(args.out), variant=args.variant, train_steps=args.train_steps,
                         minutes=args.minutes, seed=args.seed,
                         threads=args.threads or os.cpu_count() or 1, checkpoint=args.checkpoint,
                         with_stages=tuple(args.with_stages))
    run_pipeline(cfg, only=args.only)
    print(f"report: {cfg.out / 'report' / 'index.md'}")
    return 0
