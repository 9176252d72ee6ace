"""The paper's ablations as model-config overrides (paper, ablation table): one name per
row, shared by `e3dpsm train --ablation` and `e3dpsm ablation`."""
from __future__ import annotations

from typing import Any

from e3dpsm.errors import ConfigError

ABLATIONS: dict[str, dict[str, Any]] = {
    "full": {},                              # learned Kalman fusion, S5 blocks
    "naive_fusion": {"fusion": "naive"},     # previous fused pose + delta: drifts
    "direct_only": {"fusion": "direct"},     # the direct pose alone: jitters
    "static_fusion": {"fusion": "static"},   # Kalman filter with Q, R frozen at their init
    "no_ssm": {"ssm_stages": ()},            # no temporal state in the encoder
}


def ablation_overrides(name: str) -> dict[str, Any]:
    try:
        return dict(ABLATIONS[name])
    except KeyError:
        raise ConfigError(f"unknown ablation {name!r}; choose from {list(ABLATIONS)}") from None
