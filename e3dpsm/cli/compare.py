"""`e3dpsm compare BASE NEW`: differences between two runs' reports; exit 1 on a regression."""
from __future__ import annotations

import argparse


def percent(text: str) -> float:
    try:
        value = float(text.strip().rstrip("%"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a percentage such as 10% or 0.5, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative percentage, got {text}")
    return value


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "compare", help="compare two reports (profile, validate, pipeline) and fail on a regression",
        description="Read the report.json of `profile`, `validate` or `pipeline` (or a pipeline output "
                    "folder) for a base and a new run, print a table of every figure (p50 latency and graph "
                    "size per target, MPJPE per variant) and exit 1 if one grew beyond its limit.")
    p.add_argument("base", help="base report.json (or pipeline folder)")
    p.add_argument("new", help="new report.json (or pipeline folder)")
    p.add_argument("--max-latency-regression", type=percent, default=10.0, metavar="PCT",
                   help="allowed p50 latency growth (default 10%%)")
    p.add_argument("--max-mpjpe-regression", type=percent, default=0.5, metavar="PCT",
                   help="allowed MPJPE growth (default 0.5%%)")
    p.add_argument("--max-size-growth", type=percent, default=None, metavar="PCT",
                   help="allowed graph size growth (default: not checked)")
    p.add_argument("--json", help="also write the comparison as JSON to this path")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from e3dpsm.pipeline.compare import compare, table
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic

    limits = {"latency": args.max_latency_regression, "mpjpe": args.max_mpjpe_regression, "size": args.max_size_growth}
    changes = compare(args.base, args.new, limits)
    print(table(changes))
    regressed = [c.name for c in changes if c.regressed]
    if args.json:
        report = report_header("compare", {k: v for k, v in vars(args).items() if k != "func"})
        report.update(changes=[c.to_dict() for c in changes], regressions=regressed, passed=not regressed)
        write_json_atomic(args.json, report)
    print(f"{len(regressed)} regression(s)" + (f": {', '.join(regressed)}" if regressed else ""))
    return 1 if regressed else 0
