"""GEGLU equalisation (quantize/equalize.py): the fp32 function is unchanged, the product's
per-channel ranges are evened out by the SmoothQuant scales."""
from __future__ import annotations

import numpy as np
import onnx
from onnx import numpy_helper

from e3dpsm.quantize.equalize import channel_maxima, equalize_geglu, find_geglu_sites


def test_equalized_graph_computes_the_same_poses(tmp_path, trained_graph, quant_data) -> None:  # noqa: F811
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.calibration import record_calibration_set
    from e3dpsm.runtime import StepSession

    model = onnx.load(str(trained_graph))
    sites = find_geglu_sites(model)
    assert len(sites) == 2 and all(s.value_columns[0] == 0 for s in sites)  # the two S5 blocks' feed-forwards
    data = PreparedData.open(quant_data)
    calib = record_calibration_set(trained_graph, data.split("train"), 16, 20.0)
    equalized, done = equalize_geglu(model, calib.feeds)
    assert len(done) == 2
    before = channel_maxima(model, [s.product for s in sites], calib.feeds)
    after = channel_maxima(equalized, [s.product for s in sites], calib.feeds)
    for site, record in zip(sites, done):
        # s_j = sqrt(a_j / w_j): the channels' ranges a_j / s_j = sqrt(a_j w_j) are closer together
        spread = lambda m: m.max() / m[m > 0].min()  # noqa: E731
        assert spread(after[site.product]) < spread(before[site.product])
        assert abs(after[site.product].max() - record["activation_range_after"]) < 1e-4 * record["activation_range_after"]
    weights = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    changed = [i.name for i in equalized.graph.initializer
               if not np.array_equal(numpy_helper.to_array(i), weights[i.name])]
    assert len(changed) == 4  # W_in and W_out of each site, nothing else
    onnx.save(equalized, str(tmp_path / "eq.onnx"))
    a, b = StepSession(trained_graph), StepSession(tmp_path / "eq.onnx")
    sa, sb, worst = a.init_state(1), b.init_state(1), 0.0
    seq = data.split("val")[0]
    for f in range(20):
        x = np.asarray(seq.lnes[f: f + 1], np.float32)
        oa, sa = a.step(x, sa, 20.0)
        ob, sb = b.step(x, sb, 20.0)
        worst = max(worst, max(float(np.abs(oa[k] - ob[k]).max()) for k in oa))
    assert worst < 1e-3  # mm: float32 round-off on poses of ~1,000 mm


def test_a_scale_on_one_side_only_breaks_the_function(tmp_path, trained_graph) -> None:  # noqa: F811
    """The test above can fail: scaling W_out's rows without W_in's value columns moves the
    poses by far more than round-off."""
    from e3dpsm.runtime import StepSession

    model = onnx.load(str(trained_graph))
    site = find_geglu_sites(model)[1]
    node = next(n for n in model.graph.node if n.name == site.proj_out)
    init = next(i for i in model.graph.initializer if i.name == node.input[1])
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * 2.0, init.name))
    onnx.save(model, str(tmp_path / "broken.onnx"))
    session_a, session_b = StepSession(trained_graph), StepSession(tmp_path / "broken.onnx")
    x = np.random.default_rng(0).random((1, 2, 192, 256), dtype=np.float32) * (np.random.default_rng(1).random(
        (1, 2, 192, 256)) < 0.05)
    oa, _ = session_a.step(x, session_a.init_state(1), 20.0)
    ob, _ = session_b.step(x, session_b.init_state(1), 20.0)
    assert np.abs(oa["pose"] - ob["pose"]).max() > 1e-2
