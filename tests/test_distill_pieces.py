"""The pieces of distillation (compress/distill.py) without data: the config's refusals and
edges, the loss's terms and weights by hand, the pair check, and the lanes a streamed batch
restarts. The runs themselves are in test_distill.py."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from _training_helpers import numpy_terms
from e3dpsm.compress.distill import DistillConfig, check_pair, distill_loss, distill_terms, restart_lanes
from e3dpsm.errors import ConfigError
from e3dpsm.models import create_model


@pytest.mark.parametrize("fields, message", [
    ({"steps": 0}, "distill steps must be at least 1, got 0"),
    ({"batch_size": 0}, "distill batch_size must be at least 1, got 0"),
    ({"log_every": 0}, "distill log_every must be at least 1, got 0"),
    ({"prior_windows": 0}, "distill prior_windows must be at least 1, got 0"),
    ({"seq_len": 1}, "distill seq_len must be at least 2 (the delta term needs two frames), got 1"),
    ({"labels": "yes"}, "distill labels must be one of ['none', 'gt'], got 'yes'"),
    ({"stream_windows": 0}, "distill stream_windows must be at least 1, got 0"),
    ({"stream_windows": 2}, "distill --stream-windows carries states from window to window, which only a causal run "
                             "has: add --causal"),
    ({"qat_ranges_only": True}, "distill --qat-ranges-only learns the QAT ranges alone: add --qat"),
    ({"qat": True, "qat_ranges_only": True, "prior": "teacher"},
     "distill --qat-ranges-only keeps the student's weights and pose prior as they are; --prior teacher would "
     "change the prior: use --prior keep"),
    ({"qat_calibration_windows": 0}, "distill qat_calibration_windows must be at least 1, got 0"),
    ({"prior": "mean"}, "distill prior must be one of ['keep', 'teacher', 'data'], got 'mean'"),
    ({"lr": 0.0}, "distill lr, charbonnier_mm and clip_norm must be positive"),
    ({"charbonnier_mm": 0.0}, "distill lr, charbonnier_mm and clip_norm must be positive"),
    ({"clip_norm": 0.0}, "distill lr, charbonnier_mm and clip_norm must be positive"),
    ({"lr": float("nan")}, "distill lr, charbonnier_mm and clip_norm must be positive"),
    ({"weight_labels": -0.1}, "distill weights must be non-negative, with at least one teacher term positive"),
    ({"weight_delta": float("nan")}, "distill weights must be non-negative, with at least one teacher term positive"),
    ({"weight_fused": 0.0, "weight_direct": 0.0, "weight_delta": 0.0, "weight_labels": 1.0},
     "distill weights must be non-negative, with at least one teacher term positive"),
])
def test_a_bad_config_is_one_line_that_names_the_field(fields, message) -> None:
    with pytest.raises(ConfigError) as info:
        DistillConfig(**fields)
    assert str(info.value) == message


def test_the_edges_of_a_good_config_are_accepted() -> None:
    for fields in ({"steps": 1, "seq_len": 2, "batch_size": 1, "log_every": 1, "prior_windows": 1},
                   {"stream_windows": 1}, {"stream_windows": 3, "causal": True},
                   {"qat": True, "qat_ranges_only": True, "prior": "keep"}, {"qat_calibration_windows": 1},
                   {"weight_fused": 0.0, "weight_direct": 0.0, "weight_delta": 0.5, "weight_labels": 0.0},
                   {"labels": "gt", "prior": "data"}):
        config = DistillConfig(**fields)
        assert config.to_dict()["steps"] == config.steps
    assert DistillConfig(qat=True, qat_full_integer=True).qat_config.full_integer


def test_the_commands_defaults_are_the_configs_and_the_config_is_frozen() -> None:
    """The command writes its defaults again (its module must not import torch): they agree."""
    import argparse
    import dataclasses

    from e3dpsm.cli.distill import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["distill", "--teacher", "t.pt", "--student", "tiny", "--data", "d", "--out", "o"])
    config = DistillConfig()
    for name in ("steps", "seq_len", "batch_size", "lr", "warmup_steps", "labels", "seed", "causal", "stream_windows",
                 "freeze_norm_stats", "qat", "qat_full_integer", "qat_range_init", "qat_calibration_windows",
                 "qat_float_outputs", "qat_weight_bits", "qat_ranges_only"):
        assert getattr(args, name) == getattr(config, name), name
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.steps = 5


def test_the_documented_loss_and_schedule_are_the_defaults() -> None:
    """docs/compress.md: weights 1, 1, 1 on Charbonnier distances with eps 1 mm; the schedule's
    floor (5%) and the gradient clipping (1.0) are `train`'s."""
    from e3dpsm.training.trainer import TrainArgs

    student, teacher = _outputs(4), _outputs(5)
    total, terms = distill_loss(student, teacher, DistillConfig())
    by_hand = numpy_terms(student, teacher, 1.0)
    assert total.item() == pytest.approx(sum(by_hand.values()), rel=1e-5)
    assert terms["fused"].item() == pytest.approx(by_hand["fused"], rel=1e-5)
    assert distill_terms(student, teacher)["direct"].item() == pytest.approx(by_hand["direct"], rel=1e-5)
    assert DistillConfig().weight_labels == 1.0  # `--labels gt` adds train's pose loss as it is
    train = TrainArgs()
    assert (DistillConfig().min_lr_ratio, DistillConfig().clip_norm) == (train.min_lr_ratio, train.clip_norm)
    docs = (Path(__file__).parents[1] / "docs" / "compress.md").read_text(encoding="utf-8")
    assert "with weights 1, 1, 1" in docs and "+ 1 mm^2) - 1 mm" in docs
    assert f"the teacher's poses on the first {DistillConfig().prior_windows} windows" in docs
    assert f"cosine decay to {train.min_lr_ratio:.0%}" in docs and f"clipping at\n{train.clip_norm}" in docs


