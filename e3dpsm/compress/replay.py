"""Rebuild a pruned model from its teacher and a prune run's cuts, on another machine.

`e3dpsm prune --steps 0` plans the cuts where the latency model belongs (the target CPU) and
recovers nothing, so every round's keep lists were read from the teacher's own weights
(compress.importance.keep_lists: a magnitude criterion). Replaying the same cuts on the same
teacher therefore picks the same channels, and the student comes out bit for bit the prune
run's: the recovery can then run elsewhere (a GPU) from the teacher and the report alone.
A run that recovered between rounds cannot be replayed: round k+1's keep lists read weights
that round k's distillation changed.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

from e3dpsm.errors import ConfigError
from e3dpsm.models import E3DPSM

Cuts = Mapping[str, Any]  # one round's cuts, as the prune report records them


def replayable_cuts(report: Mapping[str, Any], source: str = "the report") -> tuple[list[Cuts], int]:
    """(each chosen round's cuts, the chosen model's MACs) from a prune run's report.json."""
    try:
        steps = int(report["config"]["steps"])
        best = int(report["best"])
        rounds = report["rounds"]
        cuts = [rounds[k]["cuts"] for k in range(1, best + 1)]
        macs = int(rounds[best]["macs"])
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise ConfigError(f"{source} is not an `e3dpsm prune` report.json (missing {exc})") from None
    if steps != 0:
        raise ConfigError(f"{source}: a prune run with --steps {steps}; its cuts replay exactly only from a run with "
                          "--steps 0 (recovery between rounds changes the weights the next round's cuts were read from)")
    return cuts, macs


def replay_cuts(teacher: E3DPSM, rounds: Sequence[Cuts], expected_macs: int | None = None) -> E3DPSM:
    """The teacher cut round by round (each round cuts the previous round's model, as the
    prune run did); `expected_macs`, when given, must be the result's MACs."""
    from e3dpsm.compress.importance import keep_lists
    from e3dpsm.compress.plan import total_macs
    from e3dpsm.compress.surgery import prune_model
    from e3dpsm.compress.units import prunable_units

    student = teacher
    for index, cuts in enumerate(rounds, start=1):
        try:
            student = prune_model(student, keep_lists(student, prunable_units(student.config), cuts))
        except (KeyError, ValueError, RuntimeError) as exc:  # unknown unit, bad width (torch.topk)
            raise ConfigError(f"round {index}'s cuts do not fit this model ({exc}); was the report made by pruning "
                              "this checkpoint?") from None
    macs = total_macs(student)
    if expected_macs is not None and macs != expected_macs:
        raise ConfigError(f"the replayed model has {macs:,} MACs, the report's {expected_macs:,}: the report was not "
                          "made by pruning this checkpoint")
    return student.eval()


def replay_prune_report(checkpoint: str, report_path: str, out: str, force: bool = False) -> dict[str, Any]:
    """`e3dpsm prune --replay`: the student of `report_path` rebuilt from `checkpoint`, written
    as OUT/checkpoint.pt (no recovery: `step` 0, the cuts and their source in `prune`)."""
    import json
    from pathlib import Path

    from e3dpsm.checkpoint import load_checkpoint, save_checkpoint
    from e3dpsm.compress.plan import total_macs
    from e3dpsm.utils.io import atomic_dir, refuse_existing_output

    refuse_existing_output(out, force)  # before the teacher loads, not after
    try:
        report = json.loads(Path(report_path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot read the prune report {report_path}: {exc}") from None
    cuts, macs = replayable_cuts(report, str(report_path))
    teacher, payload = load_checkpoint(checkpoint)
    student = replay_cuts(teacher, cuts, macs)
    with atomic_dir(out, force=force) as tmp:
        save_checkpoint(tmp / "checkpoint.pt", student, step=0, window_ms=payload.get("window_ms"), prune={
            "round": len(cuts), "source": str(checkpoint), "replayed_from": str(report_path),
            "config": report.get("config"), "cuts": cuts})
    return {"rounds": len(cuts), "params": student.num_parameters(), "macs": macs,
            "macs_fraction": macs / total_macs(teacher), "checkpoint": str(Path(out) / "checkpoint.pt")}
