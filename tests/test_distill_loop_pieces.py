"""Distillation's training loop (e3dpsm/compress/distill.py `_run`, `teacher_mean_pose`,
`distill`) on toy pose models and recorded batches, in seconds: what each model is handed
(causal, window, states, gradients), the schedule's learning rate, the loss against the
teacher and its log, a non-finite loss, streamed lanes, frozen BatchNorm statistics, the
label term, the prior, and what `distill` gives back. The tiny's real distillation is the
slower tests/test_distill.py."""
from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch
from torch import nn

from e3dpsm.compress import distill as distill_module
from e3dpsm.compress.distill import DistillConfig, _run, teacher_mean_pose
from e3dpsm.errors import DataError
from e3dpsm.training.schedule import WarmupCosine

FEATURES, JOINTS, FRAMES = 6, 2, 3


class ToyPose(nn.Module):
    """forward_sequence like E3DPSM's: [B, T, F] -> poses [B, T, J, 3] (fused, direct, delta),
    with an optional carried state [B, F]; each call recorded."""

    def __init__(self, variant: str, seed: int) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.config = types.SimpleNamespace(variant=variant, num_joints=JOINTS, in_channels=2, height=4, width=4)
        self.norm = nn.BatchNorm1d(FEATURES)
        self.head = nn.Linear(FEATURES, 3 * JOINTS * 3)
        self.register_buffer("pose_prior_mm", torch.zeros(JOINTS, 3))
        self.calls: list[dict] = []
        self.poison_at: int | None = None
        object.__setattr__(self, "fake_quant", None)  # QAT's ranges, not the model's own parameters

    def init_state(self, batch: int) -> dict[str, torch.Tensor]:
        return {"h": torch.full((batch, FEATURES), -1.0)}

    def set_pose_prior(self, mean_pose_mm: torch.Tensor) -> None:
        self.pose_prior_mm.copy_(mean_pose_mm)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def forward_sequence(self, lnes, causal=False, window_ms=None, state=None, return_state=False):
        self.calls.append({"causal": causal, "window_ms": window_ms, "state": None if state is None else
                           {k: v.clone() for k, v in state.items()}, "grad": torch.is_grad_enabled(),
                           "training": self.training, "lnes": lnes.clone()})
        batch, frames = lnes.shape[:2]
        x = lnes if state is None else lnes + state["h"][:, None]
        if self.fake_quant is not None:
            x = x * (1.0 + sum(q.weight.sum() for q in self.fake_quant.quantizers))
        y = self.head(self.norm(x.reshape(batch * frames, FEATURES))).view(batch, frames, 3, JOINTS, 3)
        if self.poison_at is not None and len(self.calls) == self.poison_at:
            y = y * float("nan")
        out = {"pose": y[:, :, 0] + self.pose_prior_mm, "pose_direct": y[:, :, 1], "pose_delta": y[:, :, 2]}
        if return_state:
            return out, {"h": x[:, -1]}
        return out


def _batches(count: int, batch: int = 2, seed: int = 0, stream: bool = False):
    generator = torch.Generator().manual_seed(seed)
    for step in range(count):
        lnes = torch.randn(batch, FRAMES, FEATURES, generator=generator)
        data = {"lnes": lnes, "j3d_mm": torch.randn(batch, FRAMES, JOINTS, 3, generator=generator),
                "j2d_px": torch.randn(batch, FRAMES, JOINTS, 2, generator=generator),
                "visible": torch.ones(batch, FRAMES, JOINTS)}
        if stream:
            yield step, data, torch.tensor([step % 2 == 0, step % 3 == 0])
        else:
            yield step, data


@pytest.fixture
def batches(monkeypatch):
    """seeded_batches and stream_batches replaced by seeded toy batches (endless enough)."""
    asked = {}

    def seeded(dataset, batch_size, seed):
        asked["seeded"] = (dataset, batch_size, seed)
        return _batches(100, batch_size)

    def streamed(dataset, batch_size, seed, windows):
        asked["stream"] = (dataset, batch_size, seed, windows)
        return _batches(100, batch_size, stream=True)

    monkeypatch.setattr(distill_module, "seeded_batches", seeded)
    monkeypatch.setattr(distill_module, "stream_batches", streamed)
    return asked


def _config(**fields) -> DistillConfig:
    return DistillConfig(**{"steps": 12, "seq_len": FRAMES, "batch_size": 2, "lr": 0.05, "warmup_steps": 4,
                            "log_every": 5, **fields})


