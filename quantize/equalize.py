"""Equivalent scaling folded into weights (`quantize --equalize`): the GEGLU feed-forwards,
and the LayerNorms whose outputs MatMul/Gemm projections read.

A GEGLU block computes y = W_out (v * gelu(g)) with [v; g] = W_in x (+ b_in). Scaling the
value rows of W_in (and b_in) by 1 / s_j and the matching columns of W_out by s_j leaves y
unchanged for any s_j > 0, since (v_j / s_j) * gelu(g_j) * s_j = v_j * gelu(g_j): the fp32
graph computes the same function to float32 round-off, only the INT8 graph changes. The
product p = v * gelu(g), the activation the output projection reads, is where the trained
`small`'s worst INT8 error sits (its S5 stage-4 feed-forward output projection, 6.7% of MPJPE
alone): a few channels far larger than the rest force one coarse per-tensor step on all.

The scales are SmoothQuant's (Xiao et al. 2023) with alpha = 1/2: s_j = sqrt(max|p_j| /
max|W_out[j, :]|) over the calibration frames, which moves half of each channel's range
from the activation (one scale per tensor) into the weights (one scale per output channel,
so a column scaled up costs little). Exact in ONNX terms: MatMul weights are [in, out], so
"rows of W_out" in the formula are W_out's input rows here.

A LayerNorm computes y = gamma * xhat + beta per channel j of its last axis. Dividing gamma_j and
beta_j by s_j and multiplying the rows j of every projection that reads y by s_j leaves those
projections' outputs unchanged (SmoothQuant's migration into the preceding LayerNorm; Xiao et
al. 2023, section 4). The LayerNorm outputs of this model are also read by residual Adds, the
deformable attention's query Add and the S5 skip Mul: each such reader gets y back through one
float Mul by s (`<norm>/equalize_restore<k>`), so the fp32 function is unchanged everywhere.
On the committed `small` (full integer, mse, MatMul/Gemm outputs float; docs/quantize.md) the
LayerNorm scales with the GEGLU ones took the unseen `val` sequence from 3.53% to 2.98% of MPJPE.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import onnx
from onnx import numpy_helper

from e3dpsm.onnx_graph import GraphIndex, node_key, with_outputs

ALPHA = 0.5


@dataclass(frozen=True)
class GegluSite:
    proj_in: str        # MatMul or Gemm node: x @ W_in (+ b), W_in [D, 2H] (value columns first)
    bias: str | None    # b's initialiser: a Gemm's third input, or the Add after a MatMul
    proj_out: str       # MatMul or Gemm node: p @ W_out, W_out [H, D]
    product: str        # the tensor p = value * gelu(gate)
    value_columns: tuple[int, int]  # [start, end) of the value half in W_in's columns


def smoothquant_scales(act: np.ndarray, wmax: np.ndarray, alpha: float) -> np.ndarray:
    """s_j = max|a_j|^alpha / max|W_j|^(1 - alpha) per channel (1 where either is zero)."""
    return np.where((act > 0) & (wmax > 0), act**alpha / np.maximum(wmax, 1e-12) ** (1 - alpha), 1.0)


def _ranges_record(act: np.ndarray, scale: np.ndarray) -> dict:
    return {"channels": int(scale.size), "activation_range_before": float(act.max()),
            "activation_range_after": float((act / scale).max()),
            "scale_min": float(scale.min()), "scale_max": float(scale.max())}


def _const(model: onnx.ModelProto, name: str) -> np.ndarray | None:
    for init in model.graph.initializer:
        if init.name == name:
            return numpy_helper.to_array(init)
    for node in model.graph.node:
        if node.op_type == "Constant" and node.output[0] == name:
            return numpy_helper.to_array(node.attribute[0].t)
    return None


def _plain_projection(node: onnx.NodeProto, inits: Mapping[str, onnx.TensorProto]) -> bool:
    """A MatMul, or a Gemm without transposes or scaling, whose weight is a 2-D initialiser."""
    if node.op_type not in ("MatMul", "Gemm") or len(node.input) < 2 or node.input[1] not in inits:
        return False
    if len(inits[node.input[1]].dims) != 2:
        return False
    attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
    return not attrs.get("transA", 0) and not attrs.get("transB", 0) and attrs.get("alpha", 1.0) == 1.0 \
        and attrs.get("beta", 1.0) == 1.0


def _channel_vector(init: onnx.TensorProto, channels: int) -> bool:
    """A bias of one value per output channel ([C], [1, C], ...), not a scalar or a full tensor."""
    return int(np.prod(init.dims)) == channels and len(init.dims) >= 1 and int(init.dims[-1]) == channels


def _past_reshapes(model: onnx.ModelProto, index: GraphIndex, tensor: str, channels: int) -> tuple[str, list[str]]:
    """Follow `tensor` through Reshapes that are its only non-Shape reader and keep its last
    axis of `channels` (the exporter writes a Gemm's input and output as 2-D Reshapes of the
    3-D activations): (the last tensor, its readers other than Shape). A Reshape to a shape
    computed in the graph is followed too; the widths the equalisation meets at run time and
    `equalize`'s check of the whole graph catch one that moved the channel axis."""
    while True:
        readers = [c for c in index.consumers.get(tensor, []) if index.nodes[c].op_type not in _SHAPE_ONLY]
        if len(readers) == 1 and index.nodes[readers[0]].op_type == "Reshape" \
                and index.nodes[readers[0]].input[0] == tensor \
                and _last_dim_kept(model, index.nodes[readers[0]], channels, unknown=True):
            tensor = index.nodes[readers[0]].output[0]
            continue
        return tensor, readers


