"""The released importer's Kalman identity check at its edge: F, B and H must be the
identity, off the diagonal too. The element-wise filter of this project is exact only for
A = B = H = I; an off-diagonal coupling would be silently dropped."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import e3dpsm
from e3dpsm.errors import CheckpointError
from e3dpsm.importers.released import KALMAN_IDENTITIES, KALMAN_PREFIX, import_released, read_released_state_dict
from tests.fixtures.released.weights import make_state_dict

FIXTURE = Path(__file__).parent / "fixtures" / "released"


@pytest.fixture(scope="module")
def released(tmp_path_factory) -> dict[str, torch.Tensor]:
    """The fixture's released weights, read back as the importer reads a file (prefixes stripped)."""
    manifest = json.loads((FIXTURE / "manifest.json").read_text())
    path = tmp_path_factory.mktemp("released_edges") / "plain.pt"
    torch.save(make_state_dict(manifest["layout"], manifest["seed"]), path)
    state, _ = read_released_state_dict(path)
    return state


@pytest.fixture(scope="module")
def model() -> torch.nn.Module:
    return e3dpsm.create_model("released").eval()


def test_exact_identities_are_accepted(released, model):
    result = import_released(released, model)
    for name in KALMAN_IDENTITIES:
        assert torch.equal(released[f"{KALMAN_PREFIX}{name}"], torch.eye(48))
        assert result.checks[f"kalman_{name}_identity"] is True


@pytest.mark.parametrize("name", KALMAN_IDENTITIES)
@pytest.mark.parametrize("value", [1.0, 1e-6])
def test_one_off_diagonal_element_is_refused(released, model, name, value):
    """The diagonal is all ones, so a diagonal-only comparison would accept it."""
    key = f"{KALMAN_PREFIX}{name}"
    coupled = torch.eye(48)
    coupled[0, 3] = value  # x of joint 0 driven by x of joint 1
    assert torch.equal(torch.diagonal(coupled), torch.ones(48))
    with pytest.raises(CheckpointError, match=f"{key} is not the 48x48 identity"):
        import_released({**released, key: coupled}, model)
