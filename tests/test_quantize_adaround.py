"""AdaRound weight rounding (quantize/adaround.py): the rounding it picks against brute force
on small problems, the integers it writes into a QDQ graph of the trained tiny, and the
quantize option end to end."""
from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from e3dpsm.quantize.adaround import (AdaRoundConfig, RoundingProblem, adaround_batch, adaround_weight, apply_rounding,
                                      buckets, find_layers)


def _error(q: np.ndarray, w: np.ndarray, s: np.ndarray, gram: np.ndarray) -> np.ndarray:
    d = q * s[:, None] - w
    return np.einsum("oi,ij,oj->o", d, gram, d)


def test_adaround_finds_the_best_up_or_down_rounding_of_small_problems() -> None:
    """Brute force over every up/down choice of each row (2^8) on correlated inputs, where
    rounding errors can cancel and nearest rounding is not the best."""
    rng = np.random.default_rng(0)
    rows, cols = 6, 8
    mixing = rng.standard_normal((cols, cols)) + 2.0 * np.ones((cols, cols))  # strongly correlated inputs
    x = rng.standard_normal((400, cols)) @ mixing
    gram = x.T @ x
    w = rng.standard_normal((rows, cols))
    s = np.abs(w).max(axis=1) / 127
    # rows=1: the summed output error, large against the rounding term (lambda 0.1)
    q = adaround_weight(w, s, gram, 1, AdaRoundConfig(iterations=1500)).astype(np.float64)
    nearest = np.round(w / s[:, None])
    floor = np.floor(w / s[:, None])
    best = np.array([min(_error((floor[o] + np.array(ups))[None], w[o:o + 1], s[o:o + 1], gram)[0]
                         for ups in itertools.product((0.0, 1.0), repeat=cols)) for o in range(rows)])
    got, near = _error(q, w, s, gram), _error(nearest, w, s, gram)
    assert np.all(np.abs(q - w / s[:, None]) < 1.0)  # always floor or ceil
    assert np.all(got <= near * (1 + 1e-9))
    assert np.sum(best < 0.9 * near) >= 4  # mostly cases where nearest is clearly not the best
    # A relaxation, not an exhaustive search: it reaches the optimum on half the rows here and
    # removes most of nearest rounding's excess over it (measured: 9% of it left).
    assert np.sum(got <= 1.01 * best) >= rows // 2
    assert (got - best).sum() <= 0.2 * (near - best).sum(), ((got - best).sum(), (near - best).sum())


def test_adaround_keeps_the_symmetric_range_of_the_scale() -> None:
    w = np.array([[1.0, -1.0, 0.5039, 0.2]])
    s = np.array([1.0 / 127])
    gram = np.ones((4, 4)) * 10.0 + np.eye(4)
    q = adaround_weight(w, s, gram, 1, AdaRoundConfig(iterations=300))
    assert q.dtype == np.int8 and q.max() <= 127 and q.min() >= -127
    s7 = np.array([1.0 / 64])  # 7-bit weights (reduce_range): ONNX Runtime's +-64
    assert np.abs(adaround_weight(w, s7, gram, 1, AdaRoundConfig(iterations=300))).max() <= 64


def test_layers_solved_in_padded_batches_get_the_integers_each_gets_alone() -> None:
    """adaround_batch pads the layers of a bucket to one shape; Adam is elementwise and the
    padding decoupled (zero Gram rows and columns, zero range), so each layer's integers are
    those it gets solved alone, up to float32 summation order (a padded inner dimension may
    reorder it, and an element ending near h = 1/2 may then round the other way: at most one
    step on a few elements; bit-identical on this test's shapes on the AVX2 host). The shapes
    (Conv-like, square, 3 inputs, one wide layer in a bucket of its own) are given out of
    order, so a mix-up between buckets shows too (it moves most integers)."""
    rng = np.random.default_rng(5)
    problems = []
    for out, inputs in [(8, 16), (16, 16), (5, 3), (32, 18), (12, 16), (16, 8), (24, 20), (48, 144)]:
        x = rng.standard_normal((300, inputs)) @ (rng.standard_normal((inputs, inputs)) + 1.0)
        w = rng.standard_normal((out, inputs)) * 0.3
        problems.append(RoundingProblem(w, np.abs(w).max(axis=1) / 127, x.T @ x, 300))
    groups = buckets(problems)
    assert sorted(i for g in groups for i in g) == list(range(len(problems)))
    assert 2 <= len(groups) < len(problems) and [7] in groups  # the wide layer pads nothing else
    config = AdaRoundConfig(iterations=200)
    together = adaround_batch(problems, config)
    for p, q in zip(problems, together):
        alone = adaround_weight(p.weight, p.scale, p.gram, p.rows, config)
        assert q.shape == p.weight.shape and q.dtype == np.int8
        differ = q != alone
        assert differ.mean() <= 0.01 and np.abs(q.astype(int) - alone).max(initial=0) <= 1, differ.mean()
    assert any(not np.array_equal(q, np.round(p.weight / p.scale[:, None])) for p, q in zip(problems, together))


# -- on the trained tiny's QDQ graph -------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_qdq(tmp_path_factory, calibrated_tiny: dict) -> dict:
    from e3dpsm.quantize.static import StaticConfig, quantize_int8

    out = tmp_path_factory.mktemp("adaround") / "full.onnx"
    quantize_int8(calibrated_tiny["pre"], out, StaticConfig(), exclude=[], cache=calibrated_tiny["cache"])
    return {"pre": onnx.load(str(calibrated_tiny["pre"])), "qdq": onnx.load(str(out)), "feeds": calibrated_tiny["feeds"]}


