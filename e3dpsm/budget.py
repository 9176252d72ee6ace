"""The accuracy budget of a compressed graph, on the task's own metrics.

A compressed graph is judged the way its users judge it: on held-out frames that neither the
calibration nor the search saw, its MPJPE and PA-MPJPE may rise at most 1% above the fp32
graph's on the same frames, and the jitter of its fused pose (mean norm of the second
difference) at most 5%. That is the form of NNCF's accuracy control (`max_drop` of the
validation metric), AIMET's mixed-precision "allowed accuracy drop" and MLPerf Inference's
"99% of the fp32 reference". The distance to the fp32 poses is reported beside as a fidelity
figure; it is what `golden check` holds a device to, not what a graph is budgeted on.

Every change is a paired comparison on the same frames, and its noise comes from a
moving-block bootstrap: consecutive frames of a stream are correlated, so blocks of frames
(never crossing a sequence's end; 50 frames, where the autocorrelation of the per-frame
MPJPE difference has fallen from 0.88 at lag 1 to about 0.1: docs/quantize.md) are drawn with
replacement, the same blocks for both graphs.
The budget holds when the upper end of the one-sided interval (`confidence`) does, and the
estimate is called precise when its bootstrap standard deviation is at most a tenth of the
limit (else more held-out frames are needed: the report says so).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np

from e3dpsm.errors import ConfigError
from e3dpsm.metrics import jitter_errors, joint_errors, pa_joint_errors

# A graph's noise is small enough to judge when the bootstrap sd is at most this share of a limit.
PRECISION_SHARE = 0.1
# Blocks shorten on short rollouts so that a bootstrap draws at least this many (a 200-step
# golden rollout in blocks of 50 would have 4 to draw from, and an interval of few values).
MIN_BLOCKS = 20


@dataclass(frozen=True)
class TaskBudget:
    """Allowed rise of each task metric over fp32, in % of fp32's value on the same frames."""

    mpjpe_pct: float = 1.0
    pa_mpjpe_pct: float = 1.0
    jitter_pct: float = 5.0
    confidence: float = 0.95   # the one-sided interval whose upper end must hold
    block_frames: int = 50     # bootstrap block: one second of 50 Hz poses
    resamples: int = 1000
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("mpjpe_pct", "pa_mpjpe_pct", "jitter_pct"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"the {name.replace('_pct', '')} budget must be positive, got {getattr(self, name)}")
        if not 0.5 <= self.confidence < 1.0:
            raise ConfigError(f"the budget's confidence must be in [0.5, 1), got {self.confidence}")
        if self.block_frames < 1 or self.resamples < 10:
            raise ConfigError("the budget's bootstrap needs block_frames >= 1 and resamples >= 10")

    @property
    def limits(self) -> dict[str, float]:
        return {"mpjpe": self.mpjpe_pct, "pa_mpjpe": self.pa_mpjpe_pct, "jitter": self.jitter_pct}

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class MetricChange:
    """One task metric of a graph against fp32 on the same frames."""

    name: str
    fp32_mm: float
    value_mm: float
    change_pct: float      # point estimate: 100 (value / fp32 - 1)
    lower_pct: float       # the central interval whose ends are one-sided bounds at the budget's confidence
    upper_pct: float
    noise_pct: float       # bootstrap standard deviation of change_pct
    limit_pct: float

    @property
    def within(self) -> bool:
        return bool(self.upper_pct <= self.limit_pct)

    @property
    def surely_over(self) -> bool:
        """Over its limit even at the interval's lower end: more frames would not save it."""
        return bool(self.lower_pct > self.limit_pct)

    @property
    def precise(self) -> bool:
        return bool(self.noise_pct <= PRECISION_SHARE * self.limit_pct)

    def to_dict(self) -> dict:
        return {**asdict(self), "within": self.within, "surely_over": self.surely_over, "precise": self.precise}


