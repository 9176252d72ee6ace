"""INT8 edge artifacts checked like `e3dpsm quantize`'s graphs: the pieces around a converter.

An fp32 ONNX graph of the same checkpoint is the reference: its continuous rollout over the
calibration split gives every calibration frame the states a running stream carries into it
(quantize/calibration.py), and its poses on the held-out split are what the INT8 artifact is
budgeted against (budget.py through quantize/holdout.py: MPJPE and PA-MPJPE within +1%,
jitter within +5%, the bootstrap's upper bound counting), on frames calibration never saw.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from e3dpsm.budget import BudgetCheck, TaskBudget
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.models import E3DPSM
from e3dpsm.quantize.calibration import CalibrationSet, record_calibration_set
from e3dpsm.quantize.holdout import HeldOut, Judgement, check_stepper, held_out, open_stepper
from e3dpsm.quantize.place import Placement, greedy_groups
from e3dpsm.runtime.stepping import Stepper

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EdgeInt8Options:
    frames: int = 200                 # calibration frames (quantize's default)
    split: str = "train"              # where they come from
    holdout_split: str = "test"       # the budget's frames, never calibrated on
    holdout_frames: int = 0           # per held-out sequence (0: all)
    search_split: str = "val"         # where the return-to-float search judges its trials
    search_frames: int = 0            # per search sequence (0: all)
    search_rounds: int = 4            # blocks the search may return to float (0: no search)
    narrow_trials: int | None = None  # narrowing trials at most (None: every unit; 0: no narrowing)
    threads: int | None = None
    budget: TaskBudget = field(default_factory=TaskBudget)

    def __post_init__(self) -> None:
        if self.split == self.holdout_split:
            raise ConfigError(f"the held-out split must differ from the calibration split ({self.split!r})")
        if self.search_rounds and self.search_split in (self.split, self.holdout_split):
            raise ConfigError(f"the search split ({self.search_split!r}) must differ from the calibration and "
                              "held-out splits: the budget must hold on frames the search never saw")
        for name in ("holdout_frames", "search_frames", "search_rounds", "narrow_trials"):
            if (getattr(self, name) or 0) < 0:
                raise ConfigError(f"--{name.replace('_', '-')} must be 0 or positive, got {getattr(self, name)}")

    def to_dict(self) -> dict[str, Any]:
        return {**{k: v for k, v in vars(self).items() if k != "budget"}, "budget": self.budget.to_dict()}


def open_data(path: str | os.PathLike, model: E3DPSM, options: EdgeInt8Options,
              weights_only: bool = False) -> PreparedData:
    """The prepared folder, checked against the model's window and frame size and for the
    splits the conversion reads (weight-only: the held-out split alone; static: calibration,
    held-out and search), before anything is converted (DataError / ConfigError: one line, exit 2)."""
    data = PreparedData.open(path)
    cfg = model.config
    data.check_compatible(window_ms=cfg.train_window_ms, height=cfg.height, width=cfg.width)
    data.split(options.holdout_split)
    if weights_only:
        return data
    data.split(options.split)
    if options.search_rounds:
        try:
            data.split(options.search_split)
        except DataError as error:
            raise DataError(f"{error}: the return-to-float search judges its trials there "
                            "(--search-rounds 0 converts without it)") from None
    return data


def fp32_reference(model: E3DPSM, work: Path) -> Path:
    """The checkpoint's fp32 ONNX step graph: the calibration's rollout and the budget's reference."""
    from e3dpsm.export import export_step

    return export_step(model, work / "fp32.onnx")


def calibration_set(fp32_onnx: Path, data: PreparedData, options: EdgeInt8Options) -> CalibrationSet:
    return record_calibration_set(fp32_onnx, data.split(options.split), options.frames, data.window_ms,
                                  threads=options.threads)


def held_out_set(fp32_onnx: Path, data: PreparedData, options: EdgeInt8Options) -> HeldOut:
    return held_out(fp32_onnx, data.split(options.holdout_split), data.window_ms, options.holdout_frames,
                    f"{Path(data.root).name}/{options.holdout_split}", options.threads)


def search_set(fp32_onnx: Path, data: PreparedData, options: EdgeInt8Options) -> HeldOut:
    """The return-to-float search's frames: the search split, with the fp32 graph's poses."""
    return held_out(fp32_onnx, data.split(options.search_split), data.window_ms, options.search_frames,
                    f"{Path(data.root).name}/{options.search_split}", options.threads)


