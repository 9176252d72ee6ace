"""Pruning surgery (e3dpsm/compress/surgery.py): exact when the removed channels contributed
nothing, couplings respected, and the pruned checkpoint rebuilds alone, on every variant."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import e3dpsm
from e3dpsm.checkpoint import load_checkpoint, save_checkpoint
from e3dpsm.compress.surgery import prune_model
from e3dpsm.compress.units import ATTN_BLOCK, DECODER_FFN, RES, prunable_units
from tests.conftest import sparse_lnes

VARIANTS = ("paper", "released", "small", "tiny")
# A small input keeps every variant cheap; the last stage's 2 x 3 map still samples in the
# variants with 4 points.
SIZE = dict(height=64, width=96)


def _randomised(variant: str) -> e3dpsm.E3DPSM:
    model = e3dpsm.create_model(variant, **SIZE).eval()
    gen = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for name, t in model.state_dict().items():
            # Nonzero statistics, biases and attention weights: a slicing error must show.
            if name.endswith("running_var"):
                t.copy_(torch.rand(t.shape, generator=gen) + 0.5)
            elif name.endswith(("running_mean", "bias")) or "attention_weights" in name or "sampling_offsets" in name:
                t.copy_(0.1 * torch.randn(t.shape, generator=gen))
    model.set_pose_prior(torch.linspace(-800.0, 1200.0, 48).view(16, 3))
    return model


def _keep_plan(model: e3dpsm.E3DPSM, seed: int = 0) -> dict[str, list[int]]:
    """About half of every unit's channels, one residual branch and one attention block gone."""
    rng = np.random.default_rng(seed)
    keep: dict[str, list[int]] = {}
    units = prunable_units(model.config)
    res = [u for u in units if u.kind == RES]
    attn = [u for u in units if u.kind == ATTN_BLOCK]
    for unit in units:
        if unit.kind == ATTN_BLOCK:
            keep[unit.name] = [] if unit is attn[1] else [0]
        elif unit.kind == RES and unit is res[1]:
            keep[unit.name] = []
        elif unit.kind == DECODER_FFN:
            for layer in range(model.config.decoder_layers):
                keep[f"decoder.layers.{layer}.ffn"] = sorted(rng.choice(unit.width, unit.width // 2 + 1, replace=False).tolist())
        else:
            keep[unit.name] = sorted(rng.choice(unit.width, max(1, unit.width // 2 - 1), replace=False).tolist())
    keep.pop(f"{attn[1].name}.ff")  # its block goes whole
    return keep


def _silence_removed(model: e3dpsm.E3DPSM, keep: dict[str, list[int]]) -> None:
    """Zero the outgoing weights of every channel `keep` drops (and a removed block's output
    bias), so that the removed channels contribute exactly nothing."""
    sd = model.state_dict()
    with torch.no_grad():
        for name, kept in keep.items():
            if name.startswith("decoder.layers."):
                width, out = model.config.decoder_ffn, [f"{name[:-4]}.linear2.weight"]
            elif name.startswith("attention.") and name.count(".") == 1:
                if not kept:
                    sd[f"{name}.proj_out.weight"].zero_()
                    sd[f"{name}.proj_out.bias"].zero_()
                continue
            elif name.endswith(".ff"):
                width, out = sd[f"{name}.proj_out.weight"].shape[1], [f"{name}.proj_out.weight"]
            elif name.endswith(".s5"):
                width = sd[f"{name}.c_re"].shape[1]
                out = [f"{name}.{n}" for n in ("c_re", "c_im", "cb_re", "cb_im") if f"{name}.{n}" in sd]
            else:  # residual block
                width, out = sd[f"{name}.conv2.weight"].shape[1], [f"{name}.conv2.weight"]
                if not kept:
                    sd[f"{name}.conv2.bias"].zero_()
            dropped = sorted(set(range(width)) - set(kept))
            for key in out:
                sd[key][:, dropped] = 0.0


@pytest.fixture(scope="module", params=VARIANTS)
def pruned_pair(request):
    model = _randomised(request.param)
    keep = _keep_plan(model)
    _silence_removed(model, keep)
    return model, prune_model(model, keep), keep


def test_pruned_model_steps_like_the_unpruned_one(pruned_pair):
    """Step by step (each model carrying its own, differently shaped state), at two windows."""
    model, pruned, keep = pruned_pair
    assert pruned.config.res_hidden and pruned.config.attn_removed  # something was cut
    frames = sparse_lnes((4, 1, 2, SIZE["height"], SIZE["width"]), seed=3)
    state_a, state_b = model.init_state(1), pruned.init_state(1)
    with torch.no_grad():
        for t, window in enumerate((20.0, 20.0, 50.0, 25.0)):
            out_a, state_a = model.step(frames[t], state_a, window)
            out_b, state_b = pruned.step(frames[t], state_b, window)
            for key in out_a:
                # float32 round-off at pose magnitude (~1e3 mm): sums over fewer terms reorder
                torch.testing.assert_close(out_b[key], out_a[key], rtol=1e-5, atol=2e-3)
    # The kept S5 modes carry exactly the unpruned model's values for those modes.
    for s in model.config.ssm_stages:
        kept = torch.as_tensor(keep[f"ssm.{s}.s5"])
        for part in ("re", "im"):
            name = f"s5_stage{s + 1}_{part}"
            torch.testing.assert_close(state_b[name], state_a[name][..., kept], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("causal", [True, False])
def test_pruned_model_sequence_like_the_unpruned_one(pruned_pair, causal):
    model, pruned, _ = pruned_pair
    frames = sparse_lnes((2, 3, 2, SIZE["height"], SIZE["width"]), seed=4)
    with torch.no_grad():
        out_a = model.forward_sequence(frames, causal=causal)
        out_b = pruned.forward_sequence(frames, causal=causal)
    for key in out_a:
        torch.testing.assert_close(out_b[key], out_a[key], rtol=1e-5, atol=2e-3)


def test_kept_channels_carry_the_unpruned_weights(pruned_pair):
    """The couplings, checked tensor by tensor with explicit indexing (independent of the
    surgery's slicer table): rows c and H + c of a GEGLU input, columns of the next layer."""
    model, pruned, keep = pruned_pair
    old, new = model.state_dict(), pruned.state_dict()
    for name, kept in keep.items():
        k = torch.as_tensor(kept, dtype=torch.long)
        if name.startswith("decoder.layers."):
            layer = name[:-4]
            assert torch.equal(new[f"{layer}.linear1.weight"], old[f"{layer}.linear1.weight"][k])
            assert torch.equal(new[f"{layer}.linear2.weight"], old[f"{layer}.linear2.weight"][:, k])
        elif name.startswith("attention.") and name.count(".") == 1:
            assert (f"{name}.proj_out.weight" in new) == bool(kept)
        elif name.endswith(".ff"):
            hidden = old[f"{name}.proj_out.weight"].shape[1]
            w_in = old[f"{name}.proj_in.weight"]
            assert torch.equal(new[f"{name}.proj_in.weight"], torch.cat([w_in[k], w_in[k + hidden]]))
            assert torch.equal(new[f"{name}.proj_out.weight"], old[f"{name}.proj_out.weight"][:, k])
        elif name.endswith(".s5"):
            for n in ("b_re", "b_im", "log_step", "lambda_im", "log_neg_lambda_re"):
                assert torch.equal(new[f"{name}.{n}"], old[f"{name}.{n}"][k])
            for n in ("c_re", "c_im"):
                assert torch.equal(new[f"{name}.{n}"], old[f"{name}.{n}"][:, k])
        elif kept:  # residual block
            assert torch.equal(new[f"{name}.conv1.weight"], old[f"{name}.conv1.weight"][k])
            assert torch.equal(new[f"{name}.norm2.running_var"], old[f"{name}.norm2.running_var"][k])
            assert torch.equal(new[f"{name}.conv2.weight"], old[f"{name}.conv2.weight"][:, k])
        else:
            assert f"{name}.conv1.weight" not in new
    # Everything outside the units is copied unchanged (the residual stream is never cut).
    for key in new:
        if key in old and new[key].shape == old[key].shape:
            continue
        assert any(key.startswith(n.replace(".ffn", "")) for n in keep), key


def test_state_layout_follows_the_pruned_widths(pruned_pair):
    model, pruned, keep = pruned_pair
    specs = {s.name: s.shape for s in pruned.state_spec()}
    for s in model.config.ssm_stages:
        h, w = model.config.stage_hw(s)
        assert specs[f"s5_stage{s + 1}_re"] == (h, w, len(keep[f"ssm.{s}.s5"]))


def test_pruned_checkpoint_rebuilds_alone(pruned_pair, tmp_path):
    """load_checkpoint and create_model(variant, **widths) rebuild it from its config alone."""
    _, pruned, _ = pruned_pair
    path = save_checkpoint(tmp_path / "pruned.pt", pruned)
    loaded, payload = load_checkpoint(path)
    assert loaded.config == pruned.config
    fields = {f.name: getattr(pruned.config, f.name) for f in dataclasses.fields(pruned.config) if f.name != "variant"}
    rebuilt = e3dpsm.create_model(pruned.config.variant, **fields)
    rebuilt.load_state_dict(pruned.state_dict(), strict=True)  # same tensor names and shapes
    frames = sparse_lnes((1, 2, 2, SIZE["height"], SIZE["width"]), seed=5)
    with torch.no_grad():
        want = pruned.eval().forward_sequence(frames)
        for other in (loaded, rebuilt.eval()):
            got = other.forward_sequence(frames)
            for key in want:
                torch.testing.assert_close(got[key], want[key], rtol=0, atol=0)


def test_bad_keep_lists_are_refused():
    model = e3dpsm.create_model("tiny", **SIZE)
    with pytest.raises(KeyError, match="not a prunable unit"):
        prune_model(model, {"stages.9.block1": [0]})
    with pytest.raises(ValueError, match="distinct"):
        prune_model(model, {"stages.0.block1": [0, 0]})
    with pytest.raises(ValueError, match="one keep list per layer"):
        prune_model(model, {"decoder.layers.0.ffn": [0, 1], "decoder.layers.9.ffn": [0]})
    with pytest.raises(ValueError, match="outside"):
        prune_model(model, {"attention.0.ff": []})  # a GEGLU keeps at least one channel
    # an index one past the last channel, of a unit and of a decoder layer
    width = model.config.res_hidden_width(0, 0)
    with pytest.raises(ValueError, match=rf"within \[0, {width}\)"):
        prune_model(model, {"stages.0.block1": [0, width]})
    ffn = model.config.decoder_ffn
    with pytest.raises(ValueError, match=rf"within \[0, {ffn}\)"):
        prune_model(model, {f"decoder.layers.{k}.ffn": [0, ffn] for k in range(model.config.decoder_layers)})


def test_macs_per_stage_groups_each_stage_with_its_s5_and_attention():
    """Each Conv2d/Linear's MACs land in its own stage (its residual convs, deformable block
    and S5 block), the rest in the stem or the decoder and heads; nothing is lost."""
    from e3dpsm.compress.plan import count_macs, macs_per_stage

    model = e3dpsm.create_model("small", **SIZE)
    per_module = count_macs(model)
    groups = macs_per_stage(model)
    assert sum(groups.values()) == sum(per_module.values())
    for s in model.config.ssm_stages:
        ssm = sum(v for k, v in per_module.items() if k.startswith(f"ssm.{s}."))
        rest = sum(v for k, v in per_module.items() if k.startswith((f"stages.{s}.", f"attention.{s}.")))
        assert ssm > 0 and groups[f"stage{s + 1}"] == ssm + rest


def test_unpruned_configs_read_back_unchanged():
    """Configs written before pruning existed (no pruned fields) build the same model."""
    for variant in VARIANTS:
        cfg = e3dpsm.create_model(variant).config.to_dict()
        for field in ("res_hidden", "attn_ff_hidden", "attn_removed", "ssm_ff_hidden", "ssm_state_dims"):
            cfg.pop(field)
        model = e3dpsm.E3DPSM(e3dpsm.E3DPSMConfig.from_dict(cfg))
        ref = e3dpsm.create_model(variant)
        assert {k: v.shape for k, v in model.state_dict().items()} == {k: v.shape for k, v in ref.state_dict().items()}


def test_pruned_tiny_exports_with_parity(tmp_path):
    """The pruned model's step graph (state layout from the pruned widths) follows its PyTorch
    step to 0.01 mm at three window lengths."""
    from e3dpsm.export import export_step
    from e3dpsm.export.parity import Tolerances, run_parity
    from e3dpsm.runtime.session import StepSession

    model = _randomised("tiny")
    pruned = prune_model(model, _keep_plan(model)).eval()
    graph = export_step(pruned, tmp_path / "pruned.onnx")
    session = StepSession(graph, threads=1)
    assert session.init_state(1)["s5_stage1_re"].shape[-1] == pruned.config.ssm_state_dims[0]
    frames = sparse_lnes((12, 2, SIZE["height"], SIZE["width"]), seed=6).numpy()
    for window in (20.0, 25.0, 50.0):
        report = run_parity(pruned, session, frames, window, Tolerances(pose_atol_mm=0.01))
        assert report.passed, report.lines()


def test_refusals_say_what_is_wrong_and_how_to_fix_it():
    """Each refusal's whole message (a user reads it to fix the keep lists)."""
    model = e3dpsm.create_model("tiny", **SIZE)
    width = model.config.res_hidden_width(0, 0)
    # a KeyError's text is the repr of its message, which quotes a unit's name: hence the "
    with pytest.raises(KeyError, match=r"^\"'stages.9.block1' is not a prunable unit of this model; units: \['attention.0', "):
        prune_model(model, {"stages.9.block1": [0]})
    with pytest.raises(ValueError, match=rf"^unit stages.0.block1: keep indices must be distinct, within \[0, {width}\)$"):
        prune_model(model, {"stages.0.block1": [0, 0]})
    with pytest.raises(ValueError, match=r"^attention.0: an attention block is kept \(\[0\]\) or removed \(\[\]\) whole$"):
        prune_model(model, {"attention.0": [0, 1]})
    with pytest.raises(ValueError, match=r"^decoder.ffn is cut per layer: pass decoder.layers.\{l\}.ffn keep lists$"):
        prune_model(model, {"decoder.ffn": [0, 1]})
    ffn = model.config.decoder_ffn
    with pytest.raises(ValueError, match=rf"^decoder.layers.0.ffn: keep indices must be distinct, within \[0, {ffn}\)$"):
        prune_model(model, {"decoder.layers.0.ffn": [0, ffn]})


def test_decoder_keep_lists_need_every_layer_and_one_length():
    """`small` has several decoder layers: every layer named but the lengths differ, or one
    length but a layer missing, are each refused."""
    model = e3dpsm.create_model("small", **SIZE)
    layers = model.config.decoder_layers
    assert layers >= 2
    message = (rf"^the decoder feed-forward needs one keep list per layer \({layers}\), "
               r"all of one length \(decoder_ffn is one number\)$")
    uneven = {f"decoder.layers.{k}.ffn": list(range(k + 1)) for k in range(layers)}
    with pytest.raises(ValueError, match=message):
        prune_model(model, uneven)
    with pytest.raises(ValueError, match=message):
        prune_model(model, {f"decoder.layers.{k}.ffn": [0, 1] for k in range(layers - 1)})


def test_units_named_after_the_decoder_are_cut_too():
    """The keep lists are read in any order: a residual block named after the decoder's layers
    is pruned as well."""
    model = e3dpsm.create_model("tiny", **SIZE)
    keep = {"decoder.layers.0.ffn": [0, 1, 2], "stages.0.block1": [1, 3]}
    pruned = prune_model(model, keep)
    assert pruned.config.decoder_ffn == 3 and pruned.config.res_hidden_width(0, 0) == 2
    assert torch.equal(pruned.stages[0].block1.conv1.weight, model.stages[0].block1.conv1.weight[[1, 3]])


def test_a_coupling_the_surgery_does_not_know_fails_loudly(monkeypatch):
    """A unit whose tensors the slicers miss leaves a tensor at its old shape: the surgery
    names it rather than loading a model that computes something else."""
    import e3dpsm.compress.surgery as surgery

    monkeypatch.setattr(surgery, "unit_slicers", lambda model, unit, keep: {})
    model = e3dpsm.create_model("tiny", **SIZE)
    width = model.config.res_hidden_width(0, 0)
    with pytest.raises(RuntimeError, match=rf"^surgery left stages.0.block1.conv1.weight at \({width}, "
                                           r"[0-9]+, 3, 3\), the pruned model needs \(2, [0-9]+, 3, 3\)$"):
        prune_model(model, {"stages.0.block1": [0, 1]})
