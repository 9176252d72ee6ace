"""Golden checks inside your own test suite.

    from e3dpsm.testing import assert_golden

    def test_int8_graph_matches_golden(tmp_path):
        assert_golden("deploy/step_int8.onnx", "deploy/golden", profile="int8", out_dir=tmp_path)

Or, with `pytest_plugins = ["e3dpsm.testing"]` in your conftest.py, the `e3dpsm_golden`
fixture: `e3dpsm_golden("deploy/step.onnx", "deploy/golden")` writes its check.json and
plot under the test's tmp_path. Torch-free, like `e3dpsm golden check`.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Sequence

from e3dpsm.golden.check import GoldenCheck


class GoldenMismatch(AssertionError):
    """The graph left the golden rollout's tolerances; `result` holds every tensor's errors."""

    def __init__(self, message: str, result: GoldenCheck) -> None:
        super().__init__(message)
        self.result = result


def assert_golden(model_path: str | os.PathLike, golden_dir: str | os.PathLike, profile: str | None = None, *,
                  runtime: str = "onnxruntime", providers: Sequence[str] | None = None, threads: int | None = 2,
                  budget_pct: float | None = None, out_dir: str | os.PathLike | None = None) -> GoldenCheck:
    """Raise `GoldenMismatch` (an AssertionError) naming the first failing step and tensor;
    return the check's result when the graph passes. `profile` defaults to the graph's own
    precision (fp32, fp16 or int8, from its metadata)."""
    from e3dpsm.golden.verify import verify_graph

    result, _ = verify_graph(model_path, golden_dir, out_dir, runtime=runtime, providers=providers, threads=threads,
                             profile=profile, budget_pct=budget_pct)
    if not result.passed:
        failing = [t.line().strip() for t in result.tensors if not t.passed][:3]
        raise GoldenMismatch(f"{Path(model_path).name} vs golden {golden_dir} on {runtime}: {result.summary()}\n  "
                             + "\n  ".join(failing), result)
    return result


try:
    import pytest
except ImportError:  # pragma: no cover - pytest is only needed for the fixture
    pytest = None

if pytest is not None:
    @pytest.fixture
    def e3dpsm_golden(tmp_path: Path) -> Callable[..., GoldenCheck]:
        """`e3dpsm_golden(model, golden, profile=None, **kwargs)`: assert_golden writing its
        check.json and check.png under the test's tmp_path."""
        def check(model_path: str | os.PathLike, golden_dir: str | os.PathLike, profile: str | None = None,
                  **kwargs: Any) -> GoldenCheck:
            kwargs.setdefault("out_dir", tmp_path / f"golden-{Path(model_path).stem}")
            return assert_golden(model_path, golden_dir, profile, **kwargs)

        return check
