"""AdaRound weight rounding (`quantize --weight-rounding adaround`).

ONNX Runtime rounds each 8-bit weight to the nearest step of its channel's scale. AdaRound
(Nagel et al., "Up or Down? Adaptive Rounding for Post-Training Quantization", ICML 2020)
chooses, element by element, whether to round up or down so that the layer's output on the
calibration frames moves least: with W = s * (floor(W / s) + h), h in [0, 1] a rectified
sigmoid of a free variable V, it minimises

    || (W_soft - W) X ||^2 / N  +  lambda * sum(1 - |2h - 1|^beta),   beta annealed 20 -> 2,

then rounds h to 0 or 1. The output error is quadratic in the weight error, so it needs only
the Gram matrix of the layer's inputs, H = sum over rows x x^T (a Conv's rows are its im2col
patches, zero padding included): one pass over the calibration frames, then each layer
alone. The scales stay ONNX Runtime's, so only the integers in the graph change.

What it buys on `small`: docs/quantize.md ("What it measures now") and the record in
benchmarks/results/quantize_history.md ("AdaRound weights").

Grouped convolutions (none in `small` or `paper`) and weights shared between nodes keep
nearest rounding.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import onnx
from onnx import numpy_helper

from e3dpsm.onnx_graph import with_outputs
from e3dpsm.quantize.static import weight_channel_axis

log = logging.getLogger(__name__)

WEIGHT_ROUNDINGS: tuple[str, ...] = ("nearest", "adaround")
_ZETA, _GAMMA = 1.1, -0.1  # the rectified sigmoid's stretch (AdaRound's values)


@dataclass(frozen=True)
class AdaRoundConfig:
    iterations: int = 1000
    reg_weight: float = 0.1  # lambda; 0.01 gave 0.480% / 0.575% on `small` above, 0.1 0.421% / 0.461%
    lr: float = 1e-2
    warmup: float = 0.2  # share of the iterations before the rounding term joins
    beta: tuple[float, float] = (20.0, 2.0)


@dataclass
class _Layer:
    node: onnx.NodeProto
    weight: np.ndarray  # float, [out, in_flat]
    scale: np.ndarray  # [out]
    to_graph: str  # "conv" (reshape to the kernel), "rows" (as is: Gemm transB) or "cols" (transpose: MatMul)
    shape: tuple[int, ...]
    alpha: float = 1.0


def _attrs(node: onnx.NodeProto) -> dict[str, Any]:
    return {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}


def find_layers(pre: onnx.ModelProto, qdq: onnx.ModelProto) -> dict[str, _Layer]:
    """The Conv/MatMul/Gemm nodes of the float graph `pre` whose weight the QDQ graph reads as
    8-bit integers with a per-channel scale and zero point 0 (ONNX Runtime's symmetric weights)."""
    floats = {i.name: i for i in pre.graph.initializer}
    ints = {i.name: numpy_helper.to_array(i) for i in qdq.graph.initializer}
    producer = {o: n for n in qdq.graph.node for o in n.output}
    qnodes = {n.name: n for n in qdq.graph.node}
    readers: dict[str, int] = {}
    for node in pre.graph.node:
        for tensor in node.input:
            readers[tensor] = readers.get(tensor, 0) + 1
    layers: dict[str, _Layer] = {}  # by the int8 initializer the graph's DequantizeLinear reads
    for node in pre.graph.node:
        qnode = qnodes.get(node.name)
        if node.op_type not in ("Conv", "MatMul", "Gemm") or qnode is None or len(node.input) < 2:
            continue
        if node.input[1] not in floats or readers.get(node.input[1], 0) != 1:
            continue
        dq = producer.get(qnode.input[1])
        if dq is None or dq.op_type != "DequantizeLinear" or dq.input[0] not in ints:
            continue
        q = ints[dq.input[0]]
        scale = ints.get(dq.input[1])
        zero = ints.get(dq.input[2]) if len(dq.input) > 2 else None
        if q.dtype != np.int8 or scale is None or scale.ndim != 1 or (zero is not None and np.any(zero)):
            continue
        if _attrs(dq).get("axis", 1) != weight_channel_axis(node):  # per output channel, as ORT lays it out
            continue
        weight = numpy_helper.to_array(floats[node.input[1]]).astype(np.float64)
        attrs = _attrs(node)
        if node.op_type == "Conv":
            if attrs.get("group", 1) != 1:
                continue
            layer = _Layer(node, weight.reshape(weight.shape[0], -1), scale, "conv", q.shape)
        elif node.op_type == "Gemm":
            if attrs.get("transA", 0) or weight.ndim != 2:
                continue
            rows = bool(attrs.get("transB", 0))
            layer = _Layer(node, weight if rows else weight.T, scale, "rows" if rows else "cols",
                           q.shape, float(attrs.get("alpha", 1.0)))
        else:
            if weight.ndim != 2:
                continue
            layer = _Layer(node, weight.T, scale, "cols", q.shape)
        if layer.weight.shape[0] != scale.size:
            continue
        layers[dq.input[0]] = layer
    return layers


def _rows(layer: _Layer, x: np.ndarray):
    """A layer's input as the rows its weight multiplies: im2col patches for a Conv."""
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))
    if layer.to_graph == "conv":
        attrs = _attrs(layer.node)
        pads = attrs.get("pads", [0, 0, 0, 0])
        padded = F.pad(t, (pads[1], pads[3], pads[0], pads[2]))
        patches = F.unfold(padded, attrs.get("kernel_shape", list(layer.shape[2:])),
                           dilation=attrs.get("dilations", [1, 1]), stride=attrs.get("strides", [1, 1]))
        return patches.permute(0, 2, 1).reshape(-1, patches.shape[1]).double()
    return t.reshape(-1, t.shape[-1]).double()


