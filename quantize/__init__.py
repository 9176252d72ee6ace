"""Quantisation of the E-3DPSM step graph: INT8 static with state-aware calibration (QDQ,
per-channel), FP16, dynamic INT8; recurrent parts kept in float; the graph judged on the
task metrics (e3dpsm/budget.py) on frames neither calibration nor search saw.

Entry point: `quantize_graph(model, data_dir, out_dir, QuantizeOptions(...))`; CLI
`e3dpsm quantize`; the passes in pipeline.py's order: docs/quantize.md. Importing the package
is light (the CLI reads its options without loading torch): `quantize_graph` loads on use.
"""
from typing import Any

from e3dpsm.budget import BudgetCheck, TaskBudget, check_budget
from e3dpsm.quantize.options import MODES, Advanced, QuantizeOptions, artifact_name

__all__ = ["MODES", "Advanced", "BudgetCheck", "QuantizeOptions", "TaskBudget", "artifact_name", "check_budget",
           "quantize_graph"]


def __getattr__(name: str) -> Any:
    if name == "quantize_graph":
        from e3dpsm.quantize.pipeline import quantize_graph

        return quantize_graph
    raise AttributeError(f"module 'e3dpsm.quantize' has no attribute {name!r}")
