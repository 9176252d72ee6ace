"""Where a compressed graph departs from its reference, step by step, states carried.

Both graphs run the same frames, each carrying its own states, with their intermediate
tensors exposed as extra outputs. Tensors are matched by name: quantisation keeps the float
graph's tensor names and inserts `X -> QuantizeLinear -> DequantizeLinear -> X'` after a
quantised activation, so on the compressed side a tensor is read where its consumers read
it (the DequantizeLinear output when there is one), as ONNX Runtime's `qdq_loss_debug`
matches single steps.

For every group (e3dpsm.onnx_groups: the recurrent groups `s5_stageN`, `fusion`, then the
module scopes `stem`, `stages.N`, `attention.N`, `ssm`, `decoder`, ...) and every step:
- output error: relative L2 error ||x' - x|| / ||x|| of the group's boundary tensors (those
  read by another group or leaving the graph), the worst of them;
- added error: output error minus the worst output error of the groups feeding it, a
  rough share of what the group itself adds (a group that amplifies what it receives, such
  as a recurrence, shows added error without adding any);
- quantisation noise (QDQ graphs): ||DQ(Q(x)) - x|| / ||x|| inside the compressed graph for
  each quantised activation, the worst per group; the top tensors are listed by name.
  This is local: it does not depend on what the group received.
Culprits are ranked by quantisation noise where the graph has Q/DQ pairs (groups kept in
float rank last: they add none), otherwise (FP16, dynamic INT8) by mean added error.
Every state gets its relative error per step, and each series is reported at steps 1, 10,
100 and N with whether it grows (median of the last tenth over the median of the second
tenth of the rollout above GROWTH_RATIO).
"""
from __future__ import annotations

import math
import os
import tempfile
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import onnx

from e3dpsm.errors import DataError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.onnx_graph import read_onnx, with_outputs
from e3dpsm.onnx_groups import OTHER, module_scopes, recurrent_groups
from e3dpsm.runtime.session import StepSession

GROWTH_RATIO = 2.0
REPORT_STEPS = (1, 10, 100)
TINY = 1e-12


def relative_l2(got: np.ndarray, ref: np.ndarray) -> float:
    ref64 = ref.astype(np.float64, copy=False)
    denom = float(np.linalg.norm(ref64))
    diff = float(np.linalg.norm(got.astype(np.float64, copy=False) - ref64))
    if not math.isfinite(diff):
        return math.inf
    return diff / denom if denom > TINY else (0.0 if diff <= TINY else math.inf)


def node_groups(model: onnx.ModelProto, meta: GraphMetadata) -> dict[str, str]:
    """Node name -> group name: recurrent groups first, then module scopes, else OTHER."""
    group_of: dict[str, str] = {}
    for group in recurrent_groups(model, meta):
        for node in group.nodes:
            group_of.setdefault(node, group.name)
    for node, scope in module_scopes(model).items():
        if scope != OTHER:
            group_of.setdefault(node, scope)
    return group_of


def _float_tensors(model: onnx.ModelProto) -> set[str]:
    inferred = onnx.shape_inference.infer_shapes(model)
    known = {v.name: v.type.tensor_type.elem_type for v in
             (*inferred.graph.value_info, *inferred.graph.output, *inferred.graph.input)}
    return {name for name, elem in known.items() if elem == onnx.TensorProto.FLOAT}


@dataclass(frozen=True)
class Plan:
    """Which tensors to expose on each side and how they pair up."""

    boundary: dict[str, str]  # reference tensor -> its group (read by another group / graph output)
    model_name: dict[str, str]  # reference tensor -> the compressed graph's tensor to compare with
    qdq: dict[str, tuple[str, str]]  # compressed: float tensor -> (its DQ(Q(x)) tensor, group)
    states: dict[str, str]  # state name -> output tensor name
    feeds: dict[str, str]  # group -> groups feeding it


def make_plan(reference: onnx.ModelProto, model: onnx.ModelProto, meta: GraphMetadata) -> Plan:
    group_of = node_groups(reference, meta)
    producer_group: dict[str, str] = {}
    for node in reference.graph.node:
        for out in node.output:
            producer_group[out] = group_of.get(node.name, OTHER)
    readers: dict[str, set[str]] = defaultdict(set)
    for node in reference.graph.node:
        for inp in node.input:
            if inp in producer_group:
                readers[inp].add(group_of.get(node.name, OTHER))
    graph_outputs = {o.name for o in reference.graph.output}
    float_ref = _float_tensors(reference)
    boundary = {t: g for t, g in producer_group.items()
                if t in float_ref and (t in graph_outputs or readers[t] - {g}) and g != OTHER}
    feeds: dict[str, set[str]] = defaultdict(set)
    for tensor, group in producer_group.items():
        for reader in readers[tensor] - {group}:
            if group != OTHER and reader != OTHER:
                feeds[reader].add(group)

    # On the compressed side: read a tensor after its Q/DQ pair if it has one.
    dq_of: dict[str, str] = {}
    q_out: dict[str, str] = {}
    for node in model.graph.node:
        if node.op_type == "QuantizeLinear":
            q_out[node.output[0]] = node.input[0]
    for node in model.graph.node:
        if node.op_type == "DequantizeLinear" and node.input[0] in q_out:
            dq_of.setdefault(q_out[node.input[0]], node.output[0])
    model_tensors = {o for n in model.graph.node for o in n.output} | {i.name for i in model.graph.input}
    model_name = {t: dq_of.get(t, t) for t in boundary if t in model_tensors}
    if not model_name:
        raise DataError("the two graphs share no tensor names; diagnose needs the compressed graph to come from "
                        "the reference (e3dpsm quantize --model REFERENCE)")
    model_producer = {o: n.name for n in model.graph.node for o in n.output}
    model_group = {}
    for tensor, dq in dq_of.items():
        producer = model_producer.get(tensor, "")
        model_group[tensor] = group_of.get(producer) or producer_group.get(tensor, OTHER)
    qdq = {t: (dq, model_group[t]) for t, dq in dq_of.items() if t in model_producer}
    states = {s.name: s.output_name for s in meta.states}
    return Plan({t: boundary[t] for t in model_name}, model_name, qdq, states, {k: v for k, v in feeds.items()})


