"""The profile's verdict: the fastest path on the host it ran on, with its rate.

Chosen on the whole step's median (what an application stepping one stream gets), among the
targets that ran. Targets within `TIE_FRACTION` of the fastest median are named as tied: on
a shared host medians measured side by side still move by a few percent from run to run,
so the verdict does not pretend to rank them.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

TIE_FRACTION = 0.03


def fastest_path(entries: Sequence[Mapping[str, Any]], tie_fraction: float = TIE_FRACTION) -> dict[str, Any] | None:
    """{"fastest", "p50_ms", "hz", "tied", "tie_fraction", "ranking", "not_measured"} from the
    profile's target entries (each with "name", "available" and "latency_ms": {"p50": ms}
    when measured); None when no target was measured. Equal medians keep the targets' order."""
    measured = [e for e in entries if e.get("available") and (e.get("latency_ms") or {}).get("p50") is not None]
    if not measured:
        return None
    ranking = sorted(measured, key=lambda e: e["latency_ms"]["p50"])  # stable: ties keep the listed order
    best = ranking[0]
    best_ms = float(best["latency_ms"]["p50"])
    tied = [e["name"] for e in ranking[1:] if e["latency_ms"]["p50"] <= best_ms * (1 + tie_fraction)]
    return {
        "fastest": best["name"], "p50_ms": best_ms, "hz": 1e3 / best_ms, "tied": tied, "tie_fraction": tie_fraction,
        "ranking": [{"name": e["name"], "p50_ms": float(e["latency_ms"]["p50"]),
                     "hz": 1e3 / float(e["latency_ms"]["p50"])} for e in ranking],
        "not_measured": [e["name"] for e in entries if e not in measured],
    }


def verdict_line(verdict: Mapping[str, Any] | None) -> str:
    """The sentence report.md opens with."""
    if verdict is None:
        return "**No target ran on this host**: see the reasons in the latency table."
    line = (f"**Fastest path on this host: `{verdict['fastest']}`, {verdict['p50_ms']:.3g} ms per pose update "
            f"(p50) = {verdict['hz']:.1f} Hz.**")
    if verdict["tied"]:
        line += (f" Within {100 * verdict['tie_fraction']:.0f}% of it (a tie on a shared host): "
                 + ", ".join(f"`{name}`" for name in verdict["tied"]) + ".")
    return line
