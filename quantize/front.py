"""Latency-aware choice among the graphs the exclusion search built.

`--exclude auto` first runs one of two searches (exclusions.py), each measuring the held-out
distance to fp32 of every trial graph it builds:

- `--search nodes` (the INT8 default): each Conv/MatMul/Gemm is quantised alone and the nodes
  are ranked by that solo error; the search then keeps the fewest top-ranked nodes in float
  that meet the budget (doubling, then bisection);
- `--search groups` (the FP16 default): whole module / op-type groups are added to the float
  set greedily, the most helpful group each round.

Every node kept in float costs speed, and trials that cost the same accuracy can cost very
different time, so the trial graphs are also timed (side by side with fp32, step_timer.py) and:

- objective "latency" (default): the fastest candidate within the accuracy budget (within
  LATENCY_TIE of the fastest counts as a tie, which the lower distance breaks). The
  candidates' timings are short, so a pick other than the search's own choice is timed
  again beside it, longer (`confirm`), and kept only where it is surely faster: the lower
  end of the speed-up's interval above 1 (a 30-step timing of one graph against fp32 ranged
  0.56-1.25x on a shared 2-core host, step_timer.py);
- objective "accuracy": the search's own result (the fewest nodes or groups in float that
  reach the budget, or the most accurate graph found when none does);
- objective "size" (the default under int16): the accuracy objective's choice here; then the
  16-bit plan moves it to the smallest graph (precision.smallest_int16_plan).

No candidate outside the budget is chosen while one within it exists. The report holds
every timed candidate and the Pareto front of (distance to fp32, p50 step latency).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from e3dpsm.errors import ConfigError
from e3dpsm.quantize.exclusions import SearchResult
from e3dpsm.quantize.step_timer import StepTimer

log = logging.getLogger(__name__)

# "size" chooses here as "accuracy" does; under int16 the 16-bit plan's probes then move the
# choice to the smallest graph (precision.smallest_int16_plan, quantize/api.py).
OBJECTIVES: tuple[str, ...] = ("latency", "accuracy", "size")
# Candidates whose p50 is within this share of the fastest one count as equally fast (a few
# dozen steps on a shared CPU do not resolve less); among them the most accurate is chosen.
LATENCY_TIE = 0.03
FP32_LABEL = "fp32"
# Times a graph beside a reference, longer than the candidates' timing:
# SideBySideTimer.compare with its step count bound; returns its dict (speed-up, interval).
Confirm = Callable[[Path, Path], dict]


@dataclass
class Candidate:
    """One graph the search built: which groups it keeps in float and how it did."""

    label: str
    groups: list[str]                  # candidate groups kept in float beyond the recurrent ones
    excluded_nodes: list[str]
    error_pct: float                   # held-out distance to fp32 / fp32 MPJPE (bound_pct)
    path: Path | None = None           # scratch graph while the search runs
    p50_ms: float | None = None

    def row(self, budget_pct: float) -> dict[str, Any]:
        return {"label": self.label, "float_groups": list(self.groups), "distance_pct": self.error_pct,
                "p50_ms": self.p50_ms, "within_budget": self.error_pct <= budget_pct}


@dataclass
class LatencySearch:
    objective: str
    budget_pct: float
    candidates: list[Candidate]
    chosen: Candidate
    fp32_p50_ms: float | None
    timer: dict[str, Any] = field(default_factory=dict)
    # The longer timing of the fastest candidate beside the search's own choice (see `confirm`).
    confirmation: dict[str, Any] | None = None

    def front(self) -> list[Candidate]:
        return pareto_front(self.candidates)

    def to_dict(self) -> dict[str, Any]:
        """The report's stable "search" block: the pipeline index reads `front` and `chosen`."""
        front_labels = {c.label for c in self.front()}

        def row(c: Candidate) -> dict[str, Any]:
            r = c.row(self.budget_pct)
            r["speedup_vs_fp32"] = (self.fp32_p50_ms / c.p50_ms) if self.fp32_p50_ms and c.p50_ms else None
            r["on_front"] = c.label in front_labels
            r["chosen"] = c.label == self.chosen.label
            return r

        return {"objective": self.objective, "budget_pct": self.budget_pct, "fp32_p50_ms": self.fp32_p50_ms,
                "timer": self.timer, "chosen": row(self.chosen), "confirmation": self.confirmation,
                "front": [row(c) for c in self.front()],
                "candidates": [row(c) for c in self.candidates]}


def pareto_front(candidates: Sequence[Candidate]) -> list[Candidate]:
    """Timed candidates no other candidate beats on both distance and latency (and ties on
    neither), sorted by latency."""
    timed = [c for c in candidates if c.p50_ms is not None]

    def dominated(c: Candidate) -> bool:
        return any(o.error_pct <= c.error_pct and o.p50_ms <= c.p50_ms
                   and (o.error_pct < c.error_pct or o.p50_ms < c.p50_ms) for o in timed)

    return sorted((c for c in timed if not dominated(c)), key=lambda c: (c.p50_ms, c.error_pct))


def candidates_from_search(search: SearchResult, evaluated: Sequence[tuple[list[str], Path | None]]) -> list[Candidate]:
    """One candidate per trial of the greedy search. `evaluated` holds, in call order, what
    the search's evaluate callback built: (excluded nodes, scratch path or None)."""
    if len(evaluated) != len(search.trials):
        raise ValueError(f"{len(evaluated)} graphs built for {len(search.trials)} trials")
    out: list[Candidate] = []
    for index, (trial, (excluded, path)) in enumerate(zip(search.trials, evaluated)):
        round_ = trial["round"]
        groups = list(search.chosen[: max(round_ - 1, 0)]) + ([trial["group"]] if trial["group"] else [])
        # The ranked-node search names its own trials (`top8`); the greedy one by round.
        label = trial.get("label") or ("base" if trial["group"] is None else f"r{round_}:{trial['group']}")
        out.append(Candidate(label, groups, list(excluded), float(trial["error_pct"]), path))
    return out


