"""QAT ranges that reach the graph: the learned (scale, zero point) of a QAT checkpoint
written into the INT8 graph as they are (`quantize --ranges-from-checkpoint CKPT`).

Both directions use one matching (e3dpsm/training/qat_sites.py): the tensors that get a
QuantizeLinear in the INT8 graph (recurrent groups in float, as `--exclude recurrent`) are
matched by value to PyTorch sites on one step with the same inputs.
- Training (`train --qat`): `qat_plan` exports the model, finds the quantised tensors and
  their sites; each group gets one learned quantiser (training/qat_lsq.py). The checkpoint
  stores them as `qat_ranges` (`QAT_RANGES_FORMAT`): per quantiser its torch sites, the ONNX
  tensors it matched at training time, and the learned float32 scale and U8 zero point.
- Quantising: the graph to quantise is matched again against the checkpoint's model on a
  calibration frame (names of an export need not survive another export), and each matched
  tensor gets its quantiser's scale and zero point through ONNX Runtime's
  TensorQuantOverrides (scale and zero point given: ORT computes nothing). Tensors no
  learned quantiser covers (functional ops with no module: attention scores, softmax) keep
  their calibrated ranges; the report counts both.
"""
from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np
import onnx

from e3dpsm.errors import CheckpointError, ConfigError
from e3dpsm.onnx_graph import with_outputs

from e3dpsm.training.qat_sites import QuantSite

if TYPE_CHECKING:
    import torch

    from e3dpsm.training.qat_sites import QuantGroup

log = logging.getLogger(__name__)

QAT_RANGES_FORMAT = "e3dpsm-qat-ranges/1"
# ONNX Runtime's name for a quantised graph output's producer output (`<name>` + this).
GRAPH_OUTPUT_SUFFIX = "_QuantizeLinear_Input"
WEIGHT_SUFFIX = "_quantized"


def _placeholder_qdq(pre_path: str | os.PathLike, exclude: Sequence[str], op_types: Sequence[str],
                     float_outputs: str = "none") -> onnx.ModelProto:
    """The QDQ graph `pre_path` quantises to with the nodes `exclude` in float and the
    outputs `--float-outputs float_outputs` leaves float without their Q/DQ pair, built
    with placeholder ranges: where the Q/DQ pairs go, not what they hold."""
    from onnxruntime.quantization.calibrate import CalibrationMethod, TensorsData, create_calibrator, save_tensors_data

    from e3dpsm.quantize.outputs import FLOAT_OUTPUTS, dequantised_outputs
    from e3dpsm.quantize.static import StaticConfig, quantize_int8

    with tempfile.TemporaryDirectory(prefix="e3dpsm-qsites-") as work:
        calibrator = create_calibrator(Path(pre_path), list(op_types), augmented_model_path=str(Path(work) / "aug.onnx"))
        # The calibrator's own copy of the graph carries inferred shapes: a tensor without a
        # value_info (the Identity copies graph_groups.isolate_state_reads adds after the
        # pre-pass) is never selected, and quantize_static then fails for want of its range.
        names = calibrator.select_tensors_to_calibrate(calibrator.model)[0]
        del calibrator
        cache = Path(work) / "cache.json"
        save_tensors_data(TensorsData(CalibrationMethod.MinMax, {n: (np.float32(-1), np.float32(1)) for n in names}), cache)
        out = Path(work) / "q.onnx"
        quantize_int8(pre_path, out, StaticConfig(op_types=tuple(op_types)), exclude=exclude, cache=cache)
        qdq = onnx.load(str(out))
    dequantised_outputs(qdq, FLOAT_OUTPUTS[float_outputs], op_types)
    return qdq


