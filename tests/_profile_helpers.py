"""Fixture shared by test_flops.py and test_profiles.py: one tiny step-graph export per session.

Each test module imports the fixture, which makes two fixture definitions; the export itself
is cached here so the session pays for it once.
"""
from __future__ import annotations

import functools
from pathlib import Path

import pytest


@functools.lru_cache(maxsize=None)
def _export_tiny(folder: Path, model) -> Path:
    from e3dpsm.export import export_step

    folder.mkdir(parents=True, exist_ok=True)
    return export_step(model, folder / "tiny.onnx")


@pytest.fixture(scope="session")
def tiny_step_graph(tmp_path_factory, tiny_model) -> Path:
    return _export_tiny(tmp_path_factory.getbasetemp() / "profiles_tiny", tiny_model)


@pytest.fixture(scope="session")
def tiny_static_graph(tmp_path_factory, tiny_model, tiny_step_graph) -> Path:
    """tiny_model's static-batch graph, made as `e3dpsm profile` makes it for a static target
    (exported and held to the PyTorch model's parity on 8 carried steps)."""
    from e3dpsm.profiles.graphs import add_static_graph
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import STATIC_FP32, load_targets

    folder = tmp_path_factory.getbasetemp() / "profiles_tiny_static"
    folder.mkdir(parents=True, exist_ok=True)
    frames = moving_edge_frames(8, 192, 256, 20.0, seed=1)
    graphs = add_static_graph(tiny_model, folder, [load_targets()["ort-cpu-fp32-static"]],
                              {"fp32": tiny_step_graph, STATIC_FP32: None}, frames.lnes, frames.window_ms)
    return graphs[STATIC_FP32]