def test_rounded_weights_lower_each_layers_output_error_and_go_into_the_graph(tiny_qdq) -> None:
    from e3dpsm.onnx_graph import with_outputs
    from e3dpsm.quantize.adaround import adaround_weights
    import onnxruntime as ort

    pre, qdq = tiny_qdq["pre"], tiny_qdq["qdq"]
    layers = find_layers(pre, qdq)
    compute = [n for n in pre.graph.node if n.op_type in ("Conv", "MatMul", "Gemm")
               and n.input[1] in {i.name for i in pre.graph.initializer}]
    assert len(layers) >= 0.9 * len(compute) > 20
    rounded = adaround_weights(pre, qdq, tiny_qdq["feeds"], AdaRoundConfig(iterations=300), threads=1)
    assert rounded.keys() == layers.keys()
    ints = {i.name: numpy_helper.to_array(i) for i in qdq.graph.initializer}
    for key, entry in rounded.items():  # floor or ceil of the same w / s: at most one step from nearest
        assert entry.integers.shape == ints[key].shape and entry.integers.dtype == np.int8
        assert np.abs(entry.integers.astype(int) - ints[key]).max() <= 1
    ratios = np.array([r.output_error_ratio for r in rounded.values()])
    assert np.median(ratios) < 0.8 and np.all(ratios <= 1.0 + 1e-6)

    # Independently of the Gram matrices: the layer output error on one calibration frame
    # through ONNX Runtime's inputs, for the Gemm/MatMul layers (x @ W^T in numpy).
    linear = {k: l for k, l in layers.items() if l.to_graph != "conv"}
    session = ort.InferenceSession(with_outputs(pre, [l.node.input[0] for l in linear.values()]).SerializeToString(),
                                   providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    values = {}
    for feed in tiny_qdq["feeds"][:4]:
        for name, value in zip(names, session.run(None, dict(feed))):
            values.setdefault(name, []).append(value.reshape(-1, value.shape[-1]))
    better = 0
    for key, layer in linear.items():
        x = np.concatenate(values[layer.node.input[0]]).astype(np.float64)
        as_rows = (lambda q: q.T) if layer.to_graph == "cols" else (lambda q: q)
        ada = as_rows(rounded[key].integers).astype(np.float64) * layer.scale[:, None]
        near = as_rows(ints[key]).astype(np.float64) * layer.scale[:, None]
        err_ada = np.square(x @ (ada - layer.weight).T).sum()
        err_near = np.square(x @ (near - layer.weight).T).sum()
        better += err_ada < err_near
    assert better >= 0.75 * len(linear), (better, len(linear))

    model = onnx.ModelProto()
    model.CopyFrom(qdq)
    assert apply_rounding(model, rounded) == len(rounded)
    written = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    assert all(np.array_equal(written[k], r.integers) for k, r in rounded.items())
    # Another scale (another graph's weights): left as the quantiser wrote them.
    key = next(iter(rounded))
    shifted = {key: type(rounded[key])(rounded[key].integers, rounded[key].scale * 2, 0.5)}
    model.CopyFrom(qdq)
    assert apply_rounding(model, shifted) == 0


def test_weight_rounding_refuses_what_it_cannot_do() -> None:
    from e3dpsm.errors import ConfigError
    from e3dpsm.quantize import Advanced, QuantizeOptions

    with pytest.raises(ConfigError, match="--weight-rounding and --ranges-from-checkpoint shape INT8 graphs"):
        QuantizeOptions(mode="fp16", advanced=Advanced(weight_rounding="adaround"))
    with pytest.raises(ConfigError, match="unknown --weight-rounding"):
        Advanced(weight_rounding="stochastic")
    assert Advanced().weight_rounding == "nearest"  # the default: at 8-bit activations theirs is the error


@pytest.mark.slow  # ~50 s
def test_quantize_with_adaround_writes_its_integers_and_reports_them(tmp_path: Path, trained_graph: Path,
                                                                      quant_data: Path, full_integer_dir: Path) -> None:
    from _quantize_helpers import fast
    from e3dpsm.quantize import quantize_graph

    nearest = json.loads((full_integer_dir / "report.json").read_text())  # the same options, nearest rounding
    ada = quantize_graph(trained_graph, quant_data, tmp_path / "ada",
                         fast(mode="int8", exclude="recurrent", weight_rounding="adaround"))
    rounding = ada["rounding"]
    # Chosen for every weight once; written where this graph quantises it (not the recurrence's).
    assert rounding["method"] == "adaround" and 20 < rounding["applied"] < rounding["weights"]
    assert rounding["median_output_error_ratio"] < 1.0
    assert ada["quantization"]["weight_rounding"] == "adaround" and nearest["quantization"]["weight_rounding"] == "nearest"
    a = {i.name: numpy_helper.to_array(i) for i in onnx.load(str(tmp_path / "ada" / ada["artifact"])).graph.initializer}
    n = {i.name: numpy_helper.to_array(i)
         for i in onnx.load(str(full_integer_dir / nearest["artifact"])).graph.initializer}
    int8 = [k for k in a if a[k].dtype == np.int8 and a[k].ndim >= 2]
    assert int8 and all(k in n and n[k].shape == a[k].shape for k in int8)  # the same graph, names compacted alike
    changed = [k for k in int8 if not np.array_equal(a[k], n[k])]
    assert len(changed) >= 0.5 * rounding["applied"]
    assert all(np.abs(a[k].astype(int) - n[k]).max() <= 1 for k in changed)