def test_the_student_learns_the_frozen_teacher_under_the_schedule(batches) -> None:
    teacher, student = ToyPose("big", 0).eval(), ToyPose("small", 1)
    before = {k: v.clone() for k, v in teacher.state_dict().items()}
    config = _config(seed=3, steps=20)
    summary = _run(teacher, student, "DATASET", config, 20.0, None, False)
    assert torch.initial_seed() == 3000  # seeded as `train` seeds a fresh run
    assert batches["seeded"] == ("DATASET", 2, 3)
    assert all(torch.equal(v, before[k]) for k, v in teacher.state_dict().items())
    assert all(not c["grad"] for c in teacher.calls) and all(c["grad"] and c["training"] for c in student.calls)
    assert [(c["causal"], c["window_ms"], c["state"]) for c in teacher.calls + student.calls] == [
        (False, 20.0, None)] * 40
    for t, s in zip(teacher.calls, student.calls):
        assert torch.equal(t["lnes"], s["lnes"])
    assert summary["steps"] == 20 and len(student.calls) == 20
    assert [r["step"] for r in summary["log"]] == [1, 5, 10, 15, 20]
    assert summary["initial"] == summary["log"][0] and summary["final"] == summary["log"][-1]
    assert summary["final"]["loss"] < 0.5 * summary["initial"]["loss"]
    schedule = WarmupCosine(20, 2, 0.05)  # warm-up: min(4, max(1, 20 // 10))
    for record in summary["log"]:
        assert record["lr"] == pytest.approx(0.05 * schedule(record["step"] - 1))
        assert record["loss"] == pytest.approx(record["fused"] + record["direct"] + record["delta"], rel=1e-5)
        assert record["grad_norm"] > 0
    assert summary["seconds_per_step"] == pytest.approx(summary["seconds"] / 20) and 0 < summary["seconds"] < 60
    assert summary["teacher"] == {"variant": "big", "parameters": teacher.num_parameters()}
    assert summary["student"] == {"variant": "small", "parameters": student.num_parameters()}


def test_the_first_step_is_the_charbonnier_loss_computed_by_hand(batches) -> None:
    teacher, student = ToyPose("big", 0).eval(), ToyPose("small", 1)
    config = _config(steps=1, weight_direct=0.5, weight_delta=2.0, charbonnier_mm=0.5)
    _, first = next(_batches(1))
    with torch.no_grad():
        student_copy = ToyPose("small", 1).train()
        want_t, want_s = teacher.forward_sequence(first["lnes"]), student_copy.forward_sequence(first["lnes"])

    def charbonnier(a, b, eps=0.5):
        d2 = ((a.numpy() - b.numpy()) ** 2).sum(-1)
        return float((np.sqrt(d2 + eps * eps) - eps).mean())

    fused = charbonnier(want_s["pose"], want_t["pose"])
    direct = charbonnier(want_s["pose_direct"], want_t["pose_direct"])
    delta = charbonnier(want_s["pose_delta"][:, 1:], want_t["pose_delta"][:, 1:])
    record = _run(teacher, student, "D", config, 20.0, None, False)["final"]
    assert (record["fused"], record["direct"], record["delta"]) == pytest.approx((fused, direct, delta), rel=1e-5)
    assert record["loss"] == pytest.approx(fused + 0.5 * direct + 2.0 * delta, rel=1e-5)


def test_gradients_are_clipped_to_the_configured_norm(batches, monkeypatch) -> None:
    teacher, student = ToyPose("big", 0).eval(), ToyPose("small", 1)
    seen = []
    original = torch.nn.utils.clip_grad_norm_

    def clip(parameters, max_norm):
        parameters = list(parameters)
        norm = original(parameters, max_norm)
        seen.append((max_norm, float(torch.sqrt(sum((p.grad ** 2).sum() for p in parameters))), len(parameters)))
        return norm

    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", clip)
    _run(teacher, student, "D", _config(steps=2, clip_norm=1e-3), 20.0, None, False)
    assert [m for m, _, _ in seen] == [1e-3, 1e-3]
    assert all(n <= 1e-3 * 1.0001 for _, n, _ in seen)
    assert all(count == len(list(student.parameters())) for _, _, count in seen)


def test_a_non_finite_loss_names_its_step_and_terms(batches) -> None:
    teacher, student = ToyPose("big", 0).eval(), ToyPose("small", 1)
    teacher.poison_at = 3
    with pytest.raises(DataError, match=r"distillation loss is not finite at step 3 \(terms \['fused', 'direct', "
                                        r"'delta'\]\): NaN or inf in the data"):
        _run(teacher, student, "D", _config(), 20.0, None, False)


