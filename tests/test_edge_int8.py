"""INT8 ExecuTorch programs (`convert executorch --quantize int8 --data PREP`) of the trained
tiny: the calibration feeds mapped onto the traced step's arguments, the recurrent modules
float in the lowered program, the task budget on held-out frames (and that it bites on a
broken artifact), and the bad inputs of docs/edge.md#int8.

The tests on a converted program share one conversion (export, PT2E calibration, XNNPACK
lowering): about 4 minutes alone on 2 cores and 12 on a loaded host, so they are `slow`."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from _edge_helpers import skip_without
from _quantize_helpers import TRAINED_TINY
from e3dpsm.cli import main

CALIBRATION_FRAMES = 16


@pytest.fixture(scope="module")
def int8_run(tmp_path_factory, quant_data) -> dict:
    """One CLI conversion: {"code", "out", "report"} (the whole test split is the held-out check)."""
    skip_without("executorch")
    out = tmp_path_factory.mktemp("int8") / "et"
    code = main(["convert", "executorch", "--checkpoint", str(TRAINED_TINY), "--out", str(out), "--quantize", "int8",
                 "--data", str(quant_data), "--frames", str(CALIBRATION_FRAMES), "--threads", "1", "--taps"])
    return {"code": code, "out": out, "report": json.loads((out / "convert.json").read_text())}


def test_feeds_map_onto_the_traced_step(edge_model, trained_graph, quant_data) -> None:
    """Each recorded feed, given to the step wrapper torch.export traces, computes the ONNX
    graph's poses and states on it: names mapped to the right arguments (a swapped pair of
    states would not)."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.edge_export import step_spec
    from e3dpsm.export.executorch_int8 import step_inputs
    from e3dpsm.export.wrapper import StepGraph
    from e3dpsm.quantize.calibration import record_calibration_set
    from e3dpsm.runtime import StepSession

    calibration = record_calibration_set(trained_graph, PreparedData.open(quant_data).split("train"),
                                         CALIBRATION_FRAMES, 20.0, threads=1)
    spec = step_spec(edge_model)
    inputs = step_inputs(calibration, spec.input_names)
    session = StepSession(trained_graph, threads=1)
    wrapper = StepGraph(edge_model).eval()
    late = len(inputs) - 1  # a frame deep in a rollout: its states are not the initial ones
    assert np.abs(inputs[late][spec.input_names.index("fusion_pose_in")].numpy()).max() > 10.0
    with torch.no_grad():
        got = dict(zip(spec.output_names, (t.numpy() for t in wrapper(*inputs[late]))))
    want, new_state = session.run_feeds(calibration.feeds[late])
    np.testing.assert_allclose(got["pose"], want["pose"], atol=1e-3)
    np.testing.assert_allclose(got["s5_stage4_re_out"], new_state["s5_stage4_re"], atol=1e-4)


@pytest.mark.slow
def test_int8_program_is_within_budget(int8_run, quant_data) -> None:
    """Calibrated on 16 train frames, judged on the whole test split (a sequence neither the
    calibration nor the search saw). The full 8-bit program of the trained tiny is over budget
    (PA-MPJPE +2.5%, jitter +14% when it was shipped so): the search keeps blocks float, found
    on the val split, and the program it lowers is within."""
    report = int8_run["report"]
    budget = report["budget"]
    search = report["artifact"]["search"]
    assert search["split"] == "val" and search["frames"] == 50 and search["within"]
    assert search["trials"][0]["label"] == "all-int8" and not search["trials"][0]["within"]
    assert 1 <= len(search["blocks_kept_float"]) <= 4 and report["artifact"]["keep_float"]["searched"] == search["kept_float"]
    # The narrowing left float only layers of the blocks the search kept (or those blocks whole).
    assert search["kept_float"] and all(any(path == block or path.startswith(block + ".") for block in
                                            search["blocks_kept_float"]) for path in search["kept_float"])
    assert search["narrowing_untried"] == []  # no --narrow-trials: every unit tried
    assert [t["unit"] for t in search["narrowing"] if not t["within"]] == [
        path for path in search["kept_float"] if path not in search["blocks_kept_float"]]
    assert int8_run["code"] == 0 and budget["within"], budget["metrics"]
    assert budget["frames"] == 50 and budget["data"].endswith("/test")
    assert report["artifact"]["calibration"] == {**report["artifact"]["calibration"], "split": "train",
                                                  "frames": CALIBRATION_FRAMES, "state_source": "rollout"}
    for name in ("mpjpe", "pa_mpjpe", "jitter"):
        metric = budget["metrics"][name]
        assert metric["upper_pct"] <= metric["limit_pct"] and metric["upper_pct"] >= metric["change_pct"]
    assert budget["distance_to_fp32_mm"] > 0.01  # quantised: not the fp32 program under another name
    assert report["artifact"]["precision"] == "int8" and (int8_run["out"] / "step.pte").is_file()