def _expose(model: onnx.ModelProto, names: Iterable[str], folder: Path, tag: str) -> Path:
    path = folder / f"{tag}.onnx"
    onnx.save(with_outputs(model, names), str(path))
    return path


@dataclass
class Series:
    name: str
    kind: str  # "group" | "state" | "output"
    errors: np.ndarray  # relative error per step
    added: np.ndarray | None = None
    qdq_noise: float | None = None

    @property
    def growth(self) -> float:
        n = len(self.errors)
        if n < 20:
            return float("nan")
        early = float(np.median(self.errors[n // 10: n // 5]))
        late = float(np.median(self.errors[-max(n // 10, 1):]))
        return late / early if early > TINY else (math.inf if late > TINY else 1.0)

    def to_dict(self) -> dict[str, Any]:
        n = len(self.errors)
        marks = sorted({s for s in (*REPORT_STEPS, n) if s <= n})
        entry: dict[str, Any] = {
            "name": self.name, "kind": self.kind,
            "error_at_step": {str(s): float(self.errors[s - 1]) for s in marks},
            "mean_error": float(np.mean(self.errors)), "growth": self.growth,
            "grows": bool(self.growth > GROWTH_RATIO),
        }
        if self.added is not None:
            entry["mean_added_error"] = float(np.mean(self.added))
        if self.qdq_noise is not None:
            entry["qdq_noise"] = self.qdq_noise
        return entry


def diagnose(reference_path: str | os.PathLike, model_path: str | os.PathLike, frames: Iterable[np.ndarray],
             window_ms: float, *, threads: int | None = None, progress: bool = False) -> dict[str, Any]:
    """Run both graphs over `frames` (float32 [C, H, W]); per-group and per-state errors, ranked."""
    reference = read_onnx(reference_path)
    model = read_onnx(model_path)
    meta = GraphMetadata.from_onnx(reference, source=str(reference_path))
    model_meta = GraphMetadata.from_onnx(model, source=str(model_path))
    if [s.to_metadata() for s in meta.states] != [s.to_metadata() for s in model_meta.states]:
        raise DataError(f"{model_path} and {reference_path} carry different states; they are not the same model")
    plan = make_plan(reference, model, meta)
    qdq_tensors = [name for pair in plan.qdq.items() for name in (pair[0], pair[1][0])]
    with tempfile.TemporaryDirectory(prefix="e3dpsm-diagnose-") as tmp:
        # all_outputs: the exposed tensors come back beside the poses and states.
        ref = StepSession(_expose(reference, plan.boundary, Path(tmp), "reference"), threads=threads, all_outputs=True)
        got = StepSession(_expose(model, [*plan.model_name.values(), *qdq_tensors], Path(tmp), "model"),
                          threads=threads, all_outputs=True)
        ref_state, got_state = ref.init_state(1), got.init_state(1)
        del reference, model
        tensor_err: dict[str, list[float]] = defaultdict(list)
        state_err: dict[str, list[float]] = defaultdict(list)
        output_err: dict[str, list[float]] = defaultdict(list)
        qdq_noise: dict[str, list[float]] = defaultdict(list)
        iterator: Iterable[np.ndarray] = frames
        if progress:
            from tqdm import tqdm

            iterator = tqdm(frames, desc="diagnose", unit="step", leave=False, disable=None)
        for frame in iterator:
            lnes = np.ascontiguousarray(frame[None], dtype=np.float32)
            a, ref_state = ref.step(lnes, ref_state, window_ms)
            b, got_state = got.step(lnes, got_state, window_ms)
            for tensor, other in plan.model_name.items():
                tensor_err[tensor].append(relative_l2(b[other], a[tensor]))
            for name, out in plan.states.items():
                state_err[name].append(relative_l2(b[out], a[out]))
            for name in meta.output_names:
                output_err[name].append(relative_l2(b[name], a[name]))
            for tensor, (dq, _) in plan.qdq.items():
                qdq_noise[tensor].append(relative_l2(b[dq], b[tensor]))
    steps = len(next(iter(state_err.values()), []))
    if not steps:
        raise DataError("no frames to diagnose")
    by_group: dict[str, list[np.ndarray]] = defaultdict(list)
    for tensor, errors in tensor_err.items():
        by_group[plan.boundary[tensor]].append(np.asarray(errors))
    group_out = {g: np.max(np.stack(v), axis=0) for g, v in by_group.items()}
    noise_by_group: dict[str, float] = defaultdict(float)
    for tensor, (_, group) in plan.qdq.items():
        noise_by_group[group] = max(noise_by_group[group], float(np.mean(qdq_noise[tensor])))
    groups = []
    for name, errors in group_out.items():
        upstream = [group_out[g] for g in plan.feeds.get(name, ()) if g in group_out]
        incoming = np.max(np.stack(upstream), axis=0) if upstream else np.zeros(steps)
        groups.append(Series(name, "group", errors, np.maximum(errors - incoming, 0.0),
                             noise_by_group.get(name) if plan.qdq else None))
    rank_by = "qdq_noise" if plan.qdq else "added_error"
    if rank_by == "qdq_noise":
        groups.sort(key=lambda s: (-(s.qdq_noise or 0.0), -float(np.mean(s.added))))
    else:
        groups.sort(key=lambda s: -float(np.mean(s.added)))
    states = [Series(n, "state", np.asarray(v)) for n, v in state_err.items()]
    outputs = [Series(n, "output", np.asarray(v)) for n, v in output_err.items()]
    top_noise = sorted(((float(np.mean(v)), t, plan.qdq[t][1]) for t, v in qdq_noise.items()), reverse=True)[:10]
    return {
        "steps": steps, "window_ms": window_ms,
        "matched_tensors": len(plan.model_name), "quantised_activations": len(plan.qdq),
        "ranked_by": rank_by,
        "culprits": [g.name for g in groups],
        "groups": [g.to_dict() for g in groups],
        "states": [s.to_dict() for s in states],
        "outputs": [o.to_dict() for o in outputs],
        "noisiest_tensors": [{"tensor": t, "group": g, "qdq_noise": v} for v, t, g in top_noise],
        "_curves": {"group": {g.name: g.errors for g in groups}, "state": {s.name: s.errors for s in states}},
    }


def diagnosis_figure(result: dict[str, Any], top: int = 6) -> Any:
    """The top `top` culprit groups' output error (left) and the `top` states with the largest
    final error (right), per step on a log scale; a matplotlib Figure, closed by the caller."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), constrained_layout=True)
    curves = result["_curves"]
    for ax, kind, names in ((axes[0], "group", result["culprits"][:top]),
                            (axes[1], "state", sorted(curves["state"], key=lambda n: -curves["state"][n][-1])[:top])):
        for name in names:
            ax.plot(np.maximum(curves[kind][name], TINY), lw=1.0, label=name)
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_ylabel("relative L2 error")
        ax.set_title("top culprit groups (output error)" if kind == "group" else "states")
        ax.legend(fontsize=7)
    return fig


def plot_diagnosis(result: dict[str, Any], path: Any, top: int = 6) -> None:
    import matplotlib.pyplot as plt

    fig = diagnosis_figure(result, top)
    try:
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)


def markdown(result: dict[str, Any], title: str) -> str:
    marks = list(result["groups"][0]["error_at_step"]) if result["groups"] else []
    lines = [f"# {title}", "", f"{result['steps']} steps at {result['window_ms']:g} ms, both graphs carrying their own "
             f"states; {result['matched_tensors']} boundary tensors matched, {result['quantised_activations']} "
             "quantised activations.", "",
             f"## Culprits (ranked by {result['ranked_by'].replace('_', ' ')})", "",
             "| rank | group | added | " + " | ".join(f"step {m}" for m in marks) + " | QDQ noise | grows |",
             "|---:|---|---:|" + "---:|" * len(marks) + "---:|---|"]
    for rank, g in enumerate(result["groups"], 1):
        noise = f"{g['qdq_noise']:.2e}" if g.get("qdq_noise") is not None else "-"
        lines.append(f"| {rank} | {g['name']} | {g['mean_added_error']:.2e} | "
                     + " | ".join(f"{g['error_at_step'][m]:.2e}" for m in marks)
                     + f" | {noise} | {'yes' if g['grows'] else 'no'} (x{g['growth']:.2f}) |")
    lines += ["", "## States", "", "| state | " + " | ".join(f"step {m}" for m in marks) + " | grows |",
              "|---|" + "---:|" * len(marks) + "---|"]
    for s in result["states"]:
        lines.append(f"| {s['name']} | " + " | ".join(f"{s['error_at_step'][m]:.2e}" for m in marks)
                     + f" | {'yes' if s['grows'] else 'no'} (x{s['growth']:.2f}) |")
    if result["noisiest_tensors"]:
        lines += ["", "## Noisiest quantised activations", "", "| tensor | group | QDQ noise |", "|---|---|---:|"]
        lines += [f"| `{t['tensor']}` | {t['group']} | {t['qdq_noise']:.2e} |" for t in result["noisiest_tensors"]]
    return "\n".join(lines) + "\n"
