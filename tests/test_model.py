"""Model contract: variants, gradients, streaming exactness, long rollouts, bad input."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import e3dpsm
from e3dpsm.errors import ConfigError, InputError
from tests.conftest import sparse_lnes

PAPER_PARAMS = 6.64e6


@pytest.mark.parametrize("name", ["tiny", "small", "paper"])
def test_variant_forward_backward_every_parameter_gets_gradient(name: str) -> None:
    model = e3dpsm.create_model(name).train()
    lnes = sparse_lnes((2, 3, 2, 192, 256), seed=1)
    out = model.forward_sequence(lnes, causal=False)
    for key in ("pose", "pose_direct", "pose_delta"):
        assert out[key].shape == (2, 3, 16, 3)
        assert torch.isfinite(out[key]).all()
    loss = sum(out[k].square().mean() for k in out)
    loss.backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not missing, f"parameters without a finite gradient: {missing}"
    zero = [n for n, p in model.named_parameters() if p.grad.abs().sum() == 0]
    assert not zero, f"parameters whose gradient is identically zero: {zero}"


def test_paper_variant_matches_released_parameter_count() -> None:
    params = e3dpsm.create_model("paper").num_parameters()
    assert abs(params - PAPER_PARAMS) / PAPER_PARAMS < 0.05, params


# The counts each variant's docstring states (e3dpsm/models/variants.py), at 192 x 256.
DOCUMENTED_PARAMS = {"paper": 6_648_662, "released": 6_640_406 + 96, "small": 1_474_790, "tiny": 94_610}


@pytest.mark.parametrize("variant", sorted(DOCUMENTED_PARAMS))
def test_num_parameters_is_the_documented_count(variant: str) -> None:
    model = e3dpsm.create_model(variant)
    assert model.num_parameters() == DOCUMENTED_PARAMS[variant]
    # Buffers (the pose prior, the fixed grids) are state, not parameters.
    assert sum(b.numel() for b in model.buffers()) > 0


@pytest.mark.parametrize("window_ms", [20.0, 50.0])
def test_step_by_step_equals_causal_sequence(tiny_model, window_ms: float) -> None:
    lnes = sparse_lnes((1, 64, 2, 192, 256), seed=2)
    with torch.no_grad():
        whole = tiny_model.forward_sequence(lnes, causal=True, window_ms=window_ms)
        state = tiny_model.init_state(1)
        steps = []
        for t in range(lnes.shape[1]):
            out, state = tiny_model.step(lnes[:, t], state, window_ms)
            steps.append(out)
    for key in whole:
        stepped = torch.stack([o[key] for o in steps], dim=1)
        assert (stepped - whole[key]).abs().max().item() <= 1e-3, key


def test_chunked_runs_equal_whole_run(tiny_model) -> None:
    lnes = sparse_lnes((1, 40, 2, 192, 256), seed=3)
    with torch.no_grad():
        whole, whole_state = tiny_model.forward_sequence(lnes, causal=True, return_state=True)
        state, chunks = None, []
        for start, stop in ((0, 7), (7, 25), (25, 40)):
            out, state = tiny_model.forward_sequence(lnes[:, start:stop], causal=True, state=state, return_state=True)
            chunks.append(out["pose"])
    assert (torch.cat(chunks, 1) - whole["pose"]).abs().max().item() <= 1e-3
    for name, value in whole_state.items():
        assert torch.allclose(state[name], value, rtol=1e-5, atol=1e-5), name


def test_carried_state_has_an_effect(tiny_model) -> None:
    """Guard against the released code's defect: the same frames after a different history
    must give different outputs, in the S5 part alone as well as through the fusion."""
    history_a, history_b = sparse_lnes((1, 10, 2, 192, 256), seed=4), sparse_lnes((1, 10, 2, 192, 256), seed=5)
    probe = sparse_lnes((1, 5, 2, 192, 256), seed=6)
    with torch.no_grad():
        outs = []
        for history in (history_a, history_b):
            _, state = tiny_model.forward_sequence(history, causal=True, return_state=True)
            # Reset the fusion so that only the S5 state differs between the two runs.
            fresh = tiny_model.init_state(1)
            state = {k: (v if k.startswith("s5_") else fresh[k]) for k, v in state.items()}
            outs.append(tiny_model.forward_sequence(probe, causal=True, state=state)["pose_direct"])
    assert (outs[0] - outs[1]).abs().max().item() > 1e-3


def test_window_length_changes_the_dynamics(tiny_model) -> None:
    lnes = sparse_lnes((1, 12, 2, 192, 256), seed=7)
    with torch.no_grad():
        a = tiny_model.forward_sequence(lnes, causal=True, window_ms=20.0)["pose_direct"]
        b = tiny_model.forward_sequence(lnes, causal=True, window_ms=50.0)["pose_direct"]
    assert (a - b).abs().max().item() > 1e-3


def _check_bounded(peak: dict[str, float], pose: np.ndarray) -> None:
    assert np.isfinite(pose).all()
    assert np.abs(pose).max() < 1e5
    for name, value in peak.items():
        assert value < 1e5, (name, value)


@pytest.mark.parametrize("steps", [2_000, pytest.param(10_000, marks=pytest.mark.slow)])
def test_long_rollout_of_the_step_graph_stays_finite_and_bounded(steps: int, tmp_path) -> None:
    """`steps` steps (2,000: 40 s of stream at 20 ms) of the exported step graph, the form
    that ships, with states carried on random sparse LNES (a bank of frames cycled in random
    order, so the input never settles into a fixed point). A 64 x 96 input keeps the run
    short; the recurrent parts (S5 modes, fusion) are the same as at full size. ONNX Runtime
    steps it in 3 ms on one thread where PyTorch's eager step takes 14 (its own run below is
    slow); the graph computes PyTorch's step (test_export.py's rollout parity)."""
    from e3dpsm.export import export_step
    from e3dpsm.runtime import StepSession

    model = e3dpsm.create_model("tiny", height=64, width=96).eval()
    session = StepSession(export_step(model, tmp_path / "tiny_64x96.onnx"), threads=1)
    bank = sparse_lnes((64, 2, 64, 96), density=0.02, seed=8).numpy()
    order = torch.randint(0, 64, (steps,), generator=torch.Generator().manual_seed(0)).tolist()
    state = session.init_state(1)
    peak = {name: 0.0 for name in state}
    for i in order:
        out, state = session.step(bank[i : i + 1], state, 20.0)
        for name, value in state.items():
            peak[name] = max(peak[name], float(np.abs(value).max()))
    _check_bounded(peak, out["pose"])


@pytest.mark.slow
@pytest.mark.parametrize("steps", [2_000, 10_000])
def test_long_rollout_stays_finite_and_bounded(steps: int) -> None:
    """PyTorch's own step over the long stream of the test above (14 ms a step on 2 cores)."""
    tiny_model = e3dpsm.create_model("tiny", height=64, width=96).eval()
    bank = sparse_lnes((64, 2, 64, 96), density=0.02, seed=8)
    order = torch.randint(0, 64, (steps,), generator=torch.Generator().manual_seed(0))
    state = tiny_model.init_state(1)
    peak = {name: 0.0 for name in state}
    with torch.no_grad():
        for i in order.tolist():
            out, state = tiny_model.step(bank[i : i + 1], state, 20.0)
            for name, value in state.items():
                peak[name] = max(peak[name], value.abs().max().item())
    _check_bounded(peak, out["pose"].numpy())


