"""`e3dpsm import --released CKPT --out DIR`: a checkpoint of the released research code
as this project's checkpoint (variant `released`), with a report of the key mapping."""
from __future__ import annotations

import argparse
import logging
from e3dpsm.cli._common import add_force

log = logging.getLogger(__name__)
CHECKPOINT_NAME = "checkpoint.pt"


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "import", help="import a checkpoint of the released E-3DPSM code",
        description="Read a PyTorch Lightning checkpoint (or a plain state_dict) of the released "
                    "E-3DPSM code with weights_only=True and write DIR/checkpoint.pt (variant "
                    "'released', loadable by every other command) and DIR/import.json (key "
                    "mapping, derived keys, checks). Nothing is written on bad input.",
    )
    p.add_argument("--released", required=True, metavar="CKPT", help="released checkpoint (.ckpt or state_dict .pt)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (refused if it exists, unless --force)")
    add_force(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import e3dpsm
    from e3dpsm.checkpoint import load_checkpoint, save_checkpoint
    from e3dpsm.importers import import_released, read_released_state_dict
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, write_json_atomic

    released, kind = read_released_state_dict(args.released)
    model = e3dpsm.create_model("released").eval()
    result = import_released(released, model)
    model.load_state_dict(result.state_dict, strict=True)
    for line in result.warnings:
        log.warning("warning: %s", line)
    with atomic_dir(args.out, force=args.force) as tmp:
        save_checkpoint(tmp / CHECKPOINT_NAME, model, imported_from={"path": str(args.released), "kind": kind})
        load_checkpoint(tmp / CHECKPOINT_NAME, variant="released")  # the written file rebuilds its model
        report = report_header("import", {**vars(args), "func": None})
        report.update(
            source={"path": str(args.released), "kind": kind},
            variant="released",
            params=model.num_parameters(),
            checks=result.checks,
            warnings=result.warnings,
            mapping=result.mapping,
        )
        write_json_atomic(tmp / "import.json", report)
    checks = result.checks
    print(f"wrote {args.out}/{CHECKPOINT_NAME}: {checks['released_keys_used']} released tensors mapped "
          f"({checks['network_parameters']:,} network + {checks['kalman_parameters']} Kalman parameters), "
          f"Kalman F/B/H identity checked, {len(checks['derived'])} key derived")
    return 0
