"""benchmarks/bench_conv_forms.py times Winograd forms of the CNN's 3x3 convolutions against
ONNX Runtime's Conv; its graphs must compute the convolution. Checked here against a numpy
direct convolution (sum over the nine taps), on sizes that are not multiples of the tile."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_conv_forms.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_conv_forms", _PATH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their module while the file runs
    spec.loader.exec_module(module)
    return module


def direct_conv(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3x3, stride 1, zero padding 1, in float64."""
    _, _, h, width = x.shape
    padded = np.pad(x.astype(np.float64), ((0, 0), (0, 0), (1, 1), (1, 1)))
    out = np.zeros((1, w.shape[0], h, width)) + b.reshape(1, -1, 1, 1)
    for r in range(3):
        for s in range(3):
            out += np.einsum("oc,nchw->nohw", w[:, :, r, s], padded[:, :, r:r + h, s:s + width])
    return out


@pytest.mark.parametrize("m", [2, 4])
@pytest.mark.parametrize("height, width", [(8, 12), (7, 9)])
def test_winograd_graph_is_the_convolution(bench, m, height, width):
    rng = np.random.default_rng(m * 100 + height)
    shape = bench.ConvShape(3, 5, height, width)
    w = rng.standard_normal((5, 3, 3, 3)).astype(np.float32)
    b = rng.standard_normal(5).astype(np.float32)
    x = rng.standard_normal((1, 3, height, width)).astype(np.float32)
    sess = ort.InferenceSession(bench.winograd_conv_graph(shape, w, b, m).SerializeToString(),
                                providers=["CPUExecutionProvider"])
    got = sess.run(None, {"x": x})[0]
    want = direct_conv(x, w, b)
    assert got.shape == want.shape
    # float32 round-off of the transforms, relative to the output scale (F(4,3) amplifies most)
    assert np.abs(got - want).max() <= 2e-5 * np.abs(want).max()
    # and a one-tap error is far outside that tolerance
    w_off = w.copy()
    w_off[0, 0, 1, 1] += 0.05
    assert np.abs(direct_conv(x, w_off, b) - want).max() > 100 * 2e-5 * np.abs(want).max()


def test_winograd_matrices_reconstruct_a_1d_correlation(bench):
    """F(m,3) in one dimension: A^T [(G g) * (B^T d)] is the valid correlation of d with g."""
    rng = np.random.default_rng(0)
    for m in (2, 4):
        bt, g, at = bench.winograd_matrices(m)
        d, taps = rng.standard_normal(m + 2), rng.standard_normal(3)
        want = np.array([d[i:i + 3] @ taps for i in range(m)])
        assert np.allclose(at @ ((g @ taps) * (bt @ d)), want, atol=1e-12)
    with pytest.raises(ValueError, match="tabulated"):
        bench.winograd_matrices(3)