def test_unknown_variant_lists_the_known_ones() -> None:
    with pytest.raises(ConfigError, match="paper.*small.*tiny|available variants"):
        e3dpsm.create_model("huge")


def test_unknown_override_is_refused() -> None:
    with pytest.raises(ConfigError, match="unknown config fields"):
        e3dpsm.create_model("tiny", widthz=(8, 8, 8, 8))


@pytest.mark.parametrize(
    "lnes, message",
    [
        (torch.zeros(1, 2, 96, 128), r"shape \[1, 2, 96, 128\], expected \[B, 2, 192, 256\]"),
        (torch.zeros(1, 2, 192, 256, dtype=torch.float64), "dtype torch.float64, expected torch.float32"),
        (torch.zeros(2, 192, 256), "expected \\[B, 2, 192, 256\\]"),
    ],
)
def test_bad_lnes_is_refused(tiny_model, lnes, message) -> None:
    with pytest.raises(InputError, match=message):
        tiny_model.step(lnes, tiny_model.init_state(lnes.shape[0] if lnes.dim() == 4 else 1), 20.0)


def test_bad_state_is_refused(tiny_model) -> None:
    lnes = torch.zeros(1, 2, 192, 256)
    state = tiny_model.init_state(1)
    missing = {k: v for k, v in state.items() if k != "fusion_pose"}
    with pytest.raises(InputError, match="missing \\['fusion_pose'\\]"):
        tiny_model.step(lnes, missing, 20.0)
    wrong = dict(state, fusion_pose=torch.zeros(1, 15, 3))
    with pytest.raises(InputError, match="'fusion_pose' has shape \\[1, 15, 3\\], expected \\[1, 16, 3\\]"):
        tiny_model.step(lnes, wrong, 20.0)