def find_geglu_sites(model: onnx.ModelProto) -> list[GegluSite]:
    """Every proj_in [-> Add(b)] [-> Reshape] -> Slice(value) * f(Slice(gate)) [-> Reshape]
    -> proj_out, proj_in and proj_out plain MatMul/Gemm projections with initialiser weights
    (the S5 blocks' feed-forwards as MatMul, the attention blocks' as Gemm between Reshapes),
    the value slice a plain column range, and the product read by the output projection alone
    (and by Shape)."""
    index = GraphIndex(model)
    inits = {i.name: i for i in model.graph.initializer}
    sites = []
    for key, node in index.nodes.items():
        if not _plain_projection(node, inits):
            continue
        out, bias = node.output[0], (node.input[2] or None if node.op_type == "Gemm" and len(node.input) > 2 else None)
        if bias is not None and (bias not in inits or not _channel_vector(inits[bias], inits[node.input[1]].dims[1])):
            continue
        consumers = index.consumers.get(out, [])
        if bias is None and len(consumers) == 1 and index.nodes[consumers[0]].op_type == "Add":
            add = index.nodes[consumers[0]]
            other = add.input[1] if add.input[0] == out else add.input[0]
            if other in inits and _channel_vector(inits[other], inits[node.input[1]].dims[1]):
                bias, out = other, add.output[0]
        out, consumers = _past_reshapes(model, index, out, int(inits[node.input[1]].dims[1]))
        slices = [index.nodes[c] for c in consumers if index.nodes[c].op_type == "Slice"]
        if len(slices) != 2 or len(consumers) != 2:
            continue
        for value in slices:
            muls = [index.nodes[c] for c in index.consumers.get(value.output[0], [])]
            if len(muls) != 1 or muls[0].op_type != "Mul":
                continue
            product = muls[0].output[0]
            columns = _slice_columns(model, value)
            if columns is None:
                continue
            read, readers = _past_reshapes(model, index, product, columns[1] - columns[0])
            if len(readers) != 1:
                continue
            reader = index.nodes[readers[0]]
            if not _plain_projection(reader, inits) or reader.input[0] != read \
                    or inits[reader.input[1]].dims[0] != columns[1] - columns[0]:
                continue
            sites.append(GegluSite(key, bias, readers[0], product, columns))
    return sites