def search_float_groups(groups: Sequence[str], trial: Callable[[Sequence[str]], Stepper], search: HeldOut,
                        options: EdgeInt8Options, runtime: str) -> Placement:
    """The return-to-float search of both INT8 converters (quantize/place.greedy_groups): the
    artifact fully in 8 bits first, judged on `search`; while it is over budget there, the group
    whose return to float lowers the worst upper bound most stays float. `trial(floats)` is a
    stepper of the artifact with the groups `floats` float, on `runtime`."""

    def evaluate(floats: Sequence[str], _int16: Sequence[str], label: str) -> Judgement:
        check = check_stepper(trial(floats), search, options.budget)
        log.info("INT8 search (%s): %s (%d group(s) float): worst share %.3f%s", runtime, label, len(floats),
                 check.worst_share, ", within" if check.within else "")
        return Judgement({runtime: check})

    return greedy_groups([(name, [name]) for name in groups], evaluate, max_rounds=options.search_rounds,
                         first="all-int8")


@dataclass(frozen=True)
class Narrowing:
    """What the narrowing left float (units, and kept groups of fewer than two units, whole),
    one record per trial, and the units it never tried (past --narrow-trials: they stay float)."""
    floats: list[str]
    trials: list[dict[str, Any]]
    untried: list[str]

    def search_fields(self, blocks: Sequence[str]) -> dict[str, Any]:
        """Its entries in convert.json's `artifact.search`, beside the `blocks` the search kept."""
        return {"kept_float": list(self.floats), "blocks_kept_float": list(blocks), "narrowing": self.trials,
                "narrowing_untried": self.untried}


def narrow_float_groups(kept: Sequence[str], units: Mapping[str, Sequence[str]],
                        trial: Callable[[Sequence[str]], Stepper], search: HeldOut, options: EdgeInt8Options,
                        runtime: str) -> Narrowing:
    """The search's unit is a block; one operator may be all a block needed float. For each
    group the search kept float whose `units` (operators, largest weights first) number more
    than one, each unit in turn goes back to 8 bits and stays there when the artifact is still
    within budget on `search`, until `options.narrow_trials` trials have run (each streams the
    search frames, minutes on a large program): the units past the cap stay float.
    `trial(floats)` names units and groups alike."""
    split = {group: list(units[group]) for group in kept if len(units.get(group) or ()) > 1}
    floats = [name for group in kept for name in split.get(group, [group])]
    queue = [(group, unit) for group, members in split.items() for unit in members]
    cap = len(queue) if options.narrow_trials is None else options.narrow_trials
    trials: list[dict[str, Any]] = []
    for group, unit in queue[:cap]:
        candidate = [name for name in floats if name != unit]
        check = check_stepper(trial(candidate), search, options.budget)
        log.info("INT8 narrowing (%s): %s in 8 bits: worst share %.3f%s", runtime, unit, check.worst_share,
                 ", within" if check.within else "")
        trials.append({"unit": unit, "group": group, "within": check.within,
                       "worst_share": check.worst_share, "distance_pct": check.fidelity_pct})
        if check.within:
            floats = candidate
    return Narrowing(floats, trials, [unit for _, unit in queue[cap:]])


def search_record(placement: Placement, search: HeldOut, options: EdgeInt8Options, runtime: str) -> dict[str, Any]:
    """convert.json's `artifact.search`: where the search judged, what it kept float, every trial."""
    return {"split": options.search_split, "frames": search.frames, "runtime": runtime,
            "kept_float": list(placement.float_nodes), **placement.to_dict()}


def check_artifact(path: str | os.PathLike, runtime: str, held: HeldOut, options: EdgeInt8Options) -> BudgetCheck:
    """The task budget of the artifact on its own runtime, states carried by that runtime."""
    return check_stepper(open_stepper(path, runtime, options.threads), held, options.budget)


def budget_record(check: BudgetCheck, held: HeldOut, runtime: str) -> dict[str, Any]:
    """convert.json's `budget`: within or not, each metric's change and upper bound, the frames,
    and the distance to the fp32 poses (fidelity, not budgeted)."""
    return {"within": check.within, "runtime": runtime, "data": held.name, "frames": check.frames,
            "sequences": check.sequences, "reference": "fp32 ONNX graph on ONNX Runtime",
            "distance_to_fp32_mm": check.fidelity_mm, "distance_to_fp32_pct_of_mpjpe": check.fidelity_pct,
            "metrics": {m.name: {"fp32_mm": m.fp32_mm, "int8_mm": m.value_mm, "change_pct": m.change_pct,
                                 "upper_pct": m.upper_pct, "limit_pct": m.limit_pct, "within": m.within,
                                 "precise": m.precise} for m in check.metrics},
            "budget": check.budget.to_dict()}


def budget_line(check: BudgetCheck) -> str:
    """One line for the terminal: each metric's change, its upper bound and the limit."""
    parts = [f"{m.name} {m.change_pct:+.2f}% (upper {m.upper_pct:+.2f}%, limit +{m.limit_pct:g}%)"
             for m in check.metrics]
    verdict = "within budget" if check.within else "OVER BUDGET"
    return f"{verdict} on {check.frames} held-out frames: " + ", ".join(parts) + \
        f"; {check.fidelity_mm:.3f} mm from the fp32 poses"
