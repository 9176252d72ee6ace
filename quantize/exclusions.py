"""`--exclude auto`: the smallest set of node groups to keep in float so the held-out
accuracy stays within a budget.

Always kept in float: the recurrent groups (S5 recurrences, Kalman fusion; see
graph_groups). Then greedy forward selection over the candidate groups (module scopes and
op types): while the budget is exceeded, try adding each remaining group, keep the one
that lowers the error most (ties: the smaller group), stop when within budget, when no
group helps, or after `max_rounds`. Each trial re-uses the calibration cache, so a trial
costs one quantiser pass and one held-out rollout, not a calibration.
"""
from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from e3dpsm.quantize.graph_groups import NodeGroup

log = logging.getLogger(__name__)


@dataclass
class SearchResult:
    chosen: list[str]                      # candidate groups added, in order
    excluded_nodes: list[str]              # recurrent + chosen groups
    error_pct: float                       # budgeted error of the final choice
    budget_pct: float
    trials: list[dict] = field(default_factory=list)

    @property
    def within_budget(self) -> bool:
        return self.error_pct <= self.budget_pct

    def to_dict(self) -> dict:
        return {"chosen_groups": self.chosen, "error_pct": self.error_pct, "budget_pct": self.budget_pct,
                "within_budget": self.within_budget, "trials": self.trials}


def greedy_exclusions(
    base: list[str], candidates: list[NodeGroup], budget_pct: float,
    evaluate: Callable[[list[str], str], float], max_rounds: int = 4,
) -> SearchResult:
    """`evaluate(excluded_nodes, label) -> error_pct` quantises with those nodes in float
    and measures the budgeted error (HoldoutSet bound)."""
    excluded = list(dict.fromkeys(base))
    error = evaluate(excluded, "base")
    trials = [{"round": 0, "group": None, "nodes": len(excluded), "error_pct": error}]
    chosen: list[str] = []
    remaining = list(candidates)
    for round_ in range(1, max_rounds + 1):
        if error <= budget_pct or not remaining:
            break
        scored = []
        for group in remaining:
            trial = list(dict.fromkeys(excluded + list(group.nodes)))
            err = evaluate(trial, group.name)
            trials.append({"round": round_, "group": group.name, "nodes": len(group), "error_pct": err})
            scored.append((err, len(group), group.name, group, trial))
        best_err, _, _, best, trial = min(scored, key=lambda s: s[:3])
        if best_err >= error:
            log.info("no group lowers the error below %.3f%%; stopping", error)
            break
        log.info("round %d: keep %s in float (%d nodes): %.3f%% -> %.3f%%", round_, best.name, len(best), error, best_err)
        excluded, error = trial, best_err
        chosen.append(best.name)
        remaining = [g for g in remaining if g.name != best.name]
    result = SearchResult(chosen, excluded, error, budget_pct, trials)
    if not result.within_budget:
        # The artifact is still written (it is the best found); the report and this line say so.
        log.warning("held-out error %.3f%% is above the %.3g%% budget after %d round(s); raise --budget-pct "
                    "or keep more groups in float with --exclude", error, budget_pct, len(chosen))
    return result


def scratch_model_path(folder: str | os.PathLike, label: str) -> Path:
    safe = "".join(c if c.isalnum() else "_" for c in label)
    return Path(tempfile.mkstemp(prefix=f"trial_{safe}_", suffix=".onnx", dir=folder)[1])