def input_grams(pre: onnx.ModelProto, layers: Mapping[str, _Layer], feeds: Sequence[Mapping[str, np.ndarray]],
                threads: int | None = None) -> dict[str, tuple[np.ndarray, int]]:
    """Per layer, (sum of x x^T over its input rows on the calibration feeds, row count)."""
    import onnxruntime as ort

    inputs = list(dict.fromkeys(layer.node.input[0] for layer in layers.values()))
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    session = ort.InferenceSession(with_outputs(pre, inputs).SerializeToString(), options,
                                   providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    grams: dict[str, Any] = {key: 0.0 for key in layers}
    counts = dict.fromkeys(layers, 0)
    for feed in feeds:
        values = dict(zip(names, session.run(None, dict(feed))))
        for key, layer in layers.items():
            rows = _rows(layer, values[layer.node.input[0]])
            grams[key] = grams[key] + (rows.T @ rows).numpy()
            counts[key] += rows.shape[0]
    return {key: (grams[key], counts[key]) for key in layers}


@dataclass(frozen=True)
class RoundingProblem:
    """One layer's AdaRound problem: `weight` [out, in] at per-row `scale` against the input
    Gram matrix `gram` [in, in] of `rows` rows (times the node's `alpha`, a Gemm's)."""
    weight: np.ndarray
    scale: np.ndarray
    gram: np.ndarray
    rows: int
    alpha: float = 1.0

    @property
    def cost(self) -> int:  # multiply-adds of one step's (W - W_q) H
        out, inputs = self.weight.shape
        return out * inputs * inputs


def adaround_weight(weight: np.ndarray, scale: np.ndarray, gram: np.ndarray, rows: int,
                    config: AdaRoundConfig = AdaRoundConfig(), alpha: float = 1.0) -> np.ndarray:
    """The integers [out, in] for `weight` [out, in] at per-row `scale` that AdaRound chooses
    against the input Gram matrix `gram` [in, in] of `rows` rows. Symmetric: each row is
    clipped to +-round(max|w| / s), ONNX Runtime's own range (127 for 8 bits, 64 with reduce_range)."""
    return adaround_batch([RoundingProblem(weight, scale, gram, rows, alpha)], config)[0]


# A bucket may cost this much more per step than its layers alone (padding), or this many
# multiply-adds in all, whichever is larger: below it a step's cost is the interpreter's.
_BUCKET_WASTE, _BUCKET_FREE_COST = 1.5, 2_000_000
_BUCKET_MAX_BYTES = 256 << 20


def _padded(members: Sequence[RoundingProblem]) -> tuple[int, int]:
    """A bucket's multiply-adds per step and its tensors' bytes, padded to its widest layer."""
    out = max(p.weight.shape[0] for p in members)
    inputs = max(p.weight.shape[1] for p in members)
    return len(members) * out * inputs * inputs, len(members) * (inputs * inputs + 12 * out * inputs) * 4


def buckets(problems: Sequence[RoundingProblem]) -> list[list[int]]:
    """Indices of `problems` grouped so that each group is solved as one padded batch: sorted
    by input width, a group grows while its padded cost stays within _BUCKET_WASTE of its
    layers' own (or under _BUCKET_FREE_COST) and its tensors under _BUCKET_MAX_BYTES."""
    order = sorted(range(len(problems)), key=lambda i: (problems[i].weight.shape[1], problems[i].weight.shape[0]))
    groups: list[list[int]] = []
    for i in order:
        if groups:
            group = groups[-1] + [i]
            padded, bytes_ = _padded([problems[j] for j in group])
            own = sum(problems[j].cost for j in group)
            if (padded <= _BUCKET_WASTE * own or padded <= _BUCKET_FREE_COST) and bytes_ <= _BUCKET_MAX_BYTES:
                groups[-1] = group
                continue
        groups.append([i])
    return groups


def adaround_batch(problems: Sequence[RoundingProblem], config: AdaRoundConfig = AdaRoundConfig(),
                   threads: int | None = None) -> list[np.ndarray]:
    """AdaRound's integers for each problem, the problems of a bucket solved together.

    The objective is a sum of the layers' terms and Adam updates each element from its own
    gradient and moments, so a padded batch follows each layer's own trajectory: padded
    inputs have zero Gram rows and columns and padded rows a zero range, so no real entry's
    gradient depends on a padded one (the rounding term moves padded entries alone, and they
    are cut off at the end). In exact arithmetic, that is: a padded inner dimension can change
    float32's summation order, so an element that ends near h = 1/2 may round the other way
    (none did on `small`: its artifact's integers were bit for bit those of one layer at a
    time). Batching removes the interpreter's cost per layer and step (about 1 ms: 110 of the
    130 s AdaRound took on `small` one layer at a time), and a large bucket runs on `threads`
    (tiny ones on one: two threads' spin-waiting made small tensors 30-60x slower on a 2-core
    host with anything else running)."""
    import torch

    out: list[np.ndarray | None] = [None] * len(problems)
    previous = torch.get_num_threads()
    try:
        for group in buckets(problems):
            members = [problems[i] for i in group]
            torch.set_num_threads(1 if _padded(members)[0] <= _BUCKET_FREE_COST else (threads or previous))
            for index, q in zip(group, _solve_bucket(members, config)):
                out[index] = q
    finally:
        torch.set_num_threads(previous)
    return out  # type: ignore[return-value]


def _solve_bucket(problems: Sequence[RoundingProblem], config: AdaRoundConfig) -> list[np.ndarray]:
    import torch

    count = len(problems)
    rows_max = max(p.weight.shape[0] for p in problems)
    inputs_max = max(p.weight.shape[1] for p in problems)
    w = torch.zeros(count, rows_max, inputs_max, dtype=torch.float64)
    s = torch.ones(count, rows_max, 1, dtype=torch.float64)
    qmax = torch.zeros(count, rows_max, 1, dtype=torch.float64)
    hessian = torch.zeros(count, inputs_max, inputs_max, dtype=torch.float32)
    for k, p in enumerate(problems):
        out, inputs = p.weight.shape
        wk = torch.from_numpy(np.asarray(p.weight, np.float64))
        sk = torch.from_numpy(np.asarray(p.scale, np.float64)).reshape(-1, 1)
        w[k, :out, :inputs], s[k, :out] = wk, sk
        qmax[k, :out] = torch.round(wk.abs().amax(dim=1, keepdim=True) / sk)
        hessian[k, :inputs, :inputs] = torch.from_numpy(np.asarray(p.gram, np.float64) / max(p.rows, 1) * p.alpha ** 2).float()
    floor = torch.floor(w / s).float()
    frac = (w / s).float() - floor
    s32, w32, qmax32 = s.float(), w.float(), qmax.float()

    def output_error(w_q: torch.Tensor) -> torch.Tensor:
        d = w_q - w32
        return (torch.bmm(d, hessian) * d).sum()

    def rectified(v: torch.Tensor) -> torch.Tensor:
        return torch.clamp(torch.sigmoid(v) * (_ZETA - _GAMMA) + _GAMMA, 0.0, 1.0)

    # Start where h equals the fractional part: rounding to nearest is the starting point.
    v = (-torch.log((_ZETA - _GAMMA) / (frac - _GAMMA) - 1.0)).clone().requires_grad_(True)
    optimiser = torch.optim.Adam([v], lr=config.lr)
    warm = int(config.warmup * config.iterations)
    high, low = config.beta
    for step in range(config.iterations):
        h = rectified(v)
        loss = output_error(s32 * torch.maximum(torch.minimum(floor + h, qmax32), -qmax32))
        if step >= warm:
            beta = low + (high - low) * max(0.0, 1.0 - (step - warm) / max(1, config.iterations - warm))
            loss = loss + config.reg_weight * (1.0 - (2.0 * h - 1.0).abs().pow(beta)).sum()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        q = torch.maximum(torch.minimum(floor + (rectified(v) >= 0.5).float(), qmax32), -qmax32)
    return [q[k, :p.weight.shape[0], :p.weight.shape[1]].numpy().astype(np.int8) for k, p in enumerate(problems)]


def _to_graph(layer: _Layer, q: np.ndarray) -> np.ndarray:
    if layer.to_graph == "conv":
        return q.reshape(layer.shape)
    return np.ascontiguousarray(q.T if layer.to_graph == "cols" else q)


@dataclass(frozen=True)
class RoundedWeight:
    integers: np.ndarray  # as the graph stores them
    scale: np.ndarray  # the scale they were chosen for
    output_error_ratio: float  # the layer's output error over nearest rounding's (calibration frames)


def adaround_weights(pre: onnx.ModelProto, qdq: onnx.ModelProto, feeds: Sequence[Mapping[str, np.ndarray]],
                     config: AdaRoundConfig = AdaRoundConfig(), threads: int | None = None,
                     nodes: Iterable[str] | None = None) -> dict[str, RoundedWeight]:
    """{quantised weight initializer: AdaRound's integers} for every layer `find_layers` finds
    in `qdq` (a QDQ graph of `pre` with every Conv/MatMul/Gemm quantised), or for those of
    the nodes named in `nodes`."""
    layers = find_layers(pre, qdq)
    if nodes is not None:
        wanted = set(nodes)
        layers = {key: layer for key, layer in layers.items() if layer.node.name in wanted}
    if not layers:
        return {}
    grams = input_grams(pre, layers, feeds, threads)
    out: dict[str, RoundedWeight] = {}
    keys = list(layers)
    # A large bucket runs on `threads` (`small`'s six 96 x 864 convs: 74 ms a step on one
    # thread, 28 on two), a tiny one on one (adaround_batch).
    solved = adaround_batch([RoundingProblem(layers[k].weight, layers[k].scale, *grams[k], layers[k].alpha)
                             for k in keys], config, threads)
    for key, q in zip(keys, solved):
        layer, (gram, _) = layers[key], grams[key]
        nearest = np.round(layer.weight.astype(np.float32) / layer.scale[:, None].astype(np.float32))
        # Output channels are independent in the objective: keep nearest's row where the
        # relaxation ended worse (it can, for a row whose error is small against lambda).
        baseline = _row_errors(layer, nearest, gram)
        q = np.where((_row_errors(layer, q, gram) > baseline)[:, None], nearest, q).astype(np.int8)
        ratio = _row_errors(layer, q, gram).sum() / max(baseline.sum(), 1e-30)
        out[key] = RoundedWeight(_to_graph(layer, q), layer.scale, float(ratio))
    log.info("AdaRound: %d weights, layer output error %.3fx nearest's (median)", len(out),
             float(np.median([r.output_error_ratio for r in out.values()])) if out else float("nan"))
    return out


def _row_errors(layer: _Layer, q: np.ndarray, gram: np.ndarray) -> np.ndarray:
    """Each output channel's summed squared output error over the calibration rows."""
    d = q.astype(np.float64) * layer.scale[:, None] - layer.weight
    return np.einsum("oi,ij,oj->o", d, gram, d) * layer.alpha ** 2


def apply_rounding(model: onnx.ModelProto, rounded: Mapping[str, RoundedWeight]) -> int:
    """Write AdaRound's integers into `model` (in place) where it reads the same quantised
    weight at the same scale; returns how many. A weight the graph quantises otherwise (16
    bits, another scale) keeps what the quantiser wrote."""
    scales = {i.name: i for i in model.graph.initializer}
    scale_of = {n.input[0]: n.input[1] for n in model.graph.node if n.op_type == "DequantizeLinear"}
    count = 0
    for init in model.graph.initializer:
        entry = rounded.get(init.name)
        if entry is None or init.name not in scale_of or scale_of[init.name] not in scales:
            continue
        current = numpy_helper.to_array(init)
        scale = numpy_helper.to_array(scales[scale_of[init.name]])
        if current.dtype != np.int8 or current.shape != entry.integers.shape or not np.array_equal(scale, entry.scale):
            continue
        init.CopyFrom(numpy_helper.from_array(entry.integers, init.name))
        count += 1
    return count
