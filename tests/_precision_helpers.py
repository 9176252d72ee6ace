"""Injected plans and graph errors for the recurrent-projection stage of the precision search
(quantize/precision.py `quantise_recurrent_compute`), shared by its tests."""
from __future__ import annotations

from e3dpsm.quantize.precision import PrecisionChoice, PrecisionPlan


def recurrent_plan(error: float = 0.5, target: float = 0.7) -> PrecisionPlan:
    return PrecisionPlan(["x"], ["f"], error, [PrecisionChoice("x", "int16", "fits", {"int16": 0.4})],
                         [{"label": "int16_all"}], target_pct=target, int16w16=["w"])


def recurrent_evaluator(cost16: dict[str, float], cost_w16: dict[str, float], base: float = 0.5,
                        cost8: dict[str, float] | None = None):
    """A graph error from injected per-node costs at each precision (float costs nothing);
    8 bits cost 1.0 per node unless `cost8` says otherwise (nothing fits there by default)."""
    cost8 = cost8 if cost8 is not None else dict.fromkeys(cost16, 1.0)

    def evaluate(int16: list[str], w16: list[str], floats: list[str], label: str, int8: list[str] = ()) -> float:
        # The plan's own decisions always carried along, each recurrent node in exactly one list.
        assert int16[0] == "x" and w16[:1] == ["w"] and floats[0] == "f"
        recurrent = [*int16[1:], *w16[1:], *floats[1:], *int8]
        assert sorted(recurrent) == sorted(cost16), recurrent
        return (base + sum(cost16[n] for n in int16[1:]) + sum(cost_w16[n] for n in w16[1:])
                + sum(cost8[n] for n in int8))
    return evaluate
