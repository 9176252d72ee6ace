"""Write a validation result: Markdown and CSV tables, the JSON report, one plot."""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

from e3dpsm.joints import JOINT_NAMES
from e3dpsm.utils.io import atomic_path, write_json_atomic, write_text_atomic
from e3dpsm.validation.validate import ValidationResult

COLUMNS: tuple[tuple[str, str], ...] = (
    ("variant", "variant"), ("mpjpe_mm", "MPJPE"), ("pa_mpjpe_mm", "PA-MPJPE"), ("e_smooth_mm", "e_smooth"),
    ("occluded_mpjpe_mm", "MPJPE occluded"), ("delta_mpjpe_mm", "dMPJPE"), ("delta_mpjpe_pct", "dMPJPE %"),
    ("delta_pa_mpjpe_mm", "dPA-MPJPE"), ("delta_e_smooth_mm", "de_smooth"),
    ("deviation_from_reference_mm", "dist. to ref."),
)


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "n/a" if math.isnan(value) else f"{value:.3f}"
    return str(value)


def markdown_table(result: ValidationResult) -> str:
    lines = [
        f"Reference: {result.reference}; {result.frames} frames of {len(result.sequences)} sequences; "
        "all figures in mm (differences: variant minus reference).", "",
        "| " + " | ".join(title for _, title in COLUMNS) + " |",
        "|" + "|".join("---" for _ in COLUMNS) + "|",
    ]
    for row in result.rows:
        lines.append("| " + " | ".join(_fmt(row[key]) for key, _ in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def csv_table(result: ValidationResult) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow([key for key, _ in COLUMNS] + [f"mpjpe_{j}" for j in JOINT_NAMES])
    for row in result.rows:
        writer.writerow([row[key] for key, _ in COLUMNS] + result.per_joint[row["variant"]])
    return buffer.getvalue()


def plot(result: ValidationResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4.5), gridspec_kw={"width_ratios": [1, 2]})
    labels = [r["variant"] for r in result.rows]
    left.bar(range(len(labels)), [r["mpjpe_mm"] for r in result.rows], color="tab:blue")
    left.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=8)
    left.set_ylabel("MPJPE (mm)")
    left.set_title("MPJPE per variant")
    for label, values in result.per_joint.items():
        right.plot(range(len(JOINT_NAMES)), values, marker="o", ms=3, label=label)
    right.set_xticks(range(len(JOINT_NAMES)), JOINT_NAMES, rotation=45, ha="right", fontsize=8)
    right.set_ylabel("MPJPE (mm)")
    right.set_title("per joint")
    right.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def write_outputs(result: ValidationResult, out: Path, header: dict[str, Any]) -> None:
    write_text_atomic(out / "validation.md", markdown_table(result))
    write_text_atomic(out / "validation.csv", csv_table(result))
    plot(result, out / "validation.png")
    write_json_atomic(out / "report.json", {**header, **result.to_dict()})