def _outputs(seed: int, batch: int = 2, frames: int = 3, joints: int = 4) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {k: 50 * torch.randn(batch, frames, joints, 3, generator=g) for k in ("pose", "pose_direct", "pose_delta")}


def test_the_terms_are_charbonnier_distances_and_the_delta_skips_each_windows_first_frame() -> None:
    student, teacher = _outputs(0), _outputs(1)
    terms = distill_terms(student, teacher, eps_mm=2.0)
    assert {k: v.item() for k, v in terms.items()} == pytest.approx(numpy_terms(student, teacher, 2.0), rel=1e-6)
    moved_first = {**student, "pose_delta": student["pose_delta"].clone()}
    moved_first["pose_delta"][:, 0] += 1000.0
    assert distill_terms(moved_first, teacher, 2.0)["delta"].item() == pytest.approx(terms["delta"].item(), rel=1e-6)
    # A perfect match costs nothing and pulls nowhere.
    exact = {k: v.clone().requires_grad_(True) for k, v in teacher.items()}
    zero = distill_terms(exact, teacher, 1.0)
    assert all(v.item() == 0.0 for v in zero.values())
    sum(zero.values()).backward()
    assert all(float(v.grad.abs().max()) == 0.0 for v in exact.values())


def test_the_loss_weighs_the_three_terms() -> None:
    student, teacher = _outputs(2), _outputs(3)
    config = DistillConfig(weight_fused=0.5, weight_direct=2.0, weight_delta=3.0, charbonnier_mm=0.5)
    total, terms = distill_loss(student, teacher, config)
    by_hand = numpy_terms(student, teacher, 0.5)
    assert {k: v.item() for k, v in terms.items()} == pytest.approx(by_hand, rel=1e-6)
    assert total.item() == pytest.approx(0.5 * by_hand["fused"] + 2.0 * by_hand["direct"] + 3.0 * by_hand["delta"],
                                         rel=1e-6)


def test_a_pair_must_be_two_models_with_one_input_and_joints() -> None:
    teacher = create_model("tiny", height=96, width=128)
    check_pair(teacher, create_model("small", height=96, width=128))
    with pytest.raises(ConfigError) as info:
        check_pair(teacher, teacher)
    assert str(info.value) == "the student is the teacher itself; distil into a copy (copy.deepcopy) or another variant"
    with pytest.raises(ConfigError) as info:
        check_pair(teacher, create_model("tiny", height=64, width=160))
    assert str(info.value) == ("teacher and student must share input size and joints (teacher vs student: height 96 vs "
                               "64, width 128 vs 160); build the student at the teacher's input size")


def test_a_streamed_batch_restarts_only_its_fresh_lanes() -> None:
    model = create_model("tiny", height=96, width=128)
    initial = model.init_state(3)
    assert {k: v.shape for k, v in restart_lanes(model, None, torch.tensor([False] * 3)).items()} == \
        {k: v.shape for k, v in initial.items()}
    for k, v in restart_lanes(model, None, torch.tensor([False] * 3)).items():
        torch.testing.assert_close(v, initial[k], rtol=0, atol=0)
    carried = {k: v + 7.0 for k, v in initial.items()}
    out = restart_lanes(model, carried, torch.tensor([True, False, True]))
    for k, v in out.items():
        torch.testing.assert_close(v[[0, 2]], initial[k][[0, 2]], rtol=0, atol=0)
        torch.testing.assert_close(v[1], carried[k][1], rtol=0, atol=0)
