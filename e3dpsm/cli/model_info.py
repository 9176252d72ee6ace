"""`e3dpsm model-info`: parameters and MACs per pose update, per module, beside the paper's table."""
from __future__ import annotations

import argparse

from e3dpsm.cli._common import add_model_source, add_threads


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "model-info", help="parameters and MACs per module, next to the paper's efficiency table",
        description="Count parameters and MACs of one pose update per module (CNN, deformable attention, "
                    "SSM, query decoder, heads, fusion) with the PyTorch counter and print them beside the "
                    "paper's efficiency table, stating the counting convention compared.")
    add_model_source(p)
    p.add_argument("--json", help="also write the counts as a JSON report to this path")
    add_threads(p, "torch threads")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import torch

    from e3dpsm.cli._common import load_model_from_args
    from e3dpsm.profiles.command import model_info_report
    from e3dpsm.profiles.report import model_info_markdown
    from e3dpsm.utils.io import write_json_atomic

    if args.threads:
        torch.set_num_threads(args.threads)
    report = model_info_report(load_model_from_args(args), {k: v for k, v in vars(args).items() if k != "func"})
    print(model_info_markdown(report))
    if args.json:
        write_json_atomic(args.json, report)
        print(f"wrote {args.json}")
    return 0
