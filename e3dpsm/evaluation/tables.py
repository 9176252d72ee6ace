"""Markdown tables of evaluation results, written by hand (no `tabulate` dependency)."""
from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

from e3dpsm.evaluation.core import METRICS

_HEADERS = {"mpjpe": "MPJPE", "pa_mpjpe": "PA-MPJPE", "e_smooth": "e_smooth",
            "mpjpe_occluded": "MPJPE occl.", "pa_mpjpe_occluded": "PA-MPJPE occl.", "frames": "frames"}


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return "n/a" if math.isnan(value) else f"{value:.2f}"
    return str(value)


def markdown_table(rows: Mapping[str, Mapping[str, Any]], columns: Sequence[str], first: str) -> str:
    """One Markdown table: a row per key of `rows`, the given columns (mm)."""
    head = [first] + [_HEADERS.get(c, c) for c in columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["---:"] * len(columns)) + "|"]
    for name, row in rows.items():
        lines.append("| " + " | ".join([name] + [_cell(row.get(c, float("nan"))) for c in columns]) + " |")
    return "\n".join(lines) + "\n"


def results_markdown(results: Mapping[str, Any], title: str) -> str:
    """The report of one evaluation: totals, per action, per joint, per sequence."""
    parts = [f"# {title}\n\n", "All figures in mm (e_smooth: mm per frame). Totals: unweighted mean of the "
             "per-action means; occl.: joints with visible == 0 only.\n\n",
             "## Totals\n\n", markdown_table({"total": results["totals"],
                                            "frame-weighted": results["frame_weighted"]}, METRICS, "set"),
             "\n## Per action\n\n", markdown_table(results["per_action"], (*METRICS, "frames"), "action"),
             "\n## Per joint\n\n", markdown_table(results["per_joint"], ("mpjpe", "pa_mpjpe", "e_smooth", "mpjpe_occluded"), "joint"),
             "\n## Per sequence\n\n", markdown_table(results["per_sequence"], (*METRICS, "frames"), "sequence"),
             "\n## MPJPE along the sequences (tenths of each sequence)\n\n",
             markdown_table({f"{c:.2f}": {"mpjpe": m} for c, m in zip(results["error_over_time"]["bin_centres"],
                                                                    results["error_over_time"]["mpjpe"])},
                            ("mpjpe",), "position")]
    return "".join(parts)
