"""Per-node precision, int8 -> int16 -> float (`quantize --exclude auto --search nodes`).

The ranked search (exclusions.py) finds the fewest top-ranked Conv/MatMul/Gemm nodes that
must leave 8 bits for the held-out error to meet the budget. Leaving 8 bits need not mean
float: with 16-bit activations (ONNX QuantizeLinear in UINT16, opset 21) and the same 8-bit
weights, a node keeps its integer weights (the graph stays small and integer-only targets
such as NPUs with a16w8 support can run it) and its activation rounding error drops by
256x. So each such node is tried at int16 before it is given up to float: the lowest
precision whose measured graph error meets the budget wins (`choose_precision`, a pure
function the tests drive with injected errors).

`demote_to_int16` walks the nodes the ranked search took out of 8 bits: first all of them
at int16 at once (one trial; enough when 16 bits are all they needed), otherwise one node at
a time, from the least sensitive to the most, each kept at int16 when the graph still meets
its target with it there. Every decision is recorded with the errors it rests on.

The target is not the budget itself: the demotion may spend only `INT16_SLACK_SHARE` of the
slack the all-float choice left (target = float error + share x (budget - float error)). On
the committed trained `small`, demoting up to the budget's edge took the search's own error
from 0.854% to 0.996% of MPJPE (18 of 32 nodes at int16) and the split the search never saw
from 0.943% to 1.135%, over the budget (benchmarks/results/int8_small_ladder_vnni.md): a choice
fitted to the last hundredth of a percent on one split does not carry to another.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Callable, Collection, Mapping, Sequence

log = logging.getLogger(__name__)

# Cheapest first: fewer bits, smaller graph, integer kernels. "int16": 16-bit activations,
# 8-bit weights; "int16w16": 16-bit weights too.
PRECISIONS: tuple[str, ...] = ("int8", "int16", "int16w16", "float")
# What the recurrent groups' projections are tried at, before float (quantise_recurrent_compute).
RECURRENT_PRECISIONS: tuple[str, ...] = PRECISIONS[:-1]
# Share of the all-float choice's slack under the budget that 16-bit nodes may spend (module doc).
INT16_SLACK_SHARE = 0.5


@dataclass(frozen=True)
class PrecisionChoice:
    node: str
    precision: str
    reason: str
    errors: dict[str, float] = field(default_factory=dict)  # graph error (% of MPJPE) per precision tried

    def to_dict(self) -> dict:
        return asdict(self)


def choose_precision(node: str, errors: Mapping[str, float], budget_pct: float) -> PrecisionChoice:
    """The lowest precision (int8, then int16, then float) whose measured graph error is
    within `budget_pct`; precisions not measured are skipped. When none meets the budget,
    the most accurate one measured (float if it was)."""
    unknown = set(errors) - set(PRECISIONS)
    if unknown:
        raise ValueError(f"unknown precision(s) {sorted(unknown)}; choose from {list(PRECISIONS)}")
    if not errors:
        raise ValueError(f"no measured error for node {node!r}")
    tried = {p: float(errors[p]) for p in PRECISIONS if p in errors}
    over = []
    for precision, err in tried.items():
        if err <= budget_pct:
            why = f"{precision} meets the {budget_pct:g}% budget ({err:.3f}%)"
            if over:
                why += "; " + ", ".join(over) + " over it"
            return PrecisionChoice(node, precision, why, tried)
        over.append(f"{precision} {err:.3f}%")
    best = min(tried, key=lambda p: (tried[p], -PRECISIONS.index(p)))
    return PrecisionChoice(node, best, f"no precision meets the {budget_pct:g}% budget ({', '.join(over)}); "
                                       f"{best} is the most accurate", tried)


@dataclass
class PrecisionPlan:
    """Which nodes ended where, and why."""

    int16: list[str]
    float_nodes: list[str]
    error_pct: float
    choices: list[PrecisionChoice]
    trials: list[dict]

    target_pct: float | None = None
    int16w16: list[str] = field(default_factory=list)
    # Recurrent groups' projections placed at 8 bits (the groups stay float otherwise).
    int8: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"target_pct": self.target_pct, "int16_nodes": self.int16, "int16w16_nodes": self.int16w16,
                "int8_recurrent_nodes": self.int8,
                "float_nodes": self.float_nodes, "error_pct": self.error_pct,
                "choices": [c.to_dict() for c in self.choices], "trials": self.trials}


def int16_target(float_error_pct: float, budget_pct: float, share: float = INT16_SLACK_SHARE) -> float:
    """The error the 16-bit demotion may reach (module doc); the budget when the float choice
    is already over it."""
    if float_error_pct >= budget_pct:
        return budget_pct
    return float_error_pct + share * (budget_pct - float_error_pct)


def demote_to_int16(out_of_int8: Sequence[str], float_error_pct: float, budget_pct: float,
                    evaluate: Callable[[list[str], list[str], str], float],
                    slack_share: float = INT16_SLACK_SHARE, all_int16_error_pct: float | None = None) -> PrecisionPlan:
    """`out_of_int8`: the nodes the ranked search took out of 8 bits, most sensitive first;
    `float_error_pct`: the graph's error with all of them in float. `evaluate(int16_nodes,
    float_nodes, label) -> error %` builds and measures one graph (the rest as before). Each
    node's choice is `choose_precision` against `int16_target` (a share of the slack).
    `all_int16_error_pct`: the error with all of them at int16, where already measured
    (`smallest_int16_plan`), so that graph is not built again."""
    budget_pct = int16_target(float_error_pct, budget_pct, slack_share)
    nodes = list(out_of_int8)
    trials: list[dict] = []

    def measure(int16: list[str], floats: list[str], label: str) -> float:
        err = float(evaluate(int16, floats, label))
        trials.append({"label": label, "int16_nodes": len(int16), "float_nodes": len(floats), "error_pct": err})
        log.info("%s: %d node(s) int16, %d float: %.3f%%", label, len(int16), len(floats), err)
        return err

    if not nodes:
        return PrecisionPlan([], [], float_error_pct, [], trials, budget_pct)
    if all_int16_error_pct is None:
        all16 = measure(nodes, [], "int16_all")
    else:
        all16 = float(all_int16_error_pct)
        trials.append({"label": "int16_all", "int16_nodes": len(nodes), "float_nodes": 0, "error_pct": all16})
    if all16 <= budget_pct:
        choices = [choose_precision(n, {"int16": all16, "float": float_error_pct}, budget_pct) for n in nodes]
        return PrecisionPlan(nodes, [], all16, choices, trials, budget_pct)
    int16: list[str] = []
    floats = list(nodes)
    current = float_error_pct
    decided: dict[str, PrecisionChoice] = {}
    for node in reversed(nodes):  # least sensitive first: the likeliest to take 16 bits
        trial_floats = [n for n in floats if n != node]
        err = measure(int16 + [node], trial_floats, f"int16_{node}")
        choice = choose_precision(node, {"int16": err, "float": current}, budget_pct)
        decided[node] = choice
        if choice.precision == "int16":
            int16.append(node)
            floats, current = trial_floats, err
    return PrecisionPlan(int16, floats, current, [decided[n] for n in nodes], trials, budget_pct)


@dataclass(frozen=True)
class SizeProbe:
    """One candidate of the ranked search with every node it keeps out of 8 bits at int16."""

    label: str
    nodes: int  # out of 8 bits (ranked nodes)
    float_error_pct: float  # the search's figure, those nodes in float
    target_pct: float  # int16_target of that figure
    int16_error_pct: float

    @property
    def fits(self) -> bool:
        return self.int16_error_pct <= self.target_pct

    def to_dict(self) -> dict:
        return {**asdict(self), "fits": self.fits}


def smallest_int16_plan(candidates: Sequence[tuple[str, Sequence[str], float]], budget_pct: float,
                        evaluate: Callable[[list[str], str], float],
                        slack_share: float = INT16_SLACK_SHARE) -> tuple[int | None, list[SizeProbe]]:
    """The objective "size" under int16: of `candidates` (label, nodes out of 8 bits, error
    with them in float) within `budget_pct`, the one with the fewest nodes whose nodes all
    fit at int16 (16-bit activations, 8-bit weights) within its `int16_target`, tried in
    that order, one graph each (`evaluate(int16_nodes, label) -> error %`). Returns its index
    (None when none fits) and every probe made.

    Why this is the smallest graph: an int16 node's 8-bit weights weigh what an int8 node's
    do, so every candidate whose nodes all fit at int16 gives a graph of about the same
    size, the first of them with the fewest nodes out of 8 bits; a candidate whose nodes do
    not all fit keeps some with 16-bit weights or in float (promote_to_int16w16), larger.
    On the committed `small`, AVX2 target: the 37-node candidate (0.736% in float) needed 15
    nodes at int16w16, 0.305x fp32, 0.958% on unseen `val`; the 48-node one (0.478%) fitted
    at int16 (0.588%), 0.291x, 0.662% on `val`."""
    order = sorted((i for i, c in enumerate(candidates) if c[2] <= budget_pct),
                   key=lambda i: (len(candidates[i][1]), candidates[i][2]))
    probes: list[SizeProbe] = []
    for index in order:
        label, nodes, float_error = candidates[index]
        target = int16_target(float_error, budget_pct, slack_share)
        # No node out of 8 bits: the graph at "all int16" is the one already measured.
        err = float(evaluate(list(nodes), f"int16_all_{label}")) if nodes else float(float_error)
        probe = SizeProbe(label, len(nodes), float(float_error), target, err)
        probes.append(probe)
        log.info("%s: %d node(s) at int16: %.3f%% (target %.3f%%)%s", label, len(nodes), err, target,
                 ", fits" if probe.fits else "")
        if probe.fits:
            return index, probes
    return None, probes


def promote_to_int16w16(plan: PrecisionPlan,
                        evaluate: Callable[[list[str], list[str], list[str], str], float]) -> PrecisionPlan:
    """The nodes `demote_to_int16` left in float, tried with 16-bit weights as well as 16-bit
    activations: all at once first, otherwise one at a time from the least sensitive, each
    kept there when the graph still meets the plan's target. `evaluate(int16_nodes,
    int16w16_nodes, float_nodes, label) -> error %`.

    Why: a node stays in float because its 8-bit weights cost too much (on the committed
    `small`, 8-bit weights alone take 0.8 of the 1% budget, the delta head's Gemm most of
    all); at 16 bits a weight's rounding costs ~1/256 of that, so such a node computes what
    float computes while the graph keeps integer weights everywhere (an integer-only target
    with 16-bit support can run every Conv/MatMul/Gemm) and half the float bytes."""
    floats = list(plan.float_nodes)
    if not floats:
        return plan
    target = plan.target_pct if plan.target_pct is not None else plan.error_pct
    trials = list(plan.trials)

    def measure(w16: list[str], rest: list[str], label: str) -> float:
        err = float(evaluate(list(plan.int16), w16, rest, label))
        trials.append({"label": label, "int16_nodes": len(plan.int16), "int16w16_nodes": len(w16),
                       "float_nodes": len(rest), "error_pct": err})
        log.info("%s: %d node(s) int16, %d int16w16, %d float: %.3f%%", label, len(plan.int16), len(w16), len(rest), err)
        return err

    errors: dict[str, float] = {}
    w16: list[str] = []
    current = plan.error_pct
    everything = measure(floats, [], "int16w16_all")
    if everything <= target:
        w16, current = floats, everything
        errors = dict.fromkeys(floats, everything)
    else:
        for node in reversed(floats):  # least sensitive first
            rest = [n for n in floats if n not in w16 and n != node]
            err = measure(w16 + [node], rest, f"int16w16_{node}")
            errors[node] = err
            if err <= target:
                w16.append(node)
                current = err
    choices = []
    for choice in plan.choices:
        if choice.node in w16:
            choice = choose_precision(choice.node, {**choice.errors, "int16w16": errors[choice.node]}, target)
        elif choice.node in errors:  # stays in float: its decision stands, the new trial recorded
            choice = PrecisionChoice(choice.node, choice.precision,
                                     f"{choice.reason}; int16w16 {errors[choice.node]:.3f}% over the {target:g}% target",
                                     {**choice.errors, "int16w16": errors[choice.node]})
        choices.append(choice)
    return PrecisionPlan(list(plan.int16), [n for n in floats if n not in w16], current, choices, trials,
                         plan.target_pct, [n for n in floats if n in w16], list(plan.int8))


def quantise_recurrent_compute(plan: PrecisionPlan, units: Sequence[Sequence[str]],
                               evaluate: Callable[..., float], no_int8: Collection[str] = ()) -> PrecisionPlan:
    """The recurrent groups' Conv/MatMul/Gemm (S5's input and readout projections, the Kalman
    fusion's Gemms), which the ranked search leaves in float with the rest of the recurrent
    groups, given the lowest precision that keeps the graph within the plan's target: all at
    int8 at once, else all at int16, else all at int16w16, else one unit at a time (int8,
    int16, int16w16, else float); where all fitted at once above int8, each unit is then
    tried back at int8, one at a time, and kept there where the graph still fits. A unit is
    the nodes that read one activation tensor (graph_groups.shared_input_units): one of them
    at 16 bits makes the tensor 16-bit for all. `no_int8`: nodes that read a tensor the
    plan's 16-bit nodes already widen; their units are not tried at int8 (nor is the
    all-at-once int8 graph, which could not be what it says).

    The recurrences themselves (the state update's elementwise ops) stay float; these nodes
    project into and out of the state, so their activations' rounding reaches the drive
    added to the state and what a readout reads, never the state carried to the next step
    (S5's readouts read a copy of the new state, graph_groups.isolate_state_reads; the
    caller leaves out any node that still reads or writes a graph output, which ONNX
    Runtime's quantiser would round where the graph outputs it).
    `evaluate(int16_nodes, int16w16_nodes, float_nodes, label, int8=recurrent_nodes_at_int8)
    -> error %` over the whole graph's lists; `plan.int8` lists the recurrent nodes placed at
    8 bits (the caller takes them out of the recurrent groups it keeps in float).

    Why int8 first: a drive projection rounds every step's input to a state that integrates
    it and a readout reads a state whose channels span decades, so most of them need 16 bits
    (on the committed `small`: all 11 at int8 1.090% against 0.589% at int16; back at int8
    one unit at a time, two of the fusion's three Gemms fitted); but the search never priced
    them, and each that fits at 8 bits is one node fewer out of 8 bits, on the integer
    kernels."""
    if any(isinstance(u, str) for u in units):
        raise TypeError("units are sequences of node names (graph_groups.shared_input_units), not names")
    units = [list(u) for u in units if u]
    nodes = [n for u in units for n in u]
    target = plan.target_pct if plan.target_pct is not None else plan.error_pct
    if not nodes or plan.error_pct > target:  # no slack to spend: they stay in float, undecided
        return plan
    blocked = set(no_int8)
    trials = list(plan.trials)
    assigned: dict[str, str] = {}  # recurrent node -> the precision it keeps

    def split(assignment: Mapping[str, str]) -> tuple[dict[str, list[str]], list[str]]:
        """The recurrent nodes at each precision, and those in float (not assigned)."""
        return ({p: [n for n in nodes if assignment.get(n) == p] for p in RECURRENT_PRECISIONS},
                [n for n in nodes if n not in assignment])

    def measure(unit: Sequence[str], precision: str, label: str) -> float:
        """The graph with `unit` at `precision` and the others as `assigned` (float if not)."""
        at, rest = split({**assigned, **dict.fromkeys(unit, precision)})
        err = float(evaluate(plan.int16 + at["int16"], plan.int16w16 + at["int16w16"], plan.float_nodes + rest,
                             label, int8=plan.int8 + at["int8"]))
        trials.append({"label": label, "int8_recurrent_nodes": len(plan.int8 + at["int8"]),
                       "int16_nodes": len(plan.int16 + at["int16"]),
                       "int16w16_nodes": len(plan.int16w16 + at["int16w16"]),
                       "float_nodes": len(plan.float_nodes + rest), "error_pct": err})
        log.info("%s: recurrent nodes %d int8, %d int16, %d int16w16, %d float: %.3f%%", label, len(at["int8"]),
                 len(at["int16"]), len(at["int16w16"]), len(rest), err)
        return err

    def precisions(unit: Sequence[str]) -> tuple[str, ...]:
        return RECURRENT_PRECISIONS if not blocked & set(unit) else RECURRENT_PRECISIONS[1:]

    current = plan.error_pct
    errors: dict[str, dict[str, float]] = {n: {} for n in nodes}
    together = None
    for precision in precisions(nodes):  # all at once, cheapest first
        err = measure(nodes, precision, f"recurrent_{precision}_all")
        for node in nodes:
            errors[node][precision] = err
        if err <= target:
            assigned, current, together = dict.fromkeys(nodes, precision), err, precision
            break
    if together is None:  # one unit at a time, each at the first precision that fits
        for unit in units:
            errors.update({n: {} for n in unit})
            for precision in precisions(unit):
                err = measure(unit, precision, f"recurrent_{precision}_{'+'.join(unit)}")
                errors.update({n: {**errors[n], precision: err} for n in unit})
                if err <= target:
                    assigned.update(dict.fromkeys(unit, precision))
                    current = err
                    break
    elif together != "int8":  # each unit back at 8 bits where the graph still fits
        for unit in (u for u in units if "int8" in precisions(u)):
            err = measure(unit, "int8", f"recurrent_int8_{'+'.join(unit)}")
            errors.update({n: {**errors[n], "int8": err} for n in unit})
            if err <= target:
                assigned.update(dict.fromkeys(unit, "int8"))
                current = err
    # plan.error_pct (every recurrent node in float) is within the target (checked above), so
    # each node's choice is the first precision its trials found within it, float last.
    choices = list(plan.choices) + [
        PrecisionChoice(c.node, c.precision, f"recurrent group: {c.reason}", c.errors)
        for c in (choose_precision(n, {**errors[n], "float": plan.error_pct}, target) for n in nodes)]
    at, rest = split(assigned)
    return PrecisionPlan(plan.int16 + at["int16"], plan.float_nodes + rest, current, choices, trials,
                         plan.target_pct, plan.int16w16 + at["int16w16"], plan.int8 + at["int8"])
