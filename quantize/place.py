"""Pass 3, place precisions: which Conv/MatMul/Gemm outside the recurrent groups leave 8 bits.

Ordered as NNCF's accuracy control orders it: the full-integer graph first (every Conv,
MatMul and Gemm at 8 bits, the recurrent groups float). If it meets the task budget on the
search frames it is the plan. Otherwise nodes return to float, the fewest that do: each node
is ranked by how far its own 8 bits move the poses (quantised alone, every other node float:
on this model the nodes' errors add roughly in quadrature, so a solo trial measures a node's
share with little noise), and the k top-ranked return, for the smallest k whose graph meets
the budget (k doubling from 1, then bisection between the last k over and the first within).

On a target that runs 16-bit activations in integers (`--target npu`) the returning nodes try
16-bit activations first: the smallest prefix at int16, and only if none meets the budget the
smallest prefix in float. CPU targets never get 16-bit nodes: ONNX Runtime and OpenVINO run
them in float behind a DequantizeLinear, slower than float itself (a 0.58x fp32 graph of 72
such nodes was the old default).

The evaluator and the ranking are injected (the pipeline builds, runs and judges trial
graphs; tests pass numbers), so this file is the order alone.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Callable, Protocol, Sequence

log = logging.getLogger(__name__)

FULL_INTEGER = "full-integer"


class Verdict(Protocol):
    """What a trial's judgement must say (holdout.Judgement)."""

    @property
    def within(self) -> bool: ...

    @property
    def worst_share(self) -> float: ...

    @property
    def fidelity_pct(self) -> float: ...


# (nodes returned to float, nodes at 16-bit activations, label) -> the trial graph's verdict
Evaluate = Callable[[Sequence[str], Sequence[str], str], Verdict]
# node -> how far its 8 bits alone move the poses (% of fp32 MPJPE)
Rank = Callable[[str], float]


@dataclass(frozen=True)
class Trial:
    label: str
    float_nodes: int
    int16_nodes: int
    within: bool
    worst_share: float     # the largest upper bound over its limit: <= 1 within budget
    distance_pct: float    # fidelity: the poses' distance to fp32's

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Placement:
    float_nodes: tuple[str, ...]   # returned to float (the recurrent groups are float anyway)
    int16_nodes: tuple[str, ...]
    within: bool                   # on the search frames
    trials: tuple[Trial, ...]
    ranking: tuple[tuple[str, float], ...] = ()

    def to_dict(self) -> dict:
        return {"float_nodes": list(self.float_nodes), "int16_nodes": list(self.int16_nodes), "within": self.within,
                "trials": [t.to_dict() for t in self.trials],
                "ranking": [{"node": n, "distance_pct": d} for n, d in self.ranking]}

    def report_lines(self, search_frames: str) -> list[str]:
        rows = ["| trial | nodes to float | nodes at int16 | worst upper bound / limit | distance to fp32 % | within |",
                "|---|---:|---:|---:|---:|---|"]
        rows += [f"| {t.label} | {t.float_nodes} | {t.int16_nodes} | {t.worst_share:.3f} | {t.distance_pct:.3f} | "
                 f"{'yes' if t.within else 'no'} |" for t in self.trials]
        outcome = ("the full-integer graph meets the budget there" if not (self.float_nodes or self.int16_nodes) else
                   f"{len(self.float_nodes)} nodes return to float, {len(self.int16_nodes)} take 16-bit activations")
        return [f"## Placement (search on {search_frames})", "", f"Full integer first, then the fewest top-ranked "
                f"nodes out of 8 bits: {outcome}.", "", *rows, ""]


def _trial(label: str, floats: Sequence[str], int16: Sequence[str], verdict: Verdict) -> Trial:
    return Trial(label, len(floats), len(int16), bool(verdict.within), float(verdict.worst_share),
                 float(verdict.fidelity_pct))


def smallest_prefix(count: int, fits: Callable[[int], bool], max_probes: int) -> int | None:
    """The smallest k in 1..count with `fits(k)`, by doubling then bisection (assuming fits is
    monotone in k; where it is not, a measured k that fits is still returned). None when no
    probed k fits within `max_probes` probes."""
    probes, over, within, k = 0, 0, None, 1
    while within is None and probes < max_probes and count > 0:
        k = min(k, count)
        probes += 1
        if fits(k):
            within = k
        elif k == count:
            break
        else:
            over, k = k, 2 * k
    while within is not None and within - over > 1 and probes < max_probes:
        middle = (over + within) // 2
        probes += 1
        if fits(middle):
            within = middle
        else:
            over = middle
    return within


def place_precisions(compute: Sequence[str], evaluate: Evaluate, rank: Rank, *, int16: bool = False,
                     max_trials: int = 24) -> Placement:
    """The plan for `compute` (the Conv/MatMul/Gemm the search may place): module doc."""
    trials: list[Trial] = []
    full = evaluate((), (), FULL_INTEGER)
    trials.append(_trial(FULL_INTEGER, (), (), full))
    if full.within:
        return Placement((), (), True, tuple(trials))
    ranking = tuple(sorted(((node, float(rank(node))) for node in compute), key=lambda r: (-r[1], r[0])))
    ranked = [node for node, _ in ranking]

    def fits_at(precision: str) -> Callable[[int], bool]:
        def fits(k: int) -> bool:
            floats, sixteen = (ranked[:k], ()) if precision == "float" else ((), ranked[:k])
            verdict = evaluate(floats, sixteen, f"top{k}-{precision}")
            trials.append(_trial(f"top{k}-{precision}", floats, sixteen, verdict))
            return bool(verdict.within)
        return fits

    for precision in (("int16", "float") if int16 else ("float",)):
        k = smallest_prefix(len(ranked), fits_at(precision), max_trials)
        if k is not None:
            chosen = tuple(ranked[:k])
            log.info("%d ranked node(s) at %s meet the budget", k, precision)
            return Placement(chosen if precision == "float" else (), chosen if precision == "int16" else (), True,
                             tuple(trials), ranking)
    log.warning("no prefix of the ranked nodes met the budget within %d trials; every ranked node returns to float",
                max_trials)
    return Placement(tuple(ranked), (), False, tuple(trials), ranking)


def greedy_groups(groups: Sequence[tuple[str, Sequence[str]]], evaluate: Evaluate, max_rounds: int = 4,
                  first: str = "all-fp16") -> Placement:
    """FP16's search (its error lives in whole stages, not single nodes: a residual stream of
    ~5,000 rounds to steps of 4 in fp16), and the INT8 `.pte`'s (export/executorch_int8.py):
    `first` is the trial with no group in float; while over budget, try each remaining
    (name, nodes) group in float32 beside those chosen and keep the one that lowers the worst
    share most."""
    chosen: list[str] = []
    best = evaluate((), (), first)
    trials = [_trial(first, (), (), best)]
    remaining = dict(groups)
    for _ in range(max_rounds):
        if best.within or not remaining:
            break
        scored = []
        for name, nodes in remaining.items():
            floats = list(dict.fromkeys([*chosen, *nodes]))
            verdict = evaluate(floats, (), name)
            trials.append(_trial(name, floats, (), verdict))
            scored.append((verdict.worst_share, len(nodes), name, floats, verdict))
        share, _, name, floats, verdict = min(scored, key=lambda s: s[:3])
        if share >= best.worst_share:
            break
        chosen, best = floats, verdict
        del remaining[name]
    return Placement(tuple(chosen), (), bool(best.within), tuple(trials))
