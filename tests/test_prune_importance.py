"""Channel importance (compress/importance.py) against its documented formulas, each computed
here channel by channel with numpy; which channels keep_top and keep_lists keep, by unit kind."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import e3dpsm
from _model_helpers import randomised_tiny
from e3dpsm.compress.importance import channel_scores, keep_lists, keep_top
from e3dpsm.compress.units import ATTN_BLOCK, ATTN_FF, DECODER_FFN, RES, SSM_FF, SSM_MODES, prunable_units


@pytest.fixture(scope="module")
def model() -> e3dpsm.E3DPSM:
    return randomised_tiny(3, decoder_layers=2)


def _unit(model, kind: str, name: str | None = None):
    return next(u for u in prunable_units(model.config) if u.kind == kind and (name is None or u.name == name))


def _np(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().numpy().astype(np.float64)


def _norm(vector: np.ndarray) -> float:
    return float(np.sqrt(np.sum(vector ** 2)))


def test_residual_hidden_channels_by_bn_scale_and_shift_times_outgoing_weights(model) -> None:
    unit = _unit(model, RES, "stages.1.block2")
    block = model.get_submodule(unit.name)
    gamma, beta, conv2 = _np(block.norm2.weight), _np(block.norm2.bias), _np(block.conv2.weight)
    expected = [(abs(gamma[c]) + abs(beta[c])) * _norm(conv2[:, c].ravel()) for c in range(conv2.shape[1])]
    np.testing.assert_allclose(_np(channel_scores(model, unit)), expected, rtol=1e-5)


@pytest.mark.parametrize("kind", [ATTN_FF, SSM_FF])
def test_geglu_hidden_channels_by_value_gate_and_outgoing_rows(model, kind) -> None:
    unit = _unit(model, kind)
    ff = model.get_submodule(unit.name)
    w_in, w_out = _np(ff.proj_in.weight), _np(ff.proj_out.weight)
    hidden = w_out.shape[1]
    assert w_in.shape[0] == 2 * hidden
    expected = [_norm(w_in[c]) * _norm(w_in[hidden + c]) * _norm(w_out[:, c]) for c in range(hidden)]
    np.testing.assert_allclose(_np(channel_scores(model, unit)), expected, rtol=1e-5)


@pytest.mark.parametrize("bidirectional", [True, False])
def test_s5_modes_by_complex_input_and_output_norms(bidirectional) -> None:
    model = randomised_tiny(3, ssm_bidirectional=bidirectional)
    unit = _unit(model, SSM_MODES, "ssm.3.s5")
    s5 = model.get_submodule(unit.name)
    assert hasattr(s5, "cb_re") is bidirectional
    b = _np(s5.b_re) + 1j * _np(s5.b_im)  # [modes, inputs]
    c = _np(s5.c_re) + 1j * _np(s5.c_im)  # [outputs, modes]
    cb = _np(s5.cb_re) + 1j * _np(s5.cb_im) if bidirectional else None
    expected = []
    for p in range(b.shape[0]):
        out = np.sqrt(np.sum(np.abs(c[:, p]) ** 2)) + (np.sqrt(np.sum(np.abs(cb[:, p]) ** 2)) if bidirectional else 0)
        expected.append(np.sqrt(np.sum(np.abs(b[p]) ** 2)) * out)
    np.testing.assert_allclose(_np(channel_scores(model, unit)), expected, rtol=1e-5)


def test_decoder_ffn_channels_per_layer(model) -> None:
    unit = _unit(model, DECODER_FFN)
    for layer in (0, 1):
        lay = model.decoder.layers[layer]
        w1, w2 = _np(lay.linear1.weight), _np(lay.linear2.weight)
        expected = [_norm(w1[c]) * _norm(w2[:, c]) for c in range(w1.shape[0])]
        np.testing.assert_allclose(_np(channel_scores(model, unit, layer)), expected, rtol=1e-5)
    np.testing.assert_array_equal(channel_scores(model, unit), channel_scores(model, unit, 0))  # layer 0 by default


def test_a_unit_without_channels_is_refused(model) -> None:
    unit = _unit(model, ATTN_BLOCK, "attention.1")
    with pytest.raises(ValueError) as refused:
        channel_scores(model, unit)
    assert str(refused.value) == "unit attention.1 (attn_block) has no channels to rank"


def test_keep_top_keeps_the_highest_scores_in_ascending_order(model) -> None:
    unit = _unit(model, RES, "stages.1.block2")
    scores = _np(channel_scores(model, unit))
    for width in (1, 5, len(scores)):
        assert keep_top(model, unit, width) == sorted(np.argsort(-scores, kind="stable")[:width].tolist())
    assert keep_top(model, unit, 0) == [] and keep_top(model, unit, -2) == []
    decoder = _unit(model, DECODER_FFN)
    layer1 = _np(channel_scores(model, decoder, 1))
    assert keep_top(model, decoder, 7, 1) == sorted(np.argsort(-layer1, kind="stable")[:7].tolist())


def test_keep_lists_name_every_module_a_width_touches(model) -> None:
    widths = {"stages.1.block2": 5, "attention.1.ff": 9, "ssm.3.ff": 4, "ssm.3.s5": 3, "decoder.ffn": 6,
              "attention.1": 0, "attention.2": 1}
    keep = keep_lists(model, prunable_units(model.config), widths)
    by_name = {u.name: u for u in prunable_units(model.config)}
    assert keep == {
        "stages.1.block2": keep_top(model, by_name["stages.1.block2"], 5),
        "attention.1.ff": keep_top(model, by_name["attention.1.ff"], 9),
        "ssm.3.ff": keep_top(model, by_name["ssm.3.ff"], 4),
        "ssm.3.s5": keep_top(model, by_name["ssm.3.s5"], 3),
        "decoder.layers.0.ffn": keep_top(model, by_name["decoder.ffn"], 6, 0),
        "decoder.layers.1.ffn": keep_top(model, by_name["decoder.ffn"], 6, 1),
        "attention.1": [],  # an attention block goes whole or stays whole
        "attention.2": [0],
    }
    assert keep["decoder.layers.0.ffn"] != keep["decoder.layers.1.ffn"]  # each layer ranked on its own weights
    assert [len(v) for v in keep.values()] == [5, 9, 4, 3, 6, 6, 0, 1]
    with pytest.raises(KeyError):
        keep_lists(model, prunable_units(model.config), {"no.such.unit": 3})