def greedy_choice(search: SearchResult, candidates: Sequence[Candidate]) -> Candidate:
    """The candidate the greedy search settled on (today's `--objective accuracy`)."""
    wanted = list(search.chosen)
    for cand in candidates:
        if cand.groups == wanted and cand.error_pct == search.error_pct:
            return cand
    raise ValueError(f"no trial matches the search's choice {wanted}")


def to_time(candidates: Sequence[Candidate], search: SearchResult, budget_pct: float, max_timed: int) -> list[Candidate]:
    """Which candidates are worth timing (a bounded number): the greedy choice, every
    within-budget candidate (fewest float groups and lowest distance first), then the
    out-of-budget ones along the greedy path (the front's fast end)."""
    chosen = greedy_choice(search, candidates)
    # Fewest groups, then fewest float nodes, first: those are the likely fast ones.
    inside = sorted((c for c in candidates if c.error_pct <= budget_pct and c is not chosen),
                    key=lambda c: (len(c.groups), len(c.excluded_nodes), c.error_pct))
    path_labels = {"base"} | {f"r{i + 1}:{g}" for i, g in enumerate(search.chosen)}
    if search.strategy == "nodes":  # every probe of the ranked search is on its one path
        path_labels |= {t["label"] for t in search.trials}
    outside = [c for c in candidates if c.error_pct > budget_pct and c.label in path_labels and c is not chosen]
    picked = [chosen, *inside, *outside]
    return picked[:max(1, max_timed)]


def choose(candidates: Sequence[Candidate], search: SearchResult, objective: str, budget_pct: float) -> Candidate:
    if objective not in OBJECTIVES:
        raise ConfigError(f"unknown objective {objective!r}; choose from {list(OBJECTIVES)}")
    greedy = greedy_choice(search, candidates)
    if objective in ("accuracy", "size"):
        return greedy
    inside = [c for c in candidates if c.error_pct <= budget_pct and c.p50_ms is not None]
    if not inside:
        return greedy  # nothing meets the budget: the most accurate graph the search found
    fastest = min(c.p50_ms for c in inside)
    near = [c for c in inside if c.p50_ms <= fastest * (1 + LATENCY_TIE)]
    return min(near, key=lambda c: (c.error_pct, c.p50_ms, len(c.excluded_nodes)))


def latency_aware_choice(search: SearchResult, candidates: list[Candidate], timer: StepTimer | None,
                         objective: str, budget_pct: float, *, max_timed: int = 6,
                         reference: Path | None = None, timer_info: dict | None = None,
                         confirm: Confirm | None = None) -> LatencySearch:
    """Time the candidates worth timing (and the fp32 `reference`, side by side) with
    `timer`, then pick by `objective`. Without a timer only the accuracy objective works.
    With `confirm`, a latency pick other than the search's own choice ships only if timed
    surely faster than it (`confirm_faster`)."""
    if objective not in OBJECTIVES:
        raise ConfigError(f"unknown objective {objective!r}; choose from {list(OBJECTIVES)}")
    fp32_ms = None
    if timer is not None:
        timed = to_time(candidates, search, budget_pct, max_timed)
        graphs = {c.label: c.path for c in timed if c.path is not None}
        if reference is not None:
            graphs[FP32_LABEL] = reference
        ms = timer(graphs)
        for c in timed:
            c.p50_ms = ms.get(c.label)
        fp32_ms = ms.get(FP32_LABEL)
    elif objective == "latency":
        raise ConfigError("the latency objective needs a step timer")
    chosen = choose(candidates, search, objective, budget_pct)
    confirmation = None
    if objective == "latency" and confirm is not None:
        chosen, confirmation = confirm_faster(chosen, greedy_choice(search, candidates), budget_pct, confirm)
    log.info("objective %s: %s (distance %.3f%%, %s ms/step)", objective, chosen.groups or "recurrent only",
             chosen.error_pct, f"{chosen.p50_ms:.2f}" if chosen.p50_ms is not None else "untimed")
    return LatencySearch(objective, budget_pct, list(candidates), chosen, fp32_ms, timer_info or {}, confirmation)


def confirm_faster(picked: Candidate, own: Candidate, budget_pct: float,
                   confirm: Confirm) -> tuple[Candidate, dict[str, Any] | None]:
    """`picked` (the latency objective's choice) timed again beside `own` (the search's own
    choice) by `confirm`: kept where the lower end of its speed-up's interval is above 1,
    else `own` ships, the fewer nodes out of 8 bits or the lower distance, not a timing's
    noise. Nothing to confirm where they are one graph, where either has no graph, or where
    `own` is outside the budget (a graph within it is never traded for one outside)."""
    if picked is own or picked.path is None or own.path is None or own.error_pct > budget_pct:
        return picked, None
    timed = confirm(picked.path, own.path)
    interval = timed.get("interval") or {}
    low = interval.get("low", timed["speedup_vs_fp32"])
    kept = low > 1.0
    confirmation = {"candidate": picked.label, "against": own.label, "speedup": timed["speedup_vs_fp32"],
                    "interval": interval or None, "steps": (timed.get("timer") or {}).get("steps"),
                    "kept": kept}
    log.info("latency pick %s against the search's own %s: %.2fx (interval low %.2f): %s", picked.label,
             own.label, timed["speedup_vs_fp32"], low, "kept" if kept else "not surely faster, the search's own ships")
    return (picked if kept else own), confirmation
