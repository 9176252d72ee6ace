"""`e3dpsm convert litert --quantize int8 --data PREP`: an INT8 `.tflite` through
ai-edge-quantizer's static-range recipe applied to the fp32 `.tflite` litert-torch writes.

litert-torch lowers only the 8-bit patterns its own PT2E quantizer annotates, and that
quantizer filters by module type and name alone (docs/edge.md), so the 8 bits are placed on
the flatbuffer instead, by operator scope (ai-edge-quantizer names an operator by its output
tensors, which litert-torch names by the module path: `<module>.<Class>_<attribute>/...`):

- The convolutions and fully connected layers of the feature extractor take 8 bits: weights
  symmetric per output channel, activations asymmetric per tensor, ranges from the same
  calibration `e3dpsm quantize` and the INT8 `.pte` use (frames of the `train` split, each
  with the states a continuous fp32 rollout carried into it). XNNPACK runs them as QS8
  kernels; every other operator stays float, as in the `.pte` (export/executorch_int8.py).
- Kept float, as there: the S5 layers' projections (the recurrence), the pose heads, the
  embedding of the fused-pose state and the Kalman fusion.
- The return-to-float search of the `.pte` (quantize/place.greedy_groups) on the `val` split,
  each trial a real `.tflite` run by LiteRT's interpreter (quantising takes a second); the
  artifact is then judged on `test`, which neither the calibration nor the search saw.
"""
from __future__ import annotations

import copy
import os
import re
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
import torch

from e3dpsm.budget import BudgetCheck
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.export.edge_int8 import (EdgeInt8Options, Narrowing, calibration_set, check_artifact, fp32_reference,
                                     held_out_set, narrow_float_groups, search_float_groups, search_record,
                                     search_set)
from e3dpsm.export.executorch_int8 import KEEP_FLOAT_TYPES, search_groups
from e3dpsm.export.litert_export import LiteRTOptions, LiteRTResult, embed_contract, litert_content, write_litert
from e3dpsm.models import E3DPSM
from e3dpsm.quantize.calibration import CalibrationSet
from e3dpsm.quantize.holdout import HeldOut, open_stepper
from e3dpsm.quantize.place import Placement
from e3dpsm.utils.extras import require


QUANTISED_OPERATORS: tuple[str, ...] = ("CONV_2D", "FULLY_CONNECTED")
SIGNATURE = "serving_default"  # litert-torch's one signature
SEARCH_RUNTIME = "LiteRT (XNNPACK)"
# The step graph's own scope: what a module called from the step (not from another module) sits under.
_STEP_SCOPE = "e3dpsm.export.wrapper.StepGraph_step/"
# Operators kept float whatever their group (scope pattern, why). The S5 layer is not called
# as a module in the step (its `step` method is), so its projections sit under the step graph.
FLOAT_RULES: tuple[tuple[str, str], ...] = (
    (r"e3dpsm\.layers\.products\.Projection_", "S5 input drive and readouts (the recurrence)"),
    (r"Linear_direct_head|Linear_delta_head|serving_default_pose\w*_output", "pose heads (mm outputs)"),
    (r"Sequential_pose_embed", "embedding of the fused-pose state"),
)


def _scope_name(module: torch.nn.Module, attribute: str) -> str:
    return re.escape(f"{type(module).__module__}.{type(module).__name__}_{attribute}") + r"(?=[/;]|$)"


def group_patterns(model: E3DPSM) -> list[tuple[str, str]]:
    """(group, scope pattern) for each of the search's groups (executorch_int8.search_groups:
    the stem, each stage, each attention layer, the SSM blocks' feed-forwards, the decoder). A
    container that is never called (the SSM blocks' dict) is named by its members' called
    children, which the converter places under the step graph itself."""
    groups = []
    for path, _ in search_groups(model):
        module = model.get_submodule(path.removeprefix("model."))
        attribute = path.rsplit(".", 1)[1]
        if isinstance(module, torch.nn.ModuleDict):
            children = {(type(child).__module__, type(child).__name__, name): child
                        for member in module.values() for name, child in member.named_children()
                        if not isinstance(child, KEEP_FLOAT_TYPES)
                        and any(isinstance(m, (torch.nn.Conv2d, torch.nn.Linear)) for m in child.modules())}
            pattern = "|".join(re.escape(_STEP_SCOPE) + _scope_name(child, name)
                               for (_, _, name), child in sorted(children.items(), key=lambda kv: kv[0]))
        else:
            pattern = _scope_name(module, attribute)
        groups.append((path, pattern))
    return groups