def test_a_streamed_run_carries_each_lanes_states_and_restarts_the_fresh_ones(batches) -> None:
    teacher, student = ToyPose("big", 0).eval(), ToyPose("small", 1)
    _run(teacher, student, "D", _config(steps=4, causal=True, stream_windows=2), 20.0, None, False)
    assert batches["stream"] == ("D", 2, 0, 2) and "seeded" not in batches
    fresh = [torch.tensor([s % 2 == 0, s % 3 == 0]) for s in range(4)]
    for model in (teacher, student):
        assert all(c["causal"] is True and c["window_ms"] == 20.0 for c in model.calls)
        previous = None
        for call, lanes in zip(model.calls, fresh):
            state = call["state"]["h"]
            for lane in range(2):
                if previous is None or lanes[lane]:
                    assert torch.equal(state[lane], torch.full((FEATURES,), -1.0))
                else:  # the last frame's carried input of the lane's previous window
                    want = previous["lnes"][lane, -1] + previous["state"]["h"][lane]
                    torch.testing.assert_close(state[lane], want)
            previous = call
    assert not any(c["state"]["h"].requires_grad for c in student.calls)  # truncated: no gradient into the past


def test_batchnorm_statistics_stay_put_when_frozen(batches) -> None:
    for frozen in (False, True):
        teacher, student = ToyPose("big", 0).eval(), ToyPose("small", 1)
        before = student.norm.running_mean.clone()
        _run(teacher, student, "D", _config(steps=3, freeze_norm_stats=frozen), 20.0, None, False)
        assert torch.equal(student.norm.running_mean, before) is frozen
        assert student.training and student.norm.training is not frozen


def test_the_label_term_is_weighted_in_and_logged(batches) -> None:
    teacher, student = ToyPose("big", 0).eval(), ToyPose("small", 1)
    seen = []

    def criterion(outputs, j3d, j2d, visible):
        seen.append((j3d.shape, j2d.shape, visible.shape))
        return outputs["pose"].abs().mean() * 0 + 7.0, {}

    record = _run(teacher, student, "D", _config(steps=1, labels="gt", weight_labels=0.5), 20.0, criterion,
                  False)["final"]
    assert seen == [((2, FRAMES, JOINTS, 3), (2, FRAMES, JOINTS, 2), (2, FRAMES, JOINTS))]
    assert record["labels"] == 7.0
    assert record["loss"] == pytest.approx(record["fused"] + record["direct"] + record["delta"] + 3.5, rel=1e-5)


def test_the_data_prior_is_the_mean_teacher_pose_of_the_first_windows(monkeypatch) -> None:
    teacher = ToyPose("big", 0).eval()
    teacher.pose_prior_mm.fill_(100.0)
    monkeypatch.setattr(distill_module, "seeded_batches", lambda dataset, size, seed: _batches(50, size, seed))
    config = _config(prior="data", prior_windows=4, batch_size=2, seed=4, causal=True)
    got = teacher_mean_pose(teacher, "D", config, window_ms=33.0)
    # windows of FRAMES frames: 4 windows = 12 frames; batches of 2 windows: two batches reach it exactly
    poses = [teacher.forward_sequence(b["lnes"])["pose"].detach() for _, b in _batches(2, 2, 4)]
    want = torch.cat([p.reshape(-1, JOINTS, 3) for p in poses]).double().mean(0).float()
    torch.testing.assert_close(got, want)
    assert got.dtype == torch.float32 and got.shape == (JOINTS, 3)
    assert [(c["causal"], c["window_ms"], c["grad"]) for c in teacher.calls[:2]] == [(True, 33.0, False)] * 2
    assert len(teacher.calls) == 2 + 2  # two batches drawn, then the two of the reference above


class FakeData:
    def __init__(self) -> None:
        self.window_ms, self.checked, self.splits = 25.0, [], []

    def check_compatible(self, **kwargs) -> None:
        self.checked.append(kwargs)

    def split(self, name: str) -> list:
        self.splits.append(name)
        return ["SEQUENCE"]


class FakeWindows:
    def __init__(self, sequences: list, seq_len: int) -> None:
        self.sequences, self.seq_len = sequences, seq_len

    def __len__(self) -> int:
        return 9

    def frames_total(self) -> int:
        return 40


def _fake_data(monkeypatch) -> FakeData:
    data = FakeData()
    monkeypatch.setattr(distill_module.PreparedData, "open", staticmethod(lambda path: data))
    monkeypatch.setattr(distill_module, "WindowDataset", FakeWindows)
    return data


