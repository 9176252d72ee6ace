"""Golden rollouts: record a reference rollout once, check any graph against it anywhere
(torch-free), and diagnose where a compressed graph departs from its reference."""
from e3dpsm.golden.check import GoldenCheck, TensorCheck, check_golden
from e3dpsm.golden.store import GoldenRecord, load_golden
from e3dpsm.golden.tolerances import PROFILES, ToleranceProfile
from e3dpsm.golden.verify import verify_graph

__all__ = ["PROFILES", "GoldenCheck", "GoldenRecord", "TensorCheck", "ToleranceProfile", "check_golden",
           "load_golden", "verify_graph"]