class MacOperator(NamedTuple):
    name: str                  # CONV_2D or FULLY_CONNECTED
    scope: str                 # as ai-edge-quantizer matches its recipe against it
    tensors: tuple[str, ...]   # the activations the recipe quantises around it (input, outputs)
    weights: int               # elements of its weight tensor


def _mac_operators(content: bytes) -> list[MacOperator]:
    """Every QUANTISED_OPERATORS operator of the flatbuffer, in graph order."""
    from ai_edge_quantizer.utils import tfl_flatbuffer_utils as tfl

    model = tfl.read_model(bytearray(content))
    graph = model.subgraphs[0]
    found = []
    for op in graph.operators:
        code = model.operatorCodes[op.opcodeIndex]
        name = tfl.TFL_OP_CODE_TO_NAME.get(max(code.builtinCode, code.deprecatedBuiltinCode))
        if name in QUANTISED_OPERATORS:
            tensors = tuple(graph.tensors[i].name.decode() for i in (op.inputs[0], *op.outputs))
            weights = int(np.prod(graph.tensors[op.inputs[1]].shape))
            found.append(MacOperator(name, tfl.get_op_scope(op, graph.tensors), tensors, weights))
    return found


def operator_units(content: bytes, groups: Sequence[tuple[str, str]], group: str) -> list[tuple[str, str]]:
    """(label, pattern) of each MAC operator of `group`, largest weights first: the units the
    narrowing pass returns to 8 bits one at a time (edge_int8.narrow_float_groups). A label is
    the group, the operator's place in the group (graph order), its type and the module path
    below the group that litert-torch named its output after
    (`model.attention.3/3:fully_connected(ff.proj_in)`); the pattern matches that operator's
    scope alone."""
    pattern = dict(groups)[group]
    members = [op for op in _mac_operators(content) if _place(op.scope, groups) == ("group", group)]
    units = []
    for index, op in enumerate(members):
        first = op.tensors[1].split(";")[0]
        found = re.search(pattern, first)
        below = first[found.end():].strip("/").split("/") if found else []
        path = ".".join(part.rsplit(".", 1)[-1].split("_", 1)[-1] for part in below if part)
        label = f"{group}/{index}:{op.name.lower()}" + (f"({path})" if path else "")
        units.append((op.weights, index, label, "^" + re.escape(op.scope) + "$"))
    return [(label, unit) for _, _, label, unit in sorted(units, key=lambda u: (-u[0], u[1]))]


def mac_op_scopes(content: bytes) -> list[tuple[str, str]]:
    """(operator, scope) of every QUANTISED_OPERATORS operator of the flatbuffer."""
    return [(op.name, op.scope) for op in _mac_operators(content)]


def _place(scope: str, groups: Sequence[tuple[str, str]]) -> tuple[str, str | None]:
    """("rule", why) when a FLOAT_RULES rule keeps the operator float, ("group", name) for the
    one group that holds it, ("none", None) for neither. Two groups claiming one operator is a
    naming clash: ConfigError."""
    rule = next((why for pattern, why in FLOAT_RULES if re.search(pattern, scope)), None)
    if rule is not None:
        return "rule", rule
    owners = [name for name, pattern in groups if re.search(pattern, scope)]
    if len(owners) > 1:
        raise ConfigError(f"operator scope {scope[:200]!r} matches groups {owners}: the group patterns overlap")
    return ("group", owners[0]) if owners else ("none", None)


def classify(scopes: Sequence[tuple[str, str]], groups: Sequence[tuple[str, str]]) -> dict[str, Any]:
    """Where each MAC operator falls: float by a FLOAT_RULES rule, in exactly one group, or in
    none (left float: a scope this module does not know, reported)."""
    by_group: dict[str, int] = {name: 0 for name, _ in groups}
    by_rule: dict[str, int] = {why: 0 for _, why in FLOAT_RULES}
    unmatched: list[str] = []
    for _, scope in scopes:
        kind, owner = _place(scope, groups)
        if kind == "rule":
            by_rule[owner] += 1
        elif kind == "group":
            by_group[owner] += 1
        else:
            unmatched.append(scope[:300])
    return {"int8_candidates_by_group": by_group, "float_by_rule": by_rule, "unmatched_float": unmatched}


