"""`e3dpsm prepare`: raw sequences (synthetic or EE3D layout) -> prepared LNES cache."""
from __future__ import annotations

import argparse
import sys
from e3dpsm.cli._common import add_force


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "prepare",
        help="cut event streams into T-ms windows and cache LNES frames with aligned ground truth",
        description="Cut every sequence of a data set (synthetic layout or EE3D-R/W layout) into "
        "consecutive T-ms windows, build one LNES frame per window, take the ground-truth pose at "
        "each window's end, and write the prepared folder that train, evaluate, quantize and "
        "validate read. The output is built under a temporary name and renamed when complete.",
    )
    parser.add_argument("--data", required=True, help="data set root (sequence folders + train/val/test.txt)")
    parser.add_argument("--out", required=True, help="prepared folder to create")
    parser.add_argument("--window-ms", type=float, default=20.0, help="window length T in ms (default 20)")
    parser.add_argument("--height", type=int, default=192, help="LNES frame height (default 192)")
    parser.add_argument("--width", type=int, default=256, help="LNES frame width (default 256)")
    parser.add_argument("--workers", type=int, default=1,
                        help="sequences prepared at once, one per process (default 1; the same frames and poses either way)")
    add_force(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from e3dpsm.data.prepare import prepare_dataset

    report = prepare_dataset(
        args.data, args.out, args.window_ms, args.height, args.width,
        force=args.force, progress=not args.no_progress and sys.stderr.isatty(), workers=args.workers,
    )
    per_window = report["events_per_window"]
    print(
        f"prepared {len(report['sequences'])} sequences ({report['source']}), {report['frames']} windows of "
        f"{args.window_ms:g} ms, {per_window['mean']:.0f} events/window on average, "
        f"{report['empty_windows']} empty, in {report['seconds']:.1f} s -> {args.out}"
    )
    return 0
