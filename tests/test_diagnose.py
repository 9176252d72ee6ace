"""`e3dpsm diagnose` end to end in a process where torch cannot be imported (edge devices
have numpy and onnxruntime only), judged on the figures of its report."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from e3dpsm.onnx_groups import module_scopes

STEPS = 12
# `import torch` raises ImportError with a None entry in sys.modules, as on a device
# without it; anything that needs torch on the way fails loudly.
NO_TORCH = "import sys; sys.modules['torch'] = None; "


def damage_decoder(graph: Path, out: Path) -> str:
    """The graph with one decoder weight scaled by 1.5; returns the weight's name."""
    model = onnx.load(str(graph))
    scopes = module_scopes(model)
    weights = {init.name: init for init in model.graph.initializer}
    name = next(i for n in model.graph.node if scopes[n.name] == "decoder" and n.op_type in ("MatMul", "Gemm")
                for i in n.input if i in weights)
    init = weights[name]
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * np.float32(1.5), name))
    onnx.save(model, str(out))
    return name


def test_diagnose_runs_without_torch_and_blames_the_damaged_decoder(tmp_path, trained_graph, quant_data):  # noqa: F811
    damaged = tmp_path / "damaged.onnx"
    damage_decoder(trained_graph, damaged)
    out = tmp_path / "d"
    script = (NO_TORCH + "from e3dpsm.cli import main; "
              f"rc = main(['diagnose', '--reference', {str(trained_graph)!r}, '--model', {str(damaged)!r}, "
              f"'--data', {str(quant_data)!r}, '--steps', '{STEPS}', '--threads', '1', '--out', {str(out)!r}]); "
              "assert sys.modules['torch'] is None; sys.exit(rc)")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["steps"] == STEPS and report["ranked_by"] == "added_error" and report["quantised_activations"] == 0
    assert report["matched_tensors"] > 10
    groups = {g["name"]: g for g in report["groups"]}
    # Upstream of the decoder both graphs are the same graph on the same frames: exactly 0.
    upstream = [g for g in groups if g == "stem" or g.startswith(("stages.", "attention.", "s5_stage")) or g == "ssm"]
    assert len(upstream) >= 8 and "ssm" in upstream, sorted(groups)
    for name in upstream:
        assert groups[name]["mean_error"] == 0.0 and groups[name]["mean_added_error"] == 0.0, name
    states = {s["name"]: s["error_at_step"] for s in report["states"]}
    for name, errors in states.items():
        if name != "fusion_pose":
            # the S5 states are upstream; the Kalman covariance and flag do not depend on the data
            assert set(errors.values()) == {0.0}, (name, errors)
        else:  # the fused pose carries the damaged poses from the first step on
            assert errors["1"] > 0.0, (name, errors)
    assert "fusion_pose" in states and len(states) >= 5
    # The decoder's own output departs at step 1 and nothing upstream added to it.
    decoder = groups["decoder"]
    assert decoder["error_at_step"]["1"] > 0.01 and decoder["mean_added_error"] == decoder["mean_error"]
    assert report["culprits"].index("decoder") < min(report["culprits"].index(g) for g in upstream)
    assert all(o["error_at_step"]["1"] > 0.0 for o in report["outputs"])
    assert "| decoder |" in (out / "report.md").read_text()
