"""Session-scoped data and graphs shared by test_quantize.py and test_validate.py."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

import e3dpsm
from e3dpsm.camera import ee3d_default
from e3dpsm.data.layout import write_dataset_index, write_synthetic_sequence
from e3dpsm.data.prepare import prepare_dataset
from e3dpsm.data.synth.generator import SynthConfig, generate_sequence

if TYPE_CHECKING:
    from e3dpsm.budget import TaskBudget
    from e3dpsm.quantize import QuantizeOptions

SPLITS = {"train": ["seq_0000", "seq_0001"], "val": ["seq_0002"], "test": ["seq_0003"]}
TRAINED_TINY = Path(__file__).parent / "fixtures" / "tiny_trained" / "checkpoint.pt"
# One ONNX Runtime intra-op thread (a default session adds a pool thread per core that spins
# between steps, against the test itself under `pytest -n`), few frames per stage and 10 steps
# for the verdict's timing: the tests check what a graph computes, never how fast (benchmarks do).
FAST_ADVANCED = dict(search_frames=40, rank_frames=20, max_trials=8, timing_steps=10)


def fast(**fields) -> "QuantizeOptions":
    """QuantizeOptions for the tests: top-level and advanced fields by name, the fast defaults
    (16 calibration frames, one thread) where not given."""
    from e3dpsm.quantize import Advanced, QuantizeOptions

    advanced = {k: fields.pop(k) for k in list(fields) if k in Advanced.__dataclass_fields__}
    fields.setdefault("frames", 16)
    fields.setdefault("threads", 1)
    return QuantizeOptions(**fields, advanced=Advanced(**{**FAST_ADVANCED, **advanced}))


def make_prepared(root: Path, seconds: float = 1.0) -> Path:
    """Four short synthetic sequences (2 train, 1 val, 1 test), prepared at 20 ms, 192 x 256.
    Coarse rendering keeps it to a few seconds; the events are still real simulator output."""
    raw, prepared = root / "raw", root / "prepared"
    camera = ee3d_default()
    config = SynthConfig(seed=7, seconds=seconds, render_hz=50, render_scale=0.25)
    for index in range(4):
        seq, _ = generate_sequence(config, index, camera)
        write_synthetic_sequence(raw / seq.name, seq, camera.to_json())
    write_dataset_index(raw, SPLITS, {"seed": 7})
    prepare_dataset(raw, prepared, window_ms=20.0, progress=False)
    return prepared


def mean_pose_model(data: Path, **overrides) -> torch.nn.Module:
    """The tiny variant with its pose prior at the training split's mean pose."""
    from e3dpsm.data.prepared import PreparedData

    train = PreparedData.open(data).split("train")
    mean = np.concatenate([s.j3d_mm for s in train]).mean(axis=0)
    model = e3dpsm.create_model("tiny", **overrides).eval()
    model.set_pose_prior(torch.from_numpy(mean.astype(np.float32)))
    return model


@pytest.fixture(scope="session")
def quant_data(tmp_path_factory) -> Path:
    return make_prepared(tmp_path_factory.mktemp("quant_data"))


@pytest.fixture(scope="session")
def tiny_graph(tmp_path_factory, quant_data) -> Path:
    from e3dpsm.export import export_step

    return export_step(mean_pose_model(quant_data), tmp_path_factory.mktemp("graphs") / "tiny.onnx")


@pytest.fixture(scope="session")
def trained_graph(tmp_path_factory) -> Path:
    """The trained tiny of tests/fixtures/tiny_trained: poses that follow the input, for the
    tests whose budgets would be vacuous on a model sitting at its pose prior."""
    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.export import export_step

    model, _ = load_checkpoint(TRAINED_TINY, variant="tiny")
    return export_step(model, tmp_path_factory.mktemp("graphs") / "tiny_trained.onnx")


@pytest.fixture(scope="session")
def calibrated_tiny(tmp_path_factory, trained_graph, quant_data) -> dict:  # noqa: F811
    """The trained tiny pre-processed at opset 21 (16-bit Q/DQ possible) and calibrated with
    min-max ranges on 16 `train` frames: {"pre", "cache", "feeds"}, for the tests that drive
    `quantize_int8` directly (write outputs to a folder of your own)."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.calibration import record_calibration_set
    from e3dpsm.quantize.static import StaticConfig, calibrate, ensure_opset, preprocess

    work = tmp_path_factory.mktemp("calibrated_tiny")
    pre = work / "pre.onnx"
    preprocess(trained_graph, pre)
    assert ensure_opset(pre)  # the export is at 17
    calib = record_calibration_set(trained_graph, PreparedData.open(quant_data).split("train"), 16, 20.0, threads=1)
    cache = work / "cache.json"
    calibrate(pre, StaticConfig(), calib, cache)
    return {"pre": pre, "cache": cache, "feeds": calib.feeds}


@pytest.fixture(scope="session")
def full_integer_dir(tmp_path_factory, trained_graph, quant_data) -> Path:  # noqa: F811
    """The trained tiny in INT8, every Conv/MatMul/Gemm outside the recurrence at 8 bits (no search)."""
    from e3dpsm.quantize import quantize_graph

    out = tmp_path_factory.mktemp("q") / "full_integer"
    quantize_graph(trained_graph, quant_data, out, fast(mode="int8", exclude="recurrent"))
    return out


@pytest.fixture(scope="session")
def int8_test_budget(full_integer_dir, trained_graph, quant_data) -> "TaskBudget":  # noqa: F811
    """A budget the full-integer graph misses on the search split, measured on this host, so
    that the search has work to do on every kind of CPU (INT8 error depends on the kernels:
    e3dpsm/utils/isa.py): half the largest upper bound of its task metrics, the other limits wide."""
    from e3dpsm.budget import TaskBudget
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.holdout import held_out, judge

    search = held_out(trained_graph, PreparedData.open(quant_data).split("val"), 20.0,
                      FAST_ADVANCED["search_frames"], "val", threads=1)
    check = judge(full_integer_dir / "step_int8.onnx", search, TaskBudget(), ("onnxruntime",), threads=1).worst
    worst = max(check.metrics, key=lambda m: m.upper_pct)
    assert worst.upper_pct > 0, "quantising the trained tiny raised none of its task metrics"
    limits = {"mpjpe_pct": 100.0, "pa_mpjpe_pct": 100.0, "jitter_pct": 100.0}
    limits[f"{worst.name}_pct"] = round(worst.upper_pct / 2, 4)
    return TaskBudget(**limits)


@pytest.fixture(scope="session")
def int8_dir(tmp_path_factory, trained_graph, quant_data, int8_test_budget) -> Path:  # noqa: F811
    """The trained tiny quantised to INT8 by the default search under the test budget (shared
    by the quantise and golden tests)."""
    from e3dpsm.quantize import quantize_graph

    out = tmp_path_factory.mktemp("q") / "int8"
    quantize_graph(trained_graph, quant_data, out, fast(mode="int8", budget=int8_test_budget))
    return out


@pytest.fixture(scope="session")
def fp16_dir(tmp_path_factory, trained_graph, quant_data) -> Path:  # noqa: F811
    from e3dpsm.quantize import quantize_graph

    out = tmp_path_factory.mktemp("q") / "fp16"
    quantize_graph(trained_graph, quant_data, out, fast(mode="fp16"))
    return out