@pytest.mark.slow
def test_the_taps_program_computes_the_programs_steps_and_names_its_activations(int8_run, edge_golden) -> None:
    """--taps: step_taps.pte beside step.pte, checked by the converter to step as it does (on
    every calibration frame), its taps every quantised activation, readable by pte_taps."""
    from e3dpsm.golden.pte_taps import record

    taps = int8_run["report"]["taps"]
    assert taps["file"] == "step_taps.pte" and taps["identical_steps"] == CALIBRATION_FRAMES
    trace = record(int8_run["out"] / "step_taps.pte", edge_golden, steps=3)
    assert len(trace["taps"]) == taps["taps"] > 40 and trace["steps"] == 3
    assert {t["dtype"] for t in trace["taps"]} == {"int8"}
    assert any(t["tap"].startswith("model.stem") for t in trace["taps"])
    assert not any(".s5" in t["tap"] or t["tap"].startswith("model.fusion") for t in trace["taps"])  # float


@pytest.mark.slow
def test_recurrent_modules_stay_float_in_the_lowered_program(int8_run) -> None:
    """Every multiply-accumulate of the S5 layers, the Kalman fusion and the fused-pose
    embedding reads float operands; the convolutions and linears elsewhere read 8-bit ones."""
    coverage = int8_run["report"]["delegation"]["int8"]
    kept_float = (".s5", "fusion", "pose_embed", "direct_head", "delta_head")
    assert not [path for path in coverage["int8_modules"] if any(k in path for k in kept_float)]
    assert any(path.endswith(".s5") or ".s5." in path for path in coverage["float_modules"])
    assert any(".stages." in path for path in coverage["int8_modules"])
    assert coverage["xnnpack_int8"].get("aten.convolution.default", 0) >= 4
    assert coverage["xnnpack_int8"].get("aten.linear.default", 0) >= 1
    assert int8_run["report"]["artifact"]["keep_float"]["module_types"] == ["S5", "PoseFusion"]


class _Noisy:
    """A runner whose fused pose gets seeded per-joint noise of `sigma_mm`: a broken artifact
    (a constant offset would not do: MPJPE is root-relative and PA-MPJPE removes it)."""

    def __init__(self, runner, sigma_mm: float) -> None:
        self.runner, self.sigma_mm, self.meta = runner, sigma_mm, runner.meta
        self.rng = np.random.default_rng(0)

    def init_state(self, batch: int = 1):
        return self.runner.init_state(batch)

    def step(self, lnes, state, window_ms):
        out, state = self.runner.step(lnes, state, window_ms)
        noise = self.rng.normal(0.0, self.sigma_mm, out["pose"].shape).astype(np.float32)
        return {**out, "pose": out["pose"] + noise}, state


