"""The committed benchmark checkpoints: what their recipes say they are, and loadable alone."""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

import pytest

from e3dpsm.checkpoint import load_checkpoint

CHECKPOINTS = Path(__file__).resolve().parents[1] / "benchmarks" / "checkpoints"


@pytest.mark.parametrize("name", sorted(p.name for p in CHECKPOINTS.iterdir() if p.is_dir()))
def test_checkpoint_matches_its_recipe_and_rebuilds_its_model(name) -> None:
    folder = CHECKPOINTS / name
    recipe = (folder / "recipe.md").read_text()
    digest = re.search(r"sha256 `([0-9a-f]{64})`", recipe).group(1)
    assert hashlib.sha256((folder / "checkpoint.pt").read_bytes()).hexdigest() == digest
    model, payload = load_checkpoint(folder / "checkpoint.pt")
    assert f"variant `{model.config.variant}`" in recipe and f"{payload['step']:,} steps" in recipe