@pytest.mark.parametrize(
    "overrides",
    [
        {"ssm_stages": ()},                 # no SSM
        {"ssm_stages": (3,)},               # one SSM (stage 4)
        {"ssm_stages": (1, 3)},             # the paper text's placement
        {"deformable": False},              # no deformable attention
        {"fusion": "naive"}, {"fusion": "direct"}, {"fusion": "static"},
        {"ssm_discretization": "zoh"},
    ],
)
def test_ablation_switches_keep_streaming_exact(overrides) -> None:
    model = e3dpsm.create_model("tiny", **overrides).eval()
    lnes = sparse_lnes((1, 6, 2, 192, 256), seed=9)
    with torch.no_grad():
        whole = model.forward_sequence(lnes, causal=True)["pose"]
        state, steps = model.init_state(1), []
        for t in range(6):
            out, state = model.step(lnes[:, t], state, 20.0)
            steps.append(out["pose"])
    assert (torch.stack(steps, 1) - whole).abs().max().item() <= 1e-3
    names = {s.name for s in model.state_spec()}
    assert ("fusion_cov" in names) == (overrides.get("fusion", "learned") in ("learned", "static"))
    assert sum(n.startswith("s5_") for n in names) == 2 * len(overrides.get("ssm_stages", (0, 3)))


RELEASED_LAYOUT = dict(attn_layout="1d", input_norm="minmax", ssm_backward_first_frame="own_input", pose_unit_mm=1.0)


def test_released_layout_streams_exactly_and_survives_empty_frames() -> None:
    """The `released` computation at tiny size: stepping equals the causal sequence (per-frame
    min-max rescaling in both), chunks equal the whole run, and an empty frame (the release
    would divide by zero) gives finite poses."""
    model = e3dpsm.create_model("tiny", **RELEASED_LAYOUT).eval()
    # two streams whose frames span different ranges: the rescaling is per frame and stream
    lnes = sparse_lnes((2, 12, 2, 192, 256), seed=13) * torch.linspace(0.3, 1.0, 12).view(1, 12, 1, 1, 1)
    lnes[1] *= 0.5
    lnes[:, 5] = 0.0  # a window without events
    with torch.no_grad():
        whole, whole_state = model.forward_sequence(lnes, causal=True, return_state=True)
        state, steps = model.init_state(2), []
        for t in range(lnes.shape[1]):
            out, state = model.step(lnes[:, t], state)
            steps.append(out["pose"])
        first, mid = model.forward_sequence(lnes[:, :4], causal=True, return_state=True)
        rest = model.forward_sequence(lnes[:, 4:], causal=True, state=mid)
    assert torch.isfinite(whole["pose"]).all()
    assert (torch.stack(steps, 1) - whole["pose"]).abs().max().item() <= 1e-3
    assert (torch.cat([first["pose"], rest["pose"]], 1) - whole["pose"]).abs().max().item() <= 1e-3
    for name, value in whole_state.items():
        assert torch.allclose(state[name], value, rtol=1e-5, atol=1e-5), name


class _HostTensorLog(TorchDispatchMode):
    """Records the ops that bring a tensor built from Python values into the graph
    (`torch.tensor(...)`, `x.new_tensor(...)`): made on the host, each is a synchronous
    host-to-device copy per call on a GPU, and CUDA graph capture refuses it."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        if func in (torch.ops.aten.lift_fresh.default, torch.ops.aten.lift_fresh_copy.default):
            self.seen.append(str(func))
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("name", e3dpsm.list_models())
def test_step_builds_no_tensor_from_python_values(name: str) -> None:
    # A window given as a tensor, as the exported graph and the GPU benchmark give it.
    model = e3dpsm.create_model(name).eval()
    cfg = model.config
    lnes = sparse_lnes((1, 2, cfg.height, cfg.width), seed=3)
    state, window = model.init_state(1), torch.tensor([20.0])
    log = _HostTensorLog()
    with torch.inference_mode(), log:
        model.step(lnes, state, window)
    assert not log.seen, f"step() makes tensors from Python values ({len(log.seen)}x): keep constants in buffers"