def _recipe(content: bytes, groups: Sequence[tuple[str, str]], keep_float: Sequence[str] = ()) -> Any:
    """ai-edge-quantizer set up for the groups not in `keep_float` in 8 bits, the FLOAT_RULES
    operators float; None when no group is left to quantise."""
    from ai_edge_quantizer import qtyping, quantizer
    from ai_edge_quantizer.algorithm_manager import AlgorithmName

    quantised = "|".join(f"(?:{pattern})" for name, pattern in groups if name not in keep_float)
    if not quantised:
        return None
    engine = quantizer.Quantizer(bytearray(content))
    for operator in QUANTISED_OPERATORS:
        op = qtyping.TFLOperationName(operator)
        engine.add_static_config(quantised, op, activation_num_bits=8, weight_num_bits=8,
                                 weight_granularity=qtyping.QuantGranularity.CHANNELWISE)
        for pattern, _ in FLOAT_RULES:  # the last matching config wins
            engine.update_quantization_recipe(pattern, op, algorithm_key=AlgorithmName.NO_QUANTIZE)
    return engine


def quantised_content(float_content: bytes, qsvs: dict[str, Any], groups: Sequence[tuple[str, str]],
                      keep_float: Sequence[str] = ()) -> bytes:
    """The flatbuffer with the groups not in `keep_float` in 8 bits (module doc)."""
    engine = _recipe(float_content, groups, keep_float)
    if engine is None:
        return bytes(float_content)
    try:
        # A copy per trial: the quantizer writes derived ranges into the dict it is given for
        # some operators (same-as-input scales), which must not leak into the next trial.
        return bytes(engine.quantize(copy.deepcopy(qsvs), enable_progress_bar=False,
                                     enable_progress_report=False).quantized_model)
    except (ValueError, RuntimeError, KeyError) as exc:  # the quantizer's own refusals, one line each
        raise DataError(f"ai-edge-quantizer could not quantise the model: {str(exc).splitlines()[0][:300]}") from exc


def quantised_activations(content: bytes, groups: Sequence[tuple[str, str]]) -> list[str]:
    """Names of the activations a group's operators read and write (the tensors the 8-bit
    recipe quantises: each quantised operator is wrapped in QUANTIZE / DEQUANTIZE)."""
    names = [tensor for op in _mac_operators(content) if _place(op.scope, groups)[0] == "group"
             for tensor in op.tensors]
    return list(dict.fromkeys(names))


def choose_ranges(content: bytes, qsvs: dict[str, Any], names: Sequence[str], feeds: Sequence[dict[str, np.ndarray]],
                  threads: int | None, rule: str = "mse") -> dict[str, Any]:
    """Set the ranges of `names` in `qsvs` from the calibration values themselves (returns a
    summary). ai-edge-quantizer's calibration keeps a moving average of each batch's min and
    max (factor 0.95), not the extremes, so both rules first find the true min and max:
    "minmax" keeps them (every outlier in range); "mse" picks, from a histogram of the values
    on that range, the range of least expected squared quantisation error (quantize/ranges.py:
    min-max, percentiles, narrower ranges), as `quantize --calibration mse` and PT2E's
    histogram observer do."""
    from ai_edge_litert.interpreter import Interpreter

    from e3dpsm.quantize.ranges import HISTOGRAM_BINS, Histogram, choose_range, with_zero

    interpreter = Interpreter(model_content=bytes(content), num_threads=threads or 1,
                              experimental_preserve_all_tensors=True)
    runner = interpreter.get_signature_runner(SIGNATURE)
    index = {d["name"]: d["index"] for d in interpreter.get_tensor_details()}
    wanted = [n for n in names if n in qsvs and n in index]
    low = {n: np.inf for n in wanted}
    high = {n: -np.inf for n in wanted}
    for feed in feeds:
        runner(**feed)
        for n in wanted:
            values = interpreter.get_tensor(index[n])
            low[n], high[n] = min(low[n], float(values.min())), max(high[n], float(values.max()))
    bounds = {n: with_zero(low[n], high[n]) for n in wanted}
    if rule == "mse":
        counts = {n: np.zeros(HISTOGRAM_BINS, np.int64) for n in wanted}
        for feed in feeds:  # a second pass: the histograms need the true extremes first
            runner(**feed)
            for n in wanted:
                if bounds[n][1] > bounds[n][0]:
                    counts[n] += np.histogram(interpreter.get_tensor(index[n]).ravel(), HISTOGRAM_BINS, bounds[n])[0]
        chosen = {n: choose_range(Histogram(counts[n], *bounds[n])) for n in wanted}
        ranges = {n: (c.low, c.high) for n, c in chosen.items()}
        narrowed = sum(c.kind != "minmax" for c in chosen.values())
    else:
        ranges, narrowed = bounds, 0
    for n, (lo, hi) in ranges.items():
        qsvs[n] = {**qsvs[n], "min": np.full_like(qsvs[n]["min"], lo), "max": np.full_like(qsvs[n]["max"], hi)}
    return {"rule": rule, "tensors": len(wanted), "narrowed": narrowed}


