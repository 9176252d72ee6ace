"""`e3dpsm` command line: one sub-command per stage of the flow.

Each sub-command lives in its own module `e3dpsm.cli.<name>` exposing
`register(subparsers) -> argparse.ArgumentParser` whose parser sets `func(args) -> int`.
Modules import heavy libraries (torch, onnxruntime) inside `func`, so `--help` stays fast
and `e3dpsm run` never imports torch.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys
from typing import NoReturn, Sequence

from e3dpsm.errors import E3DPSMError

# Order shown in --help: the order of the flow.
COMMANDS: tuple[str, ...] = (
    "pipeline", "synth", "prepare", "model_info", "train", "import_weights", "evaluate", "distill", "ablation", "export",
    "parity", "quantize", "prune", "validate", "convert", "golden", "diagnose", "profile", "compare", "run", "serve",
)

# The guide page of each command (relative to the repository root), shown at the end of its
# --help; tests/test_docs.py checks that every command has one and that the page exists.
DOCS: dict[str, str] = {
    "pipeline": "docs/pipeline.md",
    "synth": "docs/data.md",
    "prepare": "docs/data.md",
    "model_info": "docs/model.md",
    "train": "docs/training.md",
    "import_weights": "docs/model.md",
    "evaluate": "docs/training.md",
    "distill": "docs/compress.md",
    "ablation": "docs/training.md",
    "export": "docs/export-and-parity.md",
    "parity": "docs/export-and-parity.md",
    "quantize": "docs/quantize.md",
    "prune": "docs/compress.md",
    "validate": "docs/validate-and-profile.md",
    "convert": "docs/runtimes.md",
    "golden": "docs/golden-and-diagnose.md",
    "diagnose": "docs/golden-and-diagnose.md",
    "profile": "docs/validate-and-profile.md",
    "compare": "docs/validate-and-profile.md",
    "run": "docs/runtimes.md",
    "serve": "docs/serve.md",
}


def _set_guide(parser: argparse.ArgumentParser, page: str) -> None:
    """End the command's --help (and its actions', e.g. `golden record`) with its guide page."""
    for target in [parser] + [child for action in parser._actions
                              if isinstance(action, argparse._SubParsersAction)
                              for child in action.choices.values()]:
        target.epilog = f"{target.epilog} Guide: {page}" if target.epilog else f"Guide: {page}"


class OneLineParser(argparse.ArgumentParser):
    """argparse, with a refused argument on one line like every other bad input (`e3dpsm CMD:
    error: ...`, exit 2) instead of the usage block first."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {' '.join(message.split())}\n")
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="e3dpsm",
        description="Train, export, quantise, verify and profile the E-3DPSM event-based "
        "egocentric 3D pose model.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging and tracebacks")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    for name in COMMANDS:
        module_name = f"e3dpsm.cli.{name}"
        if importlib.util.find_spec(module_name) is None:
            continue
        command = importlib.import_module(module_name).register(sub)
        if name in DOCS and isinstance(command, argparse.ArgumentParser):
            _set_guide(command, DOCS[name])
    return parser


def error_line(command: str, exc: BaseException) -> str:
    """`e3dpsm CMD: error: MESSAGE` on one line, always: a message may quote a library's own
    multi-line text (h5py, onnxruntime, torch)."""
    return f"e3dpsm {command}: error: " + " ".join(line.strip() for line in str(exc).splitlines() if line.strip())


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s", stream=sys.stderr
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except E3DPSMError as exc:
        if args.verbose:
            raise
        print(error_line(args.command, exc), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"e3dpsm {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