@pytest.mark.slow
def test_the_budget_fails_a_broken_artifact(int8_run, trained_graph, quant_data) -> None:
    """The same INT8 program with 30 mm of noise on every joint is over budget on MPJPE and
    jitter, and the CLI's exit code follows the recorded verdict."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.edge_int8 import EdgeInt8Options, held_out_set
    from e3dpsm.quantize.holdout import check_stepper
    from e3dpsm.runtime.stepping import open_stepper

    options = EdgeInt8Options(threads=1)
    held = held_out_set(trained_graph, PreparedData.open(quant_data), options)
    broken = check_stepper(_Noisy(open_stepper(int8_run["out"] / "step.pte", threads=1), 30.0), held, options.budget)
    assert not broken.within and not broken.metric("mpjpe").within and not broken.metric("jitter").within
    assert int8_run["code"] == (0 if int8_run["report"]["budget"]["within"] else 1)


@pytest.mark.slow
def test_holdout_opens_edge_artifacts_on_their_own_runtime(int8_run) -> None:
    from e3dpsm.quantize.holdout import open_stepper

    assert open_stepper(int8_run["out"] / "step.pte", "executorch", 1).runtime == "executorch"
    with pytest.raises(ValueError, match="executorch artifact"):
        open_stepper(int8_run["out"] / "step.pte", "litert", 1)


# -- bad input: one line, exit 2, nothing written ------------------------------------------

def _fails(capsys, argv: list[str], *needles: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("e3dpsm convert: error:"), err
    assert all(needle in err for needle in needles), err


def test_quantize_without_data(capsys, tmp_path) -> None:
    out = tmp_path / "et"
    _fails(capsys, ["convert", "executorch", "--variant", "tiny", "--out", str(out), "--quantize", "int8"],
           "--quantize int8 needs --data PREP")
    _fails(capsys, ["convert", "executorch", "--variant", "tiny", "--out", str(out), "--data", str(tmp_path)],
           "--data is read only with --quantize;")
    _fails(capsys, ["convert", "executorch", "--variant", "tiny", "--out", str(out), "--taps"],
           "--taps taps the quantised activations of an INT8 program: add --quantize int8 --data PREP")
    assert not out.exists()


@pytest.mark.parametrize("flag", ["--search-rounds", "--search-frames", "--narrow-trials"])
def test_a_negative_search_is_refused(capsys, tmp_path, quant_data, flag) -> None:
    skip_without("executorch")
    out = tmp_path / "et"
    _fails(capsys, ["convert", "executorch", "--checkpoint", str(TRAINED_TINY), "--out", str(out), "--quantize",
                    "int8", "--data", str(quant_data), flag, "-1"], f"{flag} must be 0 or positive, got -1")
    assert not out.exists()


def test_data_without_a_search_split(capsys, tmp_path, quant_data) -> None:
    """No val sequence: the search has nowhere to judge; the error says how to go without it."""
    skip_without("executorch")
    import shutil

    no_val = tmp_path / "prep"
    shutil.copytree(quant_data, no_val)
    meta = json.loads((no_val / "meta.json").read_text())
    meta["sequences"] = [s for s in meta["sequences"] if s["split"] != "val"]
    (no_val / "meta.json").write_text(json.dumps(meta))
    out = tmp_path / "et"
    _fails(capsys, ["convert", "executorch", "--checkpoint", str(TRAINED_TINY), "--out", str(out), "--quantize",
                    "int8", "--data", str(no_val)], "no sequences in split 'val'", "(--search-rounds 0 converts without it)")
    assert not out.exists()


def test_data_at_another_frame_size(capsys, tmp_path, quant_data) -> None:
    skip_without("executorch")
    from e3dpsm.data.prepare import prepare_dataset

    small = tmp_path / "prep96"
    prepare_dataset(Path(quant_data).parent / "raw", small, window_ms=20.0, height=96, width=128, progress=False)
    out = tmp_path / "et"
    _fails(capsys, ["convert", "executorch", "--checkpoint", str(TRAINED_TINY), "--out", str(out), "--quantize",
                    "int8", "--data", str(small)], "re-run prepare with --height 192 --width 256")
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["prep96"]


class _ToyLinear(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.linear = torch.nn.Linear(16, 8)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(x)


@pytest.mark.parametrize("quantized, int8_weights", [(True, 1), (False, 0)])
def test_constant_folding_keeps_8bit_weights(quantized, int8_weights) -> None:
    """PT2E's int8 weight and its dequantize survive ExecuTorch's constant folding only with
    the ATen quantize ops among the targets skipped; with the default targets they fold into
    one float weight (what made the first INT8 program float)."""
    skip_without("executorch")
    from executorch.backends.xnnpack.quantizer.xnnpack_quantizer import (
        XNNPACKQuantizer, get_symmetric_quantization_config)
    from executorch.exir.passes.constant_prop_pass import constant_prop_pass
    from torchao.quantization.pt2e.quantize_pt2e import convert_pt2e, prepare_pt2e

    from e3dpsm.export.executorch_export import fold_skip_targets

    toy, x = _ToyLinear().eval(), (torch.randn(4, 16),)
    quantizer = XNNPACKQuantizer().set_global(get_symmetric_quantization_config(is_per_channel=True))
    prepared = prepare_pt2e(torch.export.export(toy, x, strict=False).module(), quantizer)
    prepared(*x)
    program = torch.export.export(convert_pt2e(prepared), x, strict=False)
    folded = constant_prop_pass(program, custom_skip_targets=fold_skip_targets(quantized))
    tensors = [*folded.constants.values(), *folded.state_dict.values()]
    assert sum(t.dtype == torch.int8 and t.shape == (8, 16) for t in tensors) == int8_weights