def calibrate(float_content: bytes, calibration: CalibrationSet, groups: Sequence[tuple[str, str]],
              threads: int | None, rule: str = "mse") -> tuple[dict[str, Any], dict[str, Any], float]:
    """(ranges of every tensor the full 8-bit recipe reads, how they were chosen, seconds):
    once, before any trial. ai-edge-quantizer's calibration, then choose_ranges by `rule`
    ("mse" or "minmax") for the activations the quantised operators read and write."""
    if rule not in ("mse", "minmax"):
        raise ValueError(f"range rule must be 'mse' or 'minmax', got {rule!r}")
    started = time.perf_counter()
    engine = _recipe(float_content, groups)  # every trial's recipe is a part of this one
    feeds = [{k: np.ascontiguousarray(v) for k, v in f.items()} for f in calibration.feeds]
    try:
        qsvs = engine.calibrate({SIGNATURE: feeds}, num_threads=threads or 1)
    except (ValueError, RuntimeError, KeyError) as exc:  # e.g. feeds named for another model's signature
        raise DataError(f"ai-edge-quantizer could not calibrate the model: {str(exc).splitlines()[0][:300]}") from exc
    chosen = choose_ranges(float_content, qsvs, quantised_activations(float_content, groups), feeds, threads, rule)
    return qsvs, chosen, time.perf_counter() - started


def search_keep_float(model: E3DPSM, quantise: Callable[[Sequence[str]], bytes], search: HeldOut,
                      options: EdgeInt8Options, groups: Sequence[tuple[str, str]], work: Path,
                      litert: LiteRTOptions) -> Placement:
    """Which groups stay float for the artifact to meet the budget on `search`:
    edge_int8.search_float_groups over the groups, each trial a quantised flatbuffer run by
    LiteRT's interpreter, states carried."""
    trial = _trial_opener(model, quantise, work, litert, options)
    return search_float_groups([name for name, _ in groups], trial, search, options, SEARCH_RUNTIME)


def narrow_keep_float(model: E3DPSM, float_content: bytes, qsvs: dict[str, Any], groups: Sequence[tuple[str, str]],
                      kept: Sequence[str], search: HeldOut, options: EdgeInt8Options, work: Path,
                      litert: LiteRTOptions) -> tuple[list[tuple[str, str]], Narrowing]:
    """The kept groups narrowed to the operators that need float (edge_int8.narrow_float_groups
    over operator_units). litert-torch fuses the linears of a deformable block that read the
    same input into one FULLY_CONNECTED with one per-tensor output range (the sampling offsets
    beside the attention weights): that operator may need float where the block's feed-forward,
    most of its weights, does not. Returns (the groups with each kept group replaced by its
    units, the narrowing)."""
    units = {group: operator_units(float_content, groups, group) for group in kept}
    split = {group: found for group, found in units.items() if len(found) > 1}  # one operator: the group is the unit
    fine = [(name, pattern) for name, pattern in groups if name not in split] + [u for g in split for u in split[g]]

    def quantise(floats: Sequence[str]) -> bytes:
        return quantised_content(float_content, qsvs, fine, floats)

    return fine, narrow_float_groups(kept, {g: [label for label, _ in us] for g, us in units.items()},
                                     _trial_opener(model, quantise, work, litert, options), search, options,
                                     SEARCH_RUNTIME)