@pytest.mark.parametrize("prior", ["keep", "teacher", "data"])
def test_distill_hands_back_both_models_as_it_found_them(monkeypatch, prior) -> None:
    data = _fake_data(monkeypatch)
    monkeypatch.setattr(distill_module, "teacher_mean_pose",
                        lambda teacher, dataset, config, window_ms: torch.full((JOINTS, 3), window_ms))
    ran = {}

    def run(teacher, student, dataset, config, window_ms, criterion, progress, fake_quant):
        ran.update(window_ms=window_ms, criterion=criterion, progress=progress, fake_quant=fake_quant,
                   teacher_training=teacher.training, prior=student.pose_prior_mm.clone())
        return {"steps": config.steps}

    monkeypatch.setattr(distill_module, "_run", run)
    teacher, student = ToyPose("big", 0).train(), ToyPose("small", 1).eval()
    teacher.pose_prior_mm.fill_(5.0)
    student.head.weight.requires_grad_(False)
    threads = torch.get_num_threads()
    try:
        summary = distill_module.distill(teacher, student, "PREP", _config(prior=prior, threads=1), progress=False)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
    assert teacher.training and not student.training
    assert ran["teacher_training"] is False and ran["window_ms"] == 25.0 and ran["criterion"] is None
    assert ran["progress"] is False and ran["fake_quant"] is None
    assert ran["prior"].flatten().tolist() == [{"keep": 0.0, "teacher": 5.0, "data": 25.0}[prior]] * (JOINTS * 3)
    assert student.head.weight.requires_grad is False  # what was frozen stays frozen
    assert data.checked == [{"height": 4, "width": 4}] and data.splits == ["all"]
    assert summary["steps"] == 12 and summary["prior"] == prior and summary["split"] == "all"
    assert summary["windows"] == 9 and summary["frames"] == 40 and summary["window_ms"] == 25.0 and summary["data"] == "PREP"
    assert summary["config"] == _config(prior=prior, threads=1).to_dict() and summary["prior_seconds"] >= 0
    assert math.isfinite(summary["prior_seconds"]) and summary["prior_seconds"] < 60


def test_labels_gt_builds_the_pose_criterion_from_the_data_on_the_students_device(monkeypatch) -> None:
    from e3dpsm.training import trainer

    data = _fake_data(monkeypatch)
    moved, ran = [], {}

    class Criterion:
        def to(self, device):
            moved.append(device)
            return self

    monkeypatch.setattr(trainer, "pose_criterion", lambda given: Criterion() if given is data else None)
    monkeypatch.setattr(distill_module, "_run", lambda teacher, student, dataset, config, window_ms, criterion,
                        progress, fq: ran.update(criterion=criterion, progress=progress) or {})
    distill_module.distill(ToyPose("big", 0), ToyPose("small", 1), "PREP", _config(labels="gt"), split="train")
    assert isinstance(ran["criterion"], Criterion) and moved == [torch.device("cpu")]
    assert ran["progress"] is True and data.splits == ["train"]  # a bar by default; the split asked for


class ToyFakeQuant(nn.Module):
    """attach_fake_quant's handle: learned ranges as parameters, a payload, removal recorded."""

    def __init__(self) -> None:
        super().__init__()
        self.quantizers = nn.ModuleList([nn.Linear(1, 1, bias=False) for _ in range(3)])
        self.config = types.SimpleNamespace(range_lr_scale=10.0)
        self.weight_bits, self.removed = 7, 0

    def ranges_payload(self) -> dict:
        return {"ranges": [float(q.weight) for q in self.quantizers]}

    def remove(self) -> None:
        self.removed += 1


def _recorded_adam(monkeypatch) -> list:
    made = []
    adam = torch.optim.Adam

    def record(groups, lr):
        made.append(([{**g, "params": list(g["params"])} for g in groups], lr))
        return adam(groups, lr=lr)

    monkeypatch.setattr(torch.optim, "Adam", record)
    return made


