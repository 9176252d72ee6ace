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


def test_pruned_small_has_at_most_half_the_macs_of_small() -> None:
    """benchmarks/checkpoints/small_pruned (e3dpsm prune): its config records the cut widths,
    `create_model` rebuilds it alone, and it counts at most half the MACs of the trained small."""
    import dataclasses

    import e3dpsm
    from e3dpsm.compress.plan import total_macs

    pruned, payload = load_checkpoint(CHECKPOINTS / "small_pruned" / "checkpoint.pt")
    small, _ = load_checkpoint(CHECKPOINTS / "small" / "checkpoint.pt")
    assert pruned.config.variant == "small" and pruned.config.res_hidden  # pruned widths recorded
    fields = {f.name: getattr(pruned.config, f.name) for f in dataclasses.fields(pruned.config) if f.name != "variant"}
    e3dpsm.create_model("small", **fields).load_state_dict(pruned.state_dict(), strict=True)
    assert total_macs(pruned) <= 0.5 * total_macs(small)
    assert payload["prune"]["source"].endswith("small/checkpoint.pt")