def _slice_columns(model: onnx.ModelProto, node: onnx.NodeProto) -> tuple[int, int] | None:
    """[start, end) of a Slice over the last axis with step 1, or None."""
    parts = [_const(model, name) if name else None for name in list(node.input[1:]) + [""] * (4 - len(node.input[1:]))]
    starts, ends, axes, steps = parts[:4]
    if starts is None or ends is None or starts.size != 1:
        return None
    if axes is not None and int(axes.ravel()[0]) != -1:
        return None
    if steps is not None and int(steps.ravel()[0]) != 1:
        return None
    return int(starts.ravel()[0]), int(ends.ravel()[0])


def channel_maxima(model: onnx.ModelProto, tensors: Sequence[str],
                   feeds: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """max |t[..., j]| over the feeds, per last-axis channel j, for each named tensor."""
    import onnxruntime as ort

    session = ort.InferenceSession(with_outputs(model, tensors).SerializeToString(), providers=["CPUExecutionProvider"])
    maxima: dict[str, np.ndarray] = {}
    for feed in feeds:
        for name, value in zip(tensors, session.run(list(tensors), dict(feed))):
            m = np.abs(value).reshape(-1, value.shape[-1]).max(axis=0)
            maxima[name] = np.maximum(maxima.get(name, m), m)
    return maxima


def equalize_geglu(model: onnx.ModelProto, feeds: Sequence[Mapping[str, np.ndarray]],
                   alpha: float = ALPHA) -> tuple[onnx.ModelProto, list[dict]]:
    """A copy of `model` with every GEGLU site's scales folded in, and what was done."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    sites = find_geglu_sites(out)
    if not sites:
        return out, []
    inits = {i.name: i for i in out.graph.initializer}
    index = GraphIndex(out)
    maxima = channel_maxima(model, [s.product for s in sites], feeds)
    done = []
    for site in sites:
        w_in_name, w_out_name, bias_name = index.nodes[site.proj_in].input[1], index.nodes[site.proj_out].input[1], site.bias
        if any(len(index.consumers.get(n, ())) != 1 for n in (w_in_name, w_out_name, bias_name) if n):
            continue  # a shared weight would change another node too
        w_in, w_out = numpy_helper.to_array(inits[w_in_name]), numpy_helper.to_array(inits[w_out_name])
        start, end = site.value_columns
        act = maxima[site.product].astype(np.float64)
        wmax = np.abs(w_out).max(axis=1).astype(np.float64)
        if act.shape[0] != end - start or wmax.shape[0] != act.shape[0] or w_in.shape[1] < end:
            continue  # a Reshape on the way moved the channel axis: not this form
        scale = smoothquant_scales(act, wmax, alpha)
        w_in = w_in.astype(np.float64)
        w_in[:, start:end] /= scale
        inits[w_in_name].CopyFrom(numpy_helper.from_array(w_in.astype(np.float32), w_in_name))
        inits[w_out_name].CopyFrom(numpy_helper.from_array((w_out * scale[:, None]).astype(np.float32), w_out_name))
        if bias_name:
            bias = numpy_helper.to_array(inits[bias_name]).astype(np.float64)
            flat = bias.reshape(-1)  # [2H] or [1, 2H]: _channel_vector
            flat[start:end] /= scale
            inits[bias_name].CopyFrom(numpy_helper.from_array(flat.reshape(bias.shape).astype(np.float32), bias_name))
        done.append({"kind": "geglu", "proj_in": site.proj_in, "proj_out": site.proj_out, **_ranges_record(act, scale)})
    return out, done


@dataclass(frozen=True)
class ProjectionRead:
    node: str           # the MatMul/Gemm
    weight: str         # its weight initialiser
    channel_axis: int   # the axis of the weight that runs over the LayerNorm's channels


@dataclass(frozen=True)
class LayerNormSite:
    norm: str                                  # the LayerNormalization node
    output: str                                # its output tensor y
    gain: str                                  # gamma initialiser
    bias: str | None                           # beta initialiser, if any
    projections: tuple[ProjectionRead, ...]    # readers whose weights absorb s
    restored: tuple[tuple[str, str], ...]      # (reader node, tensor it reads) given y back by a Mul


# Readers that see y's values in a way scaling cannot change.
_SHAPE_ONLY = ("Shape", "Size")


def _last_dim_kept(model: onnx.ModelProto, reshape: onnx.NodeProto, channels: int, unknown: bool = False) -> bool:
    """Whether a Reshape keeps the last axis at `channels`; `unknown` where its shape is
    computed in the graph (the exporter's Gemm reshapes back to 3-D are)."""
    shape = _const(model, reshape.input[1])
    if shape is None:
        return unknown
    return shape.size >= 1 and int(shape.ravel()[-1]) == channels


def find_layernorm_sites(model: onnx.ModelProto) -> list[LayerNormSite]:
    """Every LayerNormalization over the last axis with initialiser gain (and bias) used by it
    alone, whose output (or a Reshape of it that keeps the last axis) at least one MatMul/Gemm
    reads as its data input with an initialiser weight used by that node alone."""
    index = GraphIndex(model)
    inits = {i.name: i for i in model.graph.initializer}

    def used_once(name: str) -> bool:  # by one input slot of one node
        return len(index.consumers.get(name, ())) == 1

    graph_outputs = {o.name for o in model.graph.output}
    sites = []
    for key, norm in index.nodes.items():
        if norm.op_type != "LayerNormalization" or len(norm.input) < 2:
            continue
        axis = next((a.i for a in norm.attribute if a.name == "axis"), -1)
        gain = norm.input[1]
        bias = norm.input[2] if len(norm.input) > 2 and norm.input[2] else None
        if axis != -1 or any(n not in inits or not used_once(n) for n in (gain, bias) if n):
            continue
        channels = int(np.prod(inits[gain].dims))
        projections: list[ProjectionRead] = []
        restored: list[tuple[str, str]] = []
        usable = True

        def visit(tensor: str, through_reshape: bool) -> None:
            nonlocal usable
            if tensor in graph_outputs:
                usable = False  # the graph would output y / s
            # A node reading y in two slots is listed twice; it needs one restoring Mul.
            for reader_key in dict.fromkeys(index.consumers.get(tensor, [])):
                reader = index.nodes[reader_key]
                op, attrs = reader.op_type, {a.name: a.i for a in reader.attribute}
                weight = reader.input[1] if len(reader.input) > 1 else ""
                if op in _SHAPE_ONLY:
                    continue
                if op == "Reshape" and not through_reshape and reader.input[0] == tensor \
                        and _last_dim_kept(model, reader, channels):
                    visit(reader.output[0], True)
                elif op in ("MatMul", "Gemm") and reader.input[0] == tensor and weight in inits \
                        and len(inits[weight].dims) == 2 and not attrs.get("transA", 0):
                    axis = 1 if attrs.get("transB", 0) else 0
                    if not used_once(weight) or inits[weight].dims[axis] != channels:
                        usable = False  # a shared weight would change another node too
                    projections.append(ProjectionRead(reader_key, weight, axis))
                else:
                    restored.append((reader_key, tensor))

        visit(norm.output[0], False)
        if usable and projections:
            sites.append(LayerNormSite(key, norm.output[0], gain, bias, tuple(projections), tuple(restored)))
    return sites


def equalize_layernorms(model: onnx.ModelProto, feeds: Sequence[Mapping[str, np.ndarray]],
                        alpha: float = ALPHA) -> tuple[onnx.ModelProto, list[dict]]:
    """A copy of `model` with every LayerNorm site's scales folded into its gain, bias and
    projections (and undone for its other readers), and what was done."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    sites = find_layernorm_sites(out)
    if not sites:
        return out, []
    inits = {i.name: i for i in out.graph.initializer}
    index = GraphIndex(out)
    maxima = channel_maxima(model, [s.output for s in sites], feeds)
    restores: dict[str, list[onnx.NodeProto]] = {}  # producer's key -> Muls to insert after it
    done = []
    for site in sites:
        act = maxima[site.output].astype(np.float64)
        weights = {p.weight: (numpy_helper.to_array(inits[p.weight]).astype(np.float64), p.channel_axis)
                   for p in site.projections}
        wmax = np.max([np.abs(w).max(axis=1 - ax) for w, ax in weights.values()], axis=0)
        if act.shape != wmax.shape:
            continue
        scale = smoothquant_scales(act, wmax, alpha)
        for name in (site.gain, site.bias):
            if name:
                value = numpy_helper.to_array(inits[name]).astype(np.float64)
                inits[name].CopyFrom(numpy_helper.from_array((value / scale.reshape(value.shape)).astype(np.float32), name))
        for name, (w, ax) in weights.items():
            scaled = w * (scale[:, None] if ax == 0 else scale[None, :])
            inits[name].CopyFrom(numpy_helper.from_array(scaled.astype(np.float32), name))
        if site.restored:
            scale_name = f"{site.norm}/equalize_scale"
            out.graph.initializer.append(numpy_helper.from_array(scale.astype(np.float32), scale_name))
        for k, (reader, tensor) in enumerate(site.restored):
            restored = f"{tensor}/equalize_restored{k}"
            mul = onnx.helper.make_node("Mul", [tensor, scale_name], [restored], name=f"{site.norm}/equalize_restore{k}")
            restores.setdefault(index.producer[tensor], []).append(mul)
            node = index.nodes[reader]
            for i, name in enumerate(node.input):
                if name == tensor:
                    node.input[i] = restored
        done.append({"kind": "layernorm", "norm": site.norm, "projections": [p.node for p in site.projections],
                     "restored_readers": len(site.restored), **_ranges_record(act, scale)})
    if restores:
        ordered = []
        for node in out.graph.node:
            ordered.append(node)
            ordered.extend(restores.get(node_key(node), []))
        del out.graph.node[:]
        out.graph.node.extend(ordered)
    return out, done


def equalize(model: onnx.ModelProto, feeds: Sequence[Mapping[str, np.ndarray]],
             alpha: float = ALPHA) -> tuple[onnx.ModelProto, list[dict]]:
    """Both foldings (`quantize --equalize`): the GEGLU sites first, then the LayerNorms, with
    the LayerNorm scales taken from the GEGLU-equalised graph's activations."""
    source = model
    model, geglu = equalize_geglu(model, feeds, alpha)
    model, norms = equalize_layernorms(model, feeds, alpha)
    if (geglu or norms) and feeds:
        _check_unchanged(source, model, feeds[0])
    return model, [*geglu, *norms]


# float32 round-off on outputs of up to ~1e3 (poses in mm); a folding that is not exact moves
# them by far more (a scale left on one side: > 1e-2 on the trained tiny's poses, tested).
_UNCHANGED_RTOL = 1e-4


def _check_unchanged(source: onnx.ModelProto, folded: onnx.ModelProto, feed: Mapping[str, np.ndarray]) -> None:
    """Every output of `folded` equals `source`'s on `feed` to float32 round-off, or InputError:
    a graph form the site finders took for one they fold exactly."""
    import onnxruntime as ort

    from e3dpsm.errors import InputError

    def run(model: onnx.ModelProto) -> list[np.ndarray]:
        session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        return session.run(None, dict(feed))

    for output, a, b in zip(source.graph.output, run(source), run(folded)):
        if np.asarray(a).dtype.kind != "f":
            continue  # indices, counters: not what a scale can move by round-off
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        if np.abs(a - b).max(initial=0.0) > _UNCHANGED_RTOL * (1.0 + np.abs(a).max(initial=0.0)):
            raise InputError(f"--equalize changed the fp32 output {output.name!r} by {np.abs(a - b).max():.3g} "
                             "(a graph form it cannot fold exactly); quantize without --equalize")
