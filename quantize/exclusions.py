"""`--exclude auto`: the smallest set of nodes to keep in float so the held-out accuracy
stays within a budget.

Always kept in float: the recurrent groups (S5 recurrences, Kalman fusion; see
graph_groups). Then one of two searches:

- `groups` (greedy forward selection over module scopes and op types): while the budget is
  exceeded, try adding each remaining group, keep the one that lowers the error most (ties:
  the smaller group), stop when within budget, when no group helps, or after `max_rounds`.
- `nodes` (sensitivity-ranked): quantise each compute node alone (every other node float)
  and measure its held-out error; rank the nodes by it; keep the top k in float, k found by
  doubling then bisection. On the trained `small` the error is concentrated in a few
  projections (attention.0's outer projections, the S5 feed-forward output) that no single
  module group isolates, and the per-node errors add roughly in quadrature (their root sum
  of squares over 106 nodes, 11.0%, is close to the all-quantised 11.2%), so a ranked
  prefix reaches a budget with far fewer float nodes than whole groups do.

Each trial re-uses the calibration cache, so a trial costs one quantiser pass and one
held-out rollout, not a calibration.
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
    strategy: str = "groups"
    # `nodes` search: every ranked node with its error when quantised alone, highest first.
    sensitivity: list[dict] = field(default_factory=list)
    # `nodes` search: held-out frames per sequence the solo (ranking) trials ran on.
    rank_frames: int | None = None

    @property
    def within_budget(self) -> bool:
        return self.error_pct <= self.budget_pct

    def to_dict(self) -> dict:
        out = {"strategy": self.strategy, "chosen_groups": self.chosen, "error_pct": self.error_pct,
               "budget_pct": self.budget_pct, "within_budget": self.within_budget, "trials": self.trials}
        if self.sensitivity:
            out["sensitivity"] = self.sensitivity
            out["rank_frames"] = self.rank_frames
        return out


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


@dataclass(frozen=True)
class NodeRanking:
    """The nodes search's ranking: every target node with its held-out error when quantised
    alone (highest first), and the held-out frames per sequence those solo trials ran on."""
    rows: list[dict]
    frames: int | None = None

    @property
    def nodes(self) -> list[str]:
        return [r["node"] for r in self.rows]


def node_sensitivity(nodes: list[str], evaluate_alone: Callable[[str], float]) -> list[dict]:
    """[{node, error_pct}] with each node quantised alone, highest error first (ties: name)."""
    rows = [{"node": node, "error_pct": float(evaluate_alone(node))} for node in nodes]
    return sorted(rows, key=lambda r: (-r["error_pct"], r["node"]))


def prefix_label(k: int) -> str:
    return f"top{k}"


def ranked_prefix_exclusions(
    base: list[str], ranking: NodeRanking, budget_pct: float,
    evaluate: Callable[[list[str], str], float], max_trials: int = 24,
) -> SearchResult:
    """Keep the `k` highest-ranked nodes in float (beyond `base`), for the smallest k whose
    held-out error is within budget: k = 0, 1, 2, 4, ... until one is within budget (or all
    are float), then bisection between the last k over budget and the first within. The
    bisection assumes the error falls as k grows; where it does not, the result is still a
    measured k within budget, the smallest the probes found. `max_trials` bounds the probes.
    Without any k within budget, the most accurate k measured is returned. The result carries
    the ranking (its rows and frames) for the report."""
    base = list(dict.fromkeys(base))
    ranked = ranking.nodes
    measured: dict[int, float] = {}
    trials: list[dict] = []

    def probe(k: int) -> float:
        if k not in measured:
            excluded = list(dict.fromkeys(base + ranked[:k]))
            label = "base" if k == 0 else prefix_label(k)
            measured[k] = float(evaluate(excluded, label))
            trials.append({"round": 0 if k == 0 else 1, "group": None if k == 0 else label, "label": label,
                           "float_nodes": k, "nodes": len(excluded), "error_pct": measured[k]})
            log.info("%s: %d ranked node(s) in float: %.3f%%", label, k, measured[k])
        return measured[k]

    over, within = 0, None
    if probe(0) > budget_pct:
        k = 1
        while within is None and len(trials) < max_trials:
            k = min(k, len(ranked))
            if probe(k) <= budget_pct:
                within = k
            elif k == len(ranked):
                break
            else:
                over, k = k, k * 2
        while within is not None and within - over > 1 and len(trials) < max_trials:
            mid = (over + within) // 2
            if probe(mid) <= budget_pct:
                within = mid
            else:
                over = mid
    else:
        within = 0
    k = within if within is not None else min(measured, key=lambda key: (measured[key], key))
    chosen = [] if k == 0 else [prefix_label(k)]
    result = SearchResult(chosen, list(dict.fromkeys(base + ranked[:k])), measured[k], budget_pct, trials,
                          strategy="nodes", sensitivity=ranking.rows, rank_frames=ranking.frames)
    if not result.within_budget:
        log.warning("held-out error %.3f%% is above the %.3g%% budget with %d ranked node(s) in float; raise "
                    "--budget-pct or keep more in float with --exclude", measured[k], budget_pct, k)
    return result


def scratch_model_path(folder: str | os.PathLike, label: str) -> Path:
    safe = "".join(c if c.isalnum() else "_" for c in label)
    return Path(tempfile.mkstemp(prefix=f"trial_{safe}_", suffix=".onnx", dir=folder)[1])