def _activations_of(qdq: onnx.ModelProto) -> list[str]:
    inits = {i.name for i in qdq.graph.initializer}
    # A quantised graph output (an S5 state, in the full-integer graph) keeps its name on the
    # DequantizeLinear; its producer's output is renamed `<name>_QuantizeLinear_Input`.
    return sorted({n.input[0].removesuffix(GRAPH_OUTPUT_SUFFIX)
                   for n in qdq.graph.node if n.op_type == "QuantizeLinear" and n.input[0] not in inits})


def _weights_of(qdq: onnx.ModelProto) -> list[str]:
    # ONNX Runtime stores a quantised weight as `<name>_quantized` beside its DequantizeLinear.
    inits = {i.name for i in qdq.graph.initializer}
    return sorted({n.input[0].removesuffix(WEIGHT_SUFFIX) for n in qdq.graph.node
                   if n.op_type == "DequantizeLinear" and n.input[0] in inits and n.input[0].endswith(WEIGHT_SUFFIX)})


def quantised_activations(pre_path: str | os.PathLike, exclude: Sequence[str], op_types: Sequence[str],
                          float_outputs: str = "none") -> list[str]:
    """Activation tensors that get a QuantizeLinear when `pre_path` is quantised with the
    nodes `exclude` in float and `--float-outputs float_outputs`."""
    return _activations_of(_placeholder_qdq(pre_path, exclude, op_types, float_outputs))


