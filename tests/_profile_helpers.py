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
