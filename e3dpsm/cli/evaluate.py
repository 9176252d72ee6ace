"""`e3dpsm evaluate`: MPJPE, PA-MPJPE, e_smooth (totals, per action, per joint, occlusion-only)
of a checkpoint on a prepared split, with JSON, Markdown and plots."""
from __future__ import annotations

import argparse
import sys
from e3dpsm.cli._common import add_threads, add_force


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "evaluate", help="benchmark a checkpoint on prepared data (MPJPE, PA-MPJPE, e_smooth)",
        description="Run a checkpoint over whole prepared sequences (causal: one stream per sequence, "
        "state never reset; non-causal: training-length windows, stitched) and write OUT/metrics.json, "
        "OUT/metrics.md, plots and the predictions. Totals are unweighted means of per-action means.",
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint written by e3dpsm train")
    p.add_argument("--data", required=True, help="prepared folder")
    p.add_argument("--out", required=True, help="report folder to create")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--causal", dest="causal", action="store_true", default=True, help="streaming (default)")
    mode.add_argument("--non-causal", dest="causal", action="store_false", help="bidirectional S5 windows")
    p.add_argument("--split", default="test", help="split to evaluate, or 'all' (default test)")
    p.add_argument("--window-ms", type=float, help="expected window length of the data (checked; the model "
                   "runs at the data's window, which may differ from its training window)")
    add_threads(p, "torch CPU threads")
    add_force(p)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import torch

    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.evaluation.evaluate import evaluate_checkpoint, write_report
    from e3dpsm.utils.env import report_header

    if args.threads:
        torch.set_num_threads(args.threads)
    from e3dpsm.utils.io import refuse_existing_output

    refuse_existing_output(args.out, args.force)  # fail before the long run, not after
    data = PreparedData.open(args.data)
    results, preds = evaluate_checkpoint(args.checkpoint, data, args.split, args.causal, args.window_ms,
                                         progress=not args.no_progress and sys.stderr.isatty())
    header = report_header("evaluate", {"checkpoint": str(args.checkpoint), "data": str(args.data),
                                        "split": args.split, "causal": args.causal, "window_ms": data.window_ms})
    write_report(args.out, header, results, preds, data.window_ms, force=args.force)
    t = results["totals"]
    print(f"{results['mode']}: MPJPE {t['mpjpe']:.2f} mm, PA-MPJPE {t['pa_mpjpe']:.2f} mm, "
          f"e_smooth {t['e_smooth']:.2f} mm over {results['frames']} frames -> {args.out}")
    return 0