@dataclass(frozen=True)
class BudgetCheck:
    """The task budget of one graph on one set of held-out frames, with its fidelity."""

    metrics: tuple[MetricChange, ...]
    frames: int
    sequences: int
    fidelity_mm: float     # mean joint distance of the fused poses to fp32's
    budget: TaskBudget

    @property
    def within(self) -> bool:
        return all(m.within for m in self.metrics)

    @property
    def precise(self) -> bool:
        return all(m.precise for m in self.metrics)

    @property
    def answer(self) -> str:
        """"within" (every upper end within its limit), "over" (some lower end over its limit)
        or "undecided" (an interval straddles its limit: too few frames to tell)."""
        if self.within:
            return "within"
        return "over" if any(m.surely_over for m in self.metrics) else "undecided"

    @property
    def fidelity_pct(self) -> float:
        """The distance to fp32's poses relative to fp32's MPJPE (the former budget's measure)."""
        return 100.0 * self.fidelity_mm / self.metric("mpjpe").fp32_mm

    @property
    def worst_share(self) -> float:
        """The largest upper end over its limit: at most 1 within budget; a scalar to rank graphs by."""
        return max(m.upper_pct / m.limit_pct for m in self.metrics)

    def metric(self, name: str) -> MetricChange:
        return next(m for m in self.metrics if m.name == name)

    def to_dict(self) -> dict:
        return {"within": self.within, "answer": self.answer, "precise": self.precise, "frames": self.frames,
                "sequences": self.sequences,
                "fidelity_mm": self.fidelity_mm, "fidelity_pct": self.fidelity_pct,
                "metrics": {m.name: m.to_dict() for m in self.metrics}, "budget": self.budget.to_dict()}

    def table(self) -> list[str]:
        """Markdown rows: metric, fp32, graph, change with its interval, limit, verdict."""
        coverage = round(100 * (2 * self.budget.confidence - 1))
        rows = [f"| metric | fp32 mm | graph mm | change % ({coverage}% interval) | limit % | within |",
                "|---|---:|---:|---|---:|---|"]
        for m in self.metrics:
            noisy = "" if m.precise else " (noisy: more frames)"
            rows.append(f"| {m.name} | {m.fp32_mm:.3f} | {m.value_mm:.3f} | {m.change_pct:+.3f} "
                        f"({m.lower_pct:+.3f} to {m.upper_pct:+.3f}) | +{m.limit_pct:g} | "
                        f"{'yes' if m.within else '**no**'}{noisy} |")
        return rows


def frame_metrics(poses: Sequence[np.ndarray], gt: Sequence[np.ndarray]) -> dict[str, list[np.ndarray]]:
    """Per-frame values of each task metric, per sequence: MPJPE and PA-MPJPE (mean over
    joints at each frame) and jitter (mean over joints of the second difference's norm,
    frames 3..N). Sequences are kept apart: jitter and the bootstrap blocks must not span two."""
    if len(poses) != len(gt) or not poses:
        raise ValueError(f"need one pose array per ground-truth sequence, got {len(poses)} and {len(gt)}")
    return {"mpjpe": [joint_errors(p, g).mean(axis=1) for p, g in zip(poses, gt)],
            "pa_mpjpe": [pa_joint_errors(p, g).mean(axis=1) for p, g in zip(poses, gt)],
            "jitter": [jitter_errors(p).mean(axis=1) for p in poses]}


def block_sums(per_sequence: Sequence[np.ndarray], block: int) -> tuple[np.ndarray, np.ndarray]:
    """(sum, count) of each block of `block` consecutive values, blocks cut per sequence (the
    last one of a sequence may be shorter)."""
    sums, counts = [], []
    for values in per_sequence:
        values = np.asarray(values, dtype=np.float64)
        for start in range(0, len(values), block):
            part = values[start:start + block]
            sums.append(part.sum())
            counts.append(len(part))
    return np.asarray(sums), np.asarray(counts, dtype=np.float64)


def paired_change(graph: Sequence[np.ndarray], fp32: Sequence[np.ndarray], limit_pct: float, name: str,
                  budget: TaskBudget) -> MetricChange:
    """`graph`'s mean over fp32's mean on the same frames, as a % change, with a paired block
    bootstrap of it (module doc)."""
    block = min(budget.block_frames, max(1, sum(len(g) for g in graph) // MIN_BLOCKS))
    g_sums, counts = block_sums(graph, block)
    f_sums, f_counts = block_sums(fp32, block)
    if not np.array_equal(counts, f_counts) or counts.sum() == 0:
        raise ValueError(f"{name}: the graph and fp32 must be measured on the same, non-empty frames")
    value, base = g_sums.sum() / counts.sum(), f_sums.sum() / counts.sum()
    if not base > 0:
        raise ValueError(f"{name}: fp32's value is {base}; a relative budget needs a positive reference")
    rng = np.random.default_rng(budget.seed)
    picks = rng.integers(0, len(counts), size=(budget.resamples, len(counts)))
    draws = 100.0 * (g_sums[picks].sum(axis=1) / f_sums[picks].sum(axis=1) - 1.0)
    tail = 100.0 * (1.0 - budget.confidence)
    lower, upper = np.percentile(draws, [tail, 100.0 - tail])
    return MetricChange(name, float(base), float(value), float(100.0 * (value / base - 1.0)), float(lower),
                        float(upper), float(np.std(draws)), float(limit_pct))


def check_budget(poses: Sequence[np.ndarray], fp32_poses: Sequence[np.ndarray], gt: Sequence[np.ndarray],
                 budget: TaskBudget = TaskBudget()) -> BudgetCheck:
    """The task budget of `poses` (the compressed graph's fused poses, one array per
    continuous sequence) against `fp32_poses` on the same frames with ground truth `gt`."""
    graph, reference = frame_metrics(poses, gt), frame_metrics(fp32_poses, gt)
    metrics = tuple(paired_change(graph[name], reference[name], limit, name, budget)
                    for name, limit in budget.limits.items())
    fidelity = float(np.concatenate([joint_errors(p, f).ravel() for p, f in zip(poses, fp32_poses)]).mean())
    return BudgetCheck(metrics, sum(len(g) for g in gt), len(gt), fidelity, budget)