def tensor_values(model_path: str | os.PathLike, names: Sequence[str], feed: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    import onnxruntime as ort

    from e3dpsm.runtime.session import exact_arithmetic_options

    model = with_outputs(onnx.load(str(model_path)), names)
    session = ort.InferenceSession(model.SerializeToString(), exact_arithmetic_options(),
                                   providers=["CPUExecutionProvider"])
    return dict(zip(names, session.run(list(names), dict(feed))))


def match_graph(model, pre_path: str | os.PathLike, quantised: Sequence[str],
                feed: Mapping[str, np.ndarray]) -> list["QuantGroup"]:
    """Groups of the graph's quantised tensors and the torch model's sites (qat_sites)."""
    from e3dpsm.training.qat_sites import capture_sites, match_groups

    sites = {k: v for k, v in capture_sites(model, feed).items() if not QuantSite.parse(k).is_weight}
    return match_groups(tensor_values(pre_path, quantised, feed), sites)


def match_weights(model, pre_path: str | os.PathLike, weights: Sequence[str],
                  feed: Mapping[str, np.ndarray]) -> list["QuantGroup"]:
    """Groups of the graph's quantised weight initializers and the `Projection` weights that
    hold the same numbers (sites `name:weight`): which products the graph rounds the weight
    of. A Conv's or Linear's weight is a parameter and needs no matching."""
    from onnx import numpy_helper

    from e3dpsm.training.qat_sites import capture_sites, match_groups

    wanted = set(weights)
    values = {i.name: numpy_helper.to_array(i) for i in onnx.load(str(pre_path)).graph.initializer if i.name in wanted}
    sites = {k: v for k, v in capture_sites(model, feed).items() if QuantSite.parse(k).is_weight}
    return match_groups(values, sites)


def probe_feed(model, steps: int = 3, seed: int = 0) -> dict[str, np.ndarray]:
    """An ONNX-style feed for matching: sparse random LNES frames, states carried `steps`
    steps from the initial ones (so no state is trivially zero)."""
    import torch

    cfg = model.config
    rng = np.random.default_rng(seed)
    window = float(cfg.train_window_ms)
    state = model.init_state(1)

    def frame() -> np.ndarray:
        shape = (1, cfg.in_channels, cfg.height, cfg.width)
        return ((rng.random(shape) < 0.05) * rng.random(shape)).astype(np.float32)

    was_training = model.training
    model.eval()
    with torch.no_grad():
        for _ in range(steps):
            _, state = model.step(torch.from_numpy(frame()), state, torch.tensor([window]))
    model.train(was_training)
    return {"lnes": frame(), "window_ms": np.array([window], np.float32),
            **{s.input_name: state[s.name].numpy() for s in model.state_spec()}}


def qat_plan(model, feed: Mapping[str, np.ndarray] | None = None, full_integer: bool = False,
             float_outputs: str = "none") -> list["QuantGroup"]:
    """The quantisers a QAT run trains: the model exported and pre-processed as `quantize`
    does, its INT8 graph's quantised tensors (recurrent groups in float, unless
    `full_integer`: the `--exclude none` graph; the outputs `quantize --float-outputs
    float_outputs` leaves float are not among them), matched to sites; and the groups of
    quantised weights matched to `Projection` weights (`QuantGroup.is_weight`)."""

    from e3dpsm.export import export_step
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.quantize.graph_groups import recurrent_groups
    from e3dpsm.quantize.static import DEFAULT_OP_TYPES, preprocess

    with tempfile.TemporaryDirectory(prefix="e3dpsm-qat-plan-") as work:
        raw, pre = Path(work) / "step.onnx", Path(work) / "pre.onnx"
        export_step(model, raw)
        preprocess(raw, pre)
        pre_model = onnx.load(str(pre))
        keep = [] if full_integer else [n for g in recurrent_groups(pre_model, GraphMetadata.from_onnx(pre_model))
                                        for n in g.nodes]
        qdq = _placeholder_qdq(pre, keep, DEFAULT_OP_TYPES, float_outputs)
        quantised = _activations_of(qdq)
        feed = feed or probe_feed(model)
        groups = match_graph(model, pre, quantised, feed)
        weight_groups = match_weights(model, pre, _weights_of(qdq), feed)
    covered = sum(len(g.tensors) for g in groups)
    log.info("QAT: %d learned quantisers cover %d of the %d tensors the INT8 graph quantises; %d projection "
             "weights rounded as the graph rounds them", len(groups), covered, len(quantised), len(weight_groups))
    return groups + weight_groups


def ranges_payload(quantizers: Sequence[tuple["QuantGroup", float, int]], float_outputs: str = "none",
                   weight_bits: int = 8) -> dict[str, Any]:
    """The checkpoint's `qat_ranges` entry. `float_outputs`: the `quantize --float-outputs`
    graph training simulated (its default under `--ranges-from-checkpoint`); `weight_bits`:
    the weights' bits it simulated (8, or 7 for a target without int8 dot-product units)."""
    return {"format": QAT_RANGES_FORMAT, "activation_type": "QUInt8", "float_outputs": float_outputs,
            "weight_bits": int(weight_bits),
            "quantizers": [{"sites": list(g.sites), "tensors": list(g.tensors), "scale": float(s), "zero_point": int(z)}
                           for g, s, z in quantizers]}


def read_ranges(payload: Mapping[str, Any], source: str) -> list[dict[str, Any]]:
    ranges = payload.get("qat_ranges")
    if not ranges:
        raise CheckpointError(f"{source} carries no learned QAT ranges (qat_ranges); fine-tune it with "
                              "`e3dpsm train --init-from CKPT --qat`, or quantise without --ranges-from-checkpoint")
    if ranges.get("format") != QAT_RANGES_FORMAT:
        raise CheckpointError(f"{source}: qat_ranges format {ranges.get('format')!r} is not {QAT_RANGES_FORMAT!r}")
    return list(ranges["quantizers"])


def simulated_weight_bits(payload: Mapping[str, Any]) -> int:
    """The weights' bits a QAT checkpoint's training simulated: 8 for checkpoints that
    predate the record."""
    return int((payload.get("qat_ranges") or {}).get("weight_bits", 8))


def simulated_float_outputs(payload: Mapping[str, Any]) -> str:
    """The `--float-outputs` graph a QAT checkpoint's training simulated: "none" (every Q/DQ
    pair) for checkpoints that predate the choice."""
    return str((payload.get("qat_ranges") or {}).get("float_outputs", "none"))


def learned_with_weights_frozen(payload: Mapping[str, Any]) -> bool:
    """Whether a checkpoint learned its ranges alone (`distill --qat-ranges-only`): its weights,
    and so its fp32 graph, are those of the checkpoint it was tuned from."""
    return bool((payload.get("distill_config") or {}).get("qat_ranges_only", False))


def unknown_sites(model: torch.nn.Module, learned: Sequence[Mapping[str, Any]]) -> list[str]:
    """Sites of the learned quantisers whose module the model does not have: a checkpoint
    trained before a module was renamed or restructured. Their tensors cannot be matched and
    keep calibrated ranges."""
    modules = dict(model.named_modules())
    return sorted({site for q in learned for site in q["sites"] if QuantSite.parse(site).module not in modules})


def learned_overrides(checkpoint: str | os.PathLike, pre_path: str | os.PathLike,
                      quantised: Sequence[str]) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    """{tensor: {"scale", "zero_point"}} for the graph's quantised tensors a learned
    quantiser of `checkpoint` covers, and a report block (the weights' bits training simulated,
    whether the weights were frozen, stale sites; `coverage_in_graph` adds the counts once the
    graph is written).

    Matched on `probe_feed`, as `qat_plan` matched at training time, not on a stream's first
    frame: with the initial states, values coincide (a state output equals the input
    projection it starts from, the fusion's previous pose is all zeros and matches nothing),
    so a tensor took another site's range or none."""
    from e3dpsm.checkpoint import load_checkpoint

    model, payload = load_checkpoint(checkpoint)
    learned = read_ranges(payload, str(checkpoint))
    by_site = {site: q for q in learned for site in q["sites"]}
    stale = unknown_sites(model, learned)
    if stale:
        log.warning("%s: %d sites of its learned ranges name modules this version of the model does not have "
                    "(%s%s); tensors matched only through them keep calibrated ranges: repeat the QAT fine-tune "
                    "with this version", checkpoint, len(stale), ", ".join(stale[:3]), ", ..." if len(stale) > 3 else "")
    groups = match_graph(model, pre_path, quantised, probe_feed(model))
    if not groups:
        raise ConfigError(f"no tensor of the graph matches {checkpoint}'s model: quantise the graph exported "
                          "from that checkpoint")
    overrides: dict[str, dict[str, Any]] = {}
    for group in groups:
        hit = next((by_site[s] for s in group.sites if s in by_site), None)
        if hit is not None:
            for tensor in group.tensors:
                overrides[tensor] = {"scale": float(hit["scale"]), "zero_point": int(hit["zero_point"])}
    report = {"checkpoint": str(checkpoint), "trained_weight_bits": simulated_weight_bits(payload),
              "weights_frozen": learned_with_weights_frozen(payload), "unknown_sites": stale,
              "float_outputs": simulated_float_outputs(payload)}
    log.info("QAT ranges: %d of the %d tensors a graph of this model may quantise have learned ranges",
             len(overrides), len(quantised))
    return overrides, report


def coverage_in_graph(report: dict[str, Any], model: onnx.ModelProto, learned: Mapping[str, Any]) -> None:
    """Count, in place, the learned and calibrated ranges over the activations the written
    graph quantises to 8 bits, and apart its 16-bit ones. Counted on the written graph, not on
    every tensor a graph of the model may quantise (`learned_overrides`' list): the written one
    quantises fewer (a search's float and 16-bit nodes, the outputs `--float-outputs` leaves
    float)."""
    from e3dpsm.onnx_precision import quantised_activation_bits

    bits = quantised_activation_bits(model)
    eight = {t for t, b in bits.items() if b == 8}
    uncovered = sorted(eight - set(learned))
    report.update(learned_tensors=len(eight) - len(uncovered), calibrated_tensors=len(uncovered),
                  uncovered=uncovered, sixteen_bit_tensors=sum(b == 16 for b in bits.values()))
