"""Where an onnxruntime step spends its time: run with `SessionOptions.enable_profiling` and
aggregate the trace's per-node kernel events by op type and by module group."""
from __future__ import annotations

import json
import os
from collections import defaultdict
from pathlib import Path
from typing import Any, Mapping

import numpy as np

_KERNEL_SUFFIX = "_kernel_time"
# Float ops that static INT8 quantisation replaces (quantize.static.DEFAULT_OP_TYPES), with
# the names ORT gives them after its own fusions.
QUANTISABLE_OPS: frozenset[str] = frozenset({"Conv", "FusedConv", "MatMul", "FusedMatMul", "Gemm", "FusedGemm"})


def summarize_trace(trace_path: str | os.PathLike, node_groups: Mapping[str, str] | None = None) -> dict[str, Any]:
    """ms per step by op type and by module group, from an ORT profiling JSON trace.

    Node names in the trace are the graph's node names (ORT may add fused nodes, e.g.
    `..._token_0` or `FusedConv`, which keep the name of the node they replace as a prefix).
    """
    events = json.loads(Path(trace_path).read_text(encoding="utf-8"))
    runs = [e for e in events if e.get("cat") == "Session" and e.get("name") == "model_run"]
    steps = max(len(runs), 1)
    by_op: dict[str, float] = defaultdict(float)
    by_group: dict[str, float] = defaultdict(float)
    by_provider: dict[str, float] = defaultdict(float)
    node_total = 0.0
    for event in events:
        if event.get("cat") != "Node" or not str(event.get("name", "")).endswith(_KERNEL_SUFFIX):
            continue
        ms = float(event.get("dur", 0)) / 1e3
        args = event.get("args", {})
        node = str(event["name"])[: -len(_KERNEL_SUFFIX)]
        by_op[str(args.get("op_name", "?"))] += ms
        by_provider[str(args.get("provider", "?"))] += ms
        if node_groups is not None:
            by_group[_group_of_node(node, node_groups)] += ms
        node_total += ms
    run_ms = float(np.median([float(e.get("dur", 0)) / 1e3 for e in runs])) if runs else None
    per_step = lambda table: {k: v / steps for k, v in sorted(table.items(), key=lambda kv: -kv[1])}  # noqa: E731
    return {
        "steps": len(runs), "run_ms_median": run_ms, "kernel_ms_per_step": node_total / steps,
        "by_op_type_ms": per_step(by_op), "by_module_ms": per_step(by_group) if node_groups is not None else None,
        "by_provider_ms": per_step(by_provider),
        "int8_speedup_bound": int8_speedup_bound(per_step(by_op)),
    }


def _group_of_node(node: str, node_groups: Mapping[str, str]) -> str:
    if node in node_groups:
        return node_groups[node]
    # ORT-fused nodes are named after the first node they absorb, plus a suffix.
    best = max((k for k in node_groups if node.startswith(k)), key=len, default=None)
    return node_groups[best] if best else "unmapped (ORT-created)"


def int8_speedup_bound(by_op_type_ms: Mapping[str, float]) -> dict[str, float]:
    """Amdahl's bound on an INT8 graph's speed-up over this float profile: only the
    QUANTISABLE_OPS get faster, so even at zero cost for them (and for the Quantize /
    DequantizeLinear pairs they bring) the step takes at least the rest's time."""
    total = float(sum(by_op_type_ms.values()))
    quantisable = float(sum(ms for op, ms in by_op_type_ms.items() if op in QUANTISABLE_OPS))
    rest = total - quantisable
    return {"kernel_ms": total, "quantisable_ms": quantisable, "float_rest_ms": rest,
            "quantisable_share": quantisable / total if total else 0.0,
            "max_speedup": total / rest if rest > 0 else float("inf")}