def _trial_opener(model: E3DPSM, quantise: Callable[[Sequence[str]], bytes], work: Path, litert: LiteRTOptions,
                  options: EdgeInt8Options) -> Callable[[Sequence[str]], Any]:
    """trial(floats): a stepper of the flatbuffer `quantise(floats)` on LiteRT."""
    trial_path = work / "trial.tflite"

    def trial(floats: Sequence[str]) -> Any:
        trial_path.write_bytes(embed_contract(quantise(floats), model, litert, "int8")[0])
        return open_stepper(trial_path, "litert", options.threads)

    return trial


def convert_litert_int8(model: E3DPSM, data: PreparedData, path: str | os.PathLike, options: EdgeInt8Options,
                        work: Path, litert: LiteRTOptions = LiteRTOptions()) -> tuple[LiteRTResult, BudgetCheck, HeldOut]:
    """Write the INT8 `.tflite` to `path` and judge it: (LiteRTResult with the calibration, the
    groups and the search recorded, the budget check on the held-out split, its frames)."""
    require("ai_edge_quantizer", "to write INT8 .tflite models")
    from absl import logging as absl_logging

    absl_logging.set_verbosity(absl_logging.WARNING)  # ai-edge-quantizer's step-by-step INFO lines
    reference = fp32_reference(model, work)
    calibration = calibration_set(reference, data, options)
    started = time.perf_counter()
    float_content = litert_content(model, litert)
    convert_seconds = time.perf_counter() - started
    groups = group_patterns(model)
    coverage = classify(mac_op_scopes(float_content), groups)
    qsvs, ranges_rule, calibrate_seconds = calibrate(float_content, calibration, groups, options.threads)

    def quantise(keep_float: Sequence[str]) -> bytes:
        return quantised_content(float_content, qsvs, groups, keep_float)

    record: dict[str, Any] = {
        "quantizer": "ai-edge-quantizer static range: int8 weights per channel, int8 activations per tensor",
        "operators": list(QUANTISED_OPERATORS), "groups": dict(groups), "coverage": coverage,
        "float_rules": [why for _, why in FLOAT_RULES],
        "calibration": {"split": options.split, "frames": len(calibration), "state_source": calibration.state_source,
                        "ranges": ranges_rule, "seconds": round(calibration.seconds + calibrate_seconds, 2)},
        "budget": options.budget.to_dict()}
    keep_float: tuple[str, ...] = ()
    search_started = time.perf_counter()
    if options.search_rounds > 0:
        search = search_set(reference, data, options)
        with tempfile.TemporaryDirectory(prefix="e3dpsm-litert-search-", dir=work) as trials:
            placement = search_keep_float(model, quantise, search, options, groups, Path(trials), litert)
            keep_float = placement.float_nodes
            record["search"] = search_record(placement, search, options, SEARCH_RUNTIME)
            if keep_float and options.narrow_trials != 0:  # --narrow-trials 0: the blocks stay float whole
                groups, narrowing = narrow_keep_float(model, float_content, qsvs, groups, keep_float, search,
                                                      options, Path(trials), litert)
                keep_float = tuple(narrowing.floats)
                record["search"].update(narrowing.search_fields(placement.float_nodes))
    record["keep_float"] = list(keep_float)
    record["int8_operators"] = sum(count for group, count in classify(mac_op_scopes(float_content), groups)
                                   ["int8_candidates_by_group"].items() if group not in keep_float)
    started = time.perf_counter()
    content = quantised_content(float_content, qsvs, groups, keep_float)
    seconds = {"convert": round(convert_seconds, 2), "calibrate": round(calibrate_seconds, 2),
               "search": round(started - search_started, 2), "quantize": round(time.perf_counter() - started, 2)}
    result = write_litert(content, model, path, litert, "int8", seconds, record)
    held = held_out_set(reference, data, options)
    return result, check_artifact(path, "litert", held, options), held


__all__ = ["FLOAT_RULES", "QUANTISED_OPERATORS", "classify", "convert_litert_int8", "group_patterns", "mac_op_scopes",
           "narrow_keep_float", "operator_units", "quantised_content"]