@pytest.mark.parametrize("ranges_only", [False, True])
def test_qat_trains_the_ranges_beside_the_weights_or_alone(batches, monkeypatch, ranges_only) -> None:
    made, clipped = _recorded_adam(monkeypatch), []
    clip = torch.nn.utils.clip_grad_norm_
    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_",
                        lambda params, norm: clipped.append(list(params)) or clip(clipped[-1], norm))
    teacher, student, fake_quant = ToyPose("big", 0).eval(), ToyPose("small", 1), ToyFakeQuant()
    object.__setattr__(student, "fake_quant", fake_quant)
    weights = [p.detach().clone() for p in student.parameters()]
    ranges_before = [p.detach().clone() for p in fake_quant.parameters()]
    student.requires_grad_(not ranges_only)  # distill freezes the weights for a ranges-only run
    _run(teacher, student, "D", _config(steps=2, qat=True, qat_ranges_only=ranges_only), 20.0, None, False, fake_quant)
    (groups, lr), = made
    ranges = {"params": list(fake_quant.parameters()), "lr": 0.05 * 10.0}
    # the ranges' gradients unclipped beside the weights' (as `train --qat`), clipped when alone
    assert clipped == [ranges["params"] if ranges_only else list(student.parameters())] * 2
    if ranges_only:
        assert [g["params"] for g in groups] == [ranges["params"]] and groups[0]["lr"] == 0.5
        assert all(torch.equal(a, b) for a, b in zip(weights, student.parameters()))
    else:
        assert [g["params"] for g in groups] == [list(student.parameters()), ranges["params"]]
        assert groups[1]["lr"] == 0.5 and "lr" not in groups[0] and lr == 0.05
        assert not all(torch.equal(a, b) for a, b in zip(weights, student.parameters()))
    assert not student.norm.training  # QAT freezes the statistics
    assert not any(torch.equal(a, b) for a, b in zip(ranges_before, fake_quant.parameters()))


@pytest.mark.parametrize("rule, windows, streams, count", [
    ("mse", 10, 1, 10), ("minmax", 10, 3, 4), ("mse", 2, 3, 2), ("mse", 30, 4, 8), ("first-batch", 10, 1, None)])
def test_qat_ranges_start_from_calibration_on_whole_streams(monkeypatch, rule, windows, streams, count) -> None:
    from e3dpsm.training import qat

    _fake_data(monkeypatch)
    fake_quant, calibrated, handed = ToyFakeQuant(), [], {}
    monkeypatch.setattr(qat, "attach_fake_quant", lambda model, config: handed.update(
        training=model.training, config=config) or fake_quant)
    monkeypatch.setattr(qat, "calibrate_on_windows", lambda fq, model, dataset, n, window_ms, causal, init:
                        calibrated.append((fq, dataset.seq_len, n, window_ms, causal, init)) or 2)
    monkeypatch.setattr(distill_module, "_run", lambda teacher, student, dataset, config, window_ms, criterion,
                        progress, fq: {"fake_quant": fq})
    config = _config(qat=True, qat_range_init=rule, qat_calibration_windows=windows, stream_windows=streams,
                     causal=streams > 1)
    summary = distill_module.distill(ToyPose("big", 0), ToyPose("small", 1), "PREP", config, progress=False)
    assert handed == {"training": True, "config": config.qat_config}
    assert summary["fake_quant"] is fake_quant and fake_quant.removed == 1
    assert summary["qat_ranges"] == fake_quant.ranges_payload()
    start = {"rule": rule, "quantizers": 3, "calibrated": 0, "weight_bits": 7}
    if count is None:
        assert calibrated == [] and summary["qat_range_start"] == start
    else:
        assert calibrated == [(fake_quant, FRAMES * streams, count, 25.0, streams > 1, rule)]
        assert summary["qat_range_start"] == {**start, "calibrated": 2, "windows": count,
                                              "frames_per_window": FRAMES * streams}


def test_qat_ranges_only_freezes_the_weights_for_the_run_and_removes_the_quantizers_on_failure(monkeypatch) -> None:
    from e3dpsm.training import qat

    _fake_data(monkeypatch)
    fake_quant, seen = ToyFakeQuant(), {}
    monkeypatch.setattr(qat, "attach_fake_quant", lambda model, config: fake_quant)
    monkeypatch.setattr(qat, "calibrate_on_windows", lambda *args: 0)

    def run(teacher, student, dataset, config, window_ms, criterion, progress, fq):
        seen["grads"] = {p.requires_grad for p in student.parameters()}
        raise DataError("stopped")

    monkeypatch.setattr(distill_module, "_run", run)
    student = ToyPose("small", 1).train()
    with pytest.raises(DataError, match="stopped"):
        distill_module.distill(ToyPose("big", 0), student, "PREP", _config(qat=True, qat_ranges_only=True),
                               progress=False)
    assert seen["grads"] == {False} and {p.requires_grad for p in student.parameters()} == {True}
    assert fake_quant.removed == 1 and student.training


@pytest.mark.parametrize("progress", [False, True])
def test_the_progress_bar_shows_only_when_asked(batches, capfd, progress) -> None:
    _run(ToyPose("big", 0).eval(), ToyPose("small", 1), "D", _config(steps=3), 20.0, None, progress)
    err = capfd.readouterr().err
    assert ("distill big -> small: " in err and " 3/3 " in err and ("step/s" in err or "s/step" in err)) is progress
    assert err == "" or progress
