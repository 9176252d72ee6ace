"""Distillation (e3dpsm.compress.distill): exact targets, a loss checked against numpy, no
label reads in label-free mode, refusals, and the `e3dpsm distill` command end to end."""
from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from _training_helpers import numpy_terms
from e3dpsm.compress.distill import DistillConfig, distill, teacher_mean_pose
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.models import create_model
from e3dpsm.training.data import WindowDataset, seeded_batches

HW = {"height": 96, "width": 128}  # the prepared_small fixture's frame size
FAST = {"seq_len": 3, "batch_size": 2, "warmup_steps": 1, "threads": 1, "log_every": 1}


def make_teacher(seed: int = 1) -> torch.nn.Module:
    """A tiny with its own random weights and a realistic prior (mm); eval mode like a loaded one."""
    teacher = create_model("tiny", seed=seed, **HW)
    teacher.set_pose_prior(torch.linspace(-600.0, 900.0, 48).view(16, 3))
    return teacher.eval()


def state_copy(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


@pytest.mark.parametrize("causal", [False, True])
def test_a_copy_of_the_teacher_is_a_fixed_point(prepared_small: Path, causal: bool) -> None:
    """Targets and loss are exact: a copy scores zero on every term, so with lr > 0 it gets a
    zero gradient and Adam leaves every weight as it was (a gradient of 1e-12 would not:
    Adam's step is lr-sized whatever the gradient's scale)."""
    teacher = make_teacher()
    student = copy.deepcopy(teacher)
    before = state_copy(student)
    config = DistillConfig(steps=3, lr=1e-2, causal=causal, freeze_norm_stats=True, **FAST)
    summary = distill(teacher, student, prepared_small, config, progress=False)
    for record in (summary["initial"], summary["final"]):
        for term in ("fused", "direct", "delta", "loss"):
            assert record[term] == pytest.approx(0.0, abs=1e-5), (term, record)
        assert record["grad_norm"] == pytest.approx(0.0, abs=1e-9)
    after = student.state_dict()
    changed = [k for k, v in before.items() if not torch.equal(v, after[k])]
    assert changed == []
    assert not teacher.training and not student.training  # modes restored


def test_batch_statistics_make_a_copy_move_unless_frozen(prepared_small: Path) -> None:
    """Default (as `train`): the student's BatchNorm normalises with batch statistics, the
    teacher's with running ones, so even a copy starts off the teacher and moves."""
    teacher = make_teacher()
    student = copy.deepcopy(teacher)
    summary = distill(teacher, student, prepared_small, DistillConfig(steps=2, **FAST), progress=False)
    assert summary["initial"]["fused"] > 0.1  # mm; 0 to 1e-5 when frozen (test above)


def test_fresh_student_loss_matches_numpy_and_falls(prepared_small: Path) -> None:
    teacher = make_teacher()
    student = create_model("tiny", seed=0, **HW)
    student.set_pose_prior(torch.full((16, 3), 100.0))
    reference = copy.deepcopy(student)
    teacher_before = state_copy(teacher)
    config = DistillConfig(steps=25, lr=3e-3, **FAST)

    data = PreparedData.open(prepared_small)
    dataset = WindowDataset(data.sequences, config.seq_len)
    _, first = next(seeded_batches(dataset, config.batch_size, config.seed))
    with torch.no_grad():
        target = teacher.forward_sequence(first["lnes"], causal=False, window_ms=data.window_ms)
        initial_out = copy.deepcopy(reference).train().forward_sequence(first["lnes"], causal=False,
                                                                        window_ms=data.window_ms)
    expected = numpy_terms(initial_out, target, config.charbonnier_mm)
    assert expected["fused"] > 50.0  # a fresh student is far from the teacher (mm)

    summary = distill(teacher, student, prepared_small, config, progress=False)
    for term, value in expected.items():
        assert summary["initial"][term] == pytest.approx(value, rel=1e-5, abs=1e-4), term
    assert summary["initial"]["loss"] == pytest.approx(sum(expected.values()), rel=1e-5)
    assert summary["steps"] == 25 and len(summary["log"]) == 25 and summary["seconds"] > 0
    # The teacher is frozen: no gradient reaches it, its weights and BatchNorm statistics stay.
    assert all(p.grad is None for p in teacher.parameters())
    assert all(torch.equal(v, teacher.state_dict()[k]) for k, v in teacher_before.items())

    with torch.no_grad():  # the same first batch, student in training mode as it was trained
        trained_out = copy.deepcopy(student).train().forward_sequence(first["lnes"], causal=False,
                                                                      window_ms=data.window_ms)
    after = numpy_terms(trained_out, target, config.charbonnier_mm)
    assert sum(after.values()) < 0.7 * sum(expected.values()), (after, expected)


def test_prior_from_the_teacher_poses(prepared_small: Path) -> None:
    teacher = make_teacher()
    config = DistillConfig(prior_windows=3, **FAST)
    data = PreparedData.open(prepared_small)
    dataset = WindowDataset(data.sequences, config.seq_len)
    batches = seeded_batches(dataset, config.batch_size, config.seed)
    with torch.no_grad():  # 3 windows -> the first 2 batches (4 windows)
        poses = [teacher.forward_sequence(next(batches)[1]["lnes"], causal=False, window_ms=data.window_ms)["pose"]
                 for _ in range(2)]
    expected = torch.cat(poses).double().numpy().reshape(-1, 16, 3).mean(axis=0)
    got = teacher_mean_pose(teacher, dataset, config, data.window_ms).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-3, rtol=0)

    student = create_model("tiny", seed=0, **HW)
    distill(teacher, student, prepared_small, DistillConfig(steps=1, prior="data", prior_windows=3, **FAST),
            progress=False)
    np.testing.assert_allclose(student.pose_prior_mm.numpy(), expected, atol=1e-3, rtol=0)
    distill(teacher, student, prepared_small, DistillConfig(steps=1, prior="teacher", **FAST), progress=False)
    assert torch.equal(student.pose_prior_mm, teacher.pose_prior_mm)


@pytest.fixture(scope="module")
def garbage_labels(prepared_small: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """prepared_small with every 3D and 2D label NaN and visibility garbage."""
    out = tmp_path_factory.mktemp("nan_labels") / "prep"
    shutil.copytree(prepared_small, out)
    for pose_file in out.glob("*/pose.npz"):
        with np.load(pose_file) as archive:
            arrays = dict(archive)
        arrays["j3d_mm"][:] = np.nan
        arrays["j2d_px"][:] = np.nan
        arrays["visible"][:] = 255
        np.savez(pose_file, **arrays)
    return out


def test_label_free_never_reads_labels(garbage_labels: Path) -> None:
    teacher = make_teacher()
    student = create_model("tiny", seed=0, **HW)
    before = state_copy(student)
    summary = distill(teacher, student, garbage_labels, DistillConfig(steps=3, prior="data", **FAST), progress=False)
    assert all(np.isfinite(v) for v in summary["final"].values())
    assert np.isfinite(student.pose_prior_mm.numpy()).all()
    assert any(not torch.equal(v, student.state_dict()[k]) for k, v in before.items() if v.is_floating_point())
    # The same data with labels="gt" reads them, and says so instead of training on NaN.
    with pytest.raises(DataError, match="not finite at step 1"):
        distill(teacher, create_model("tiny", seed=0, **HW), garbage_labels,
                DistillConfig(steps=2, labels="gt", **FAST), progress=False)


def test_labels_gt_adds_the_pose_loss(prepared_small: Path) -> None:
    teacher = make_teacher()
    student = create_model("tiny", seed=0, **HW)
    summary = distill(teacher, student, prepared_small, DistillConfig(steps=1, labels="gt", weight_labels=0.5, **FAST),
                      progress=False)
    first = summary["initial"]
    assert first["labels"] > 0
    assert first["loss"] == pytest.approx(first["fused"] + first["direct"] + first["delta"] + 0.5 * first["labels"],
                                          rel=1e-5)


def test_any_architecture_with_the_same_input(prepared_small: Path) -> None:
    """Widths, depths, attention layout and input normalisation may all differ."""
    teacher = create_model("small", attn_layout="1d", input_norm="minmax", **HW).eval()
    student = create_model("tiny", seed=0, **HW)
    summary = distill(teacher, student, prepared_small, DistillConfig(steps=2, prior="data", **FAST), progress=False)
    assert np.isfinite(summary["final"]["loss"]) and summary["student"]["parameters"] < summary["teacher"]["parameters"]


def test_refusals_are_one_line(prepared_small: Path) -> None:
    teacher = make_teacher()
    with pytest.raises(ConfigError) as info:
        distill(teacher, create_model("tiny"), prepared_small, DistillConfig(steps=1, **FAST), progress=False)
    message = str(info.value)
    assert "\n" not in message and "height 96 vs 192" in message and "width 128 vs 256" in message
    with pytest.raises(ConfigError, match="teacher itself"):
        distill(teacher, teacher, prepared_small, DistillConfig(steps=1, **FAST), progress=False)
    with pytest.raises(ConfigError, match="labels"):
        DistillConfig(labels="yes")
    with pytest.raises(ConfigError, match="seq_len"):
        DistillConfig(seq_len=1)


@pytest.fixture(scope="module")
def teacher_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from e3dpsm.checkpoint import save_checkpoint

    path = tmp_path_factory.mktemp("teacher") / "teacher.pt"
    save_checkpoint(path, make_teacher(), step=7, window_ms=20.0)
    return path


def cli_args(teacher: Path, student: str, data: Path, out: Path, *extra: str) -> list[str]:
    return ["distill", "--teacher", str(teacher), "--student", student, "--data", str(data), "--out", str(out),
            "--steps", "2", "--seq-len", "3", "--batch-size", "2", "--warmup-steps", "1", "--threads", "1",
            "--no-progress", *extra]


def test_cli_writes_a_checkpoint_that_rebuilds_and_exports(teacher_checkpoint: Path, prepared_small: Path,
                                                            tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    import hashlib
    import json

    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.cli import main

    out = tmp_path / "tiny_distilled"
    assert main(cli_args(teacher_checkpoint, "tiny", prepared_small, out)) == 0
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt", "report.json", "report.md"]
    student, payload = load_checkpoint(out / "checkpoint.pt")
    assert (student.config.variant, student.config.height, student.config.width) == ("tiny", 96, 128)
    assert payload["teacher"]["sha256"] == hashlib.sha256(teacher_checkpoint.read_bytes()).hexdigest()
    assert payload["distill_config"]["prior"] == "data" and payload["distill_config"]["steps"] == 2
    assert payload["train_args"]["seq_len"] == 3 and payload["window_ms"] == 20.0
    assert student.pose_prior_mm.abs().sum() > 0  # the fresh variant got the teacher's mean pose
    report = json.loads((out / "report.json").read_text())
    assert report["command"] == "distill" and "isa" in report["machine"]
    assert report["device"].startswith("cuda" if torch.cuda.is_available() else "cpu")  # --device auto
    assert report["steps"] == 2 and report["teacher"]["variant"] == "tiny" and report["student"]["source"] == "variant"
    assert report["final"]["fused"] == pytest.approx(report["log"][-1]["fused"])
    assert "| step |" in (out / "report.md").read_text()

    assert main(["export", "--checkpoint", str(out / "checkpoint.pt"), "--out", str(tmp_path / "graph"),
                 "--no-simplify", "--threads", "1"]) == 0
    assert (tmp_path / "graph" / "step.onnx").is_file()

    # A checkpoint student keeps its prior by default; an occupied --out is refused in one line.
    again = tmp_path / "again"
    assert main(cli_args(teacher_checkpoint, str(out / "checkpoint.pt"), prepared_small, again)) == 0
    assert json.loads((again / "report.json").read_text())["prior"] == "keep"
    capsys.readouterr()
    assert main(cli_args(teacher_checkpoint, "tiny", prepared_small, out)) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "holds a run" in err and "--force" in err
    assert main(cli_args(teacher_checkpoint, "tiny", prepared_small, out, "--force")) == 0


def test_cli_bad_input_is_one_line(teacher_checkpoint: Path, prepared_small: Path, tmp_path: Path,
                                   capsys: pytest.CaptureFixture) -> None:
    from e3dpsm.checkpoint import save_checkpoint
    from e3dpsm.cli import main

    big = tmp_path / "big.pt"
    save_checkpoint(big, create_model("tiny"))  # 192 x 256
    cases = [
        (cli_args(teacher_checkpoint, "huge", prepared_small, tmp_path / "a"), "neither a variant"),
        (cli_args(teacher_checkpoint, str(big), prepared_small, tmp_path / "b"), "height 96 vs 192"),
        (cli_args(big, "tiny", prepared_small, tmp_path / "c"), "re-run prepare with --height 192"),
        (cli_args(teacher_checkpoint, "tiny", prepared_small, tmp_path / "d", "--steps", "0"), "at least 1"),
        (cli_args(teacher_checkpoint, "tiny", prepared_small, tmp_path / "e", "--qat", "--qat-ranges-only"),
         "is a fresh variant: give a checkpoint"),
    ]
    if not torch.cuda.is_available():
        cases.append((cli_args(teacher_checkpoint, "tiny", prepared_small, tmp_path / "f", "--device", "cuda"),
                      "CUDA is not available"))
    for argv, expected in cases:
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and expected in err, err
        assert not (tmp_path / argv[argv.index("--out") + 1]).joinpath("checkpoint.pt").exists()


def test_qat_distillation_of_a_copy_learns_ranges_and_moves_towards_the_teacher(teacher_checkpoint: Path,
                                                                                 prepared_small: Path,
                                                                                 tmp_path: Path) -> None:
    """`distill --qat`: a copy of the teacher is no longer a fixed point (the rounding moves
    it), the learned ranges travel in the checkpoint, the weights stay plain, BatchNorm keeps
    the teacher's statistics, and `quantize --ranges-from-checkpoint` takes the ranges."""
    from e3dpsm.checkpoint import load_checkpoint, read_checkpoint
    from e3dpsm.cli import main

    out = tmp_path / "qat"
    assert main(cli_args(teacher_checkpoint, str(teacher_checkpoint), prepared_small, out, "--qat",
                         "--qat-full-integer", "--lr", "1e-3")) == 0
    payload = read_checkpoint(out / "checkpoint.pt")
    ranges = payload["qat_ranges"]["quantizers"]
    assert len(ranges) > 50 and all(r["scale"] > 0 and 0 <= r["zero_point"] <= 255 for r in ranges)
    assert any(s.startswith("delta_head") for r in ranges for s in r["sites"])  # the full-integer graph's
    teacher = read_checkpoint(teacher_checkpoint)["model"]
    assert set(payload["model"]) == set(teacher)  # no fake-quant keys
    stats = [k for k in teacher if k.endswith(("running_mean", "running_var"))]
    assert stats and all(torch.equal(payload["model"][k], teacher[k]) for k in stats)
    moved = [k for k, v in payload["model"].items() if v.is_floating_point() and not torch.equal(v, teacher[k])]
    assert moved  # the rounding gives a gradient the plain copy did not have
    report = json.loads((out / "report.json").read_text())
    assert report["initial"]["fused"] > 1e-3 and report["qat_ranges_learned"] == len(ranges)
    assert payload["distill_config"]["qat"] and payload["distill_config"]["qat_full_integer"]
    # The ranges started from an MSE calibration (the default), not from the first batch:
    # every quantiser but those whose calibration input is constant.
    start = report["qat_range_start"]
    assert start["rule"] == "mse" and len(ranges) - 2 <= start["calibrated"] <= start["quantizers"] == len(ranges), start
    load_checkpoint(out / "checkpoint.pt")  # strict load


def test_qat_ranges_only_learns_the_ranges_and_leaves_every_weight_as_the_teachers(teacher_checkpoint: Path,
                                                                                  prepared_small: Path,
                                                                                  tmp_path: Path) -> None:
    """`distill --qat --qat-ranges-only`: the checkpoint's tensors are the teacher's to the bit
    (its fp32 graph is the teacher's, the INT8 budget's own reference), while its ranges moved
    away from the calibration they started from (a run at a vanishing learning rate keeps that
    start: both calibrate on the same windows)."""
    from e3dpsm.checkpoint import read_checkpoint
    from e3dpsm.cli import main

    def ranges(out: Path, lr: str) -> dict[str, tuple[float, int]]:
        assert main(cli_args(teacher_checkpoint, str(teacher_checkpoint), prepared_small, out, "--qat",
                             "--qat-full-integer", "--qat-ranges-only", "--lr", lr, "--steps", "3")) == 0
        payload = read_checkpoint(out / "checkpoint.pt")
        teacher = read_checkpoint(teacher_checkpoint)["model"]
        assert set(payload["model"]) == set(teacher)
        assert all(torch.equal(v, teacher[k]) for k, v in payload["model"].items())
        assert payload["distill_config"]["qat_ranges_only"]
        assert "the ranges alone learned" in (out / "report.md").read_text()
        # the lr column is --lr's schedule, as in a full fine-tune (the ranges train at 10x)
        assert json.loads((out / "report.json").read_text())["log"][-1]["lr"] <= float(lr)
        return {r["sites"][0]: (r["scale"], r["zero_point"]) for r in payload["qat_ranges"]["quantizers"]}

    learned, start = ranges(tmp_path / "learned", "1e-2"), ranges(tmp_path / "start", "1e-12")
    assert learned.keys() == start.keys() and len(learned) > 50
    moved = [s for s in learned if learned[s] != start[s]]
    assert len(moved) > len(learned) // 2, f"{len(moved)} of {len(learned)} ranges moved"
    with pytest.raises(ConfigError, match="add --qat"):
        DistillConfig(qat_ranges_only=True)
    with pytest.raises(ConfigError, match="use --prior keep"):  # a new prior moves every pose
        DistillConfig(qat=True, qat_ranges_only=True, prior="data")
    # Frozen for the run only: the caller's model trains again afterwards.
    teacher = make_teacher()
    student = copy.deepcopy(teacher)
    distill(teacher, student, prepared_small, DistillConfig(steps=1, qat=True, qat_ranges_only=True, **FAST),
            progress=False)
    assert all(p.requires_grad for p in student.parameters())
    assert all(p.grad is None for p in student.parameters())  # no weight gradient computed while frozen


def test_qat_full_integer_without_qat_is_refused_in_distill() -> None:
    with pytest.raises(ConfigError, match="add --qat"):
        DistillConfig(qat_full_integer=True)


def test_stream_batches_continue_each_lane_with_its_next_frames(prepared_small: Path) -> None:
    """Catches: a continuing lane fed other frames than the ones after its previous window, a
    lane restarted without saying so (or said so without restarting), lanes that all restart
    at once, and draws that depend on anything but the seed."""
    from e3dpsm.training.data import stream_batches

    dataset = WindowDataset(PreparedData.open(prepared_small).split("all"), 3)
    frames = [np.asarray(s.lnes, np.float32) for s in dataset.sequences]
    stream = stream_batches(dataset, 3, 0, 4)
    batches = [next(stream) for _ in range(12)]
    again = stream_batches(dataset, 3, 0, 4)
    assert all(torch.equal(b[1]["lnes"], next(again)[1]["lnes"]) for b in batches)
    restarts = torch.stack([fresh for _, _, fresh in batches])
    assert restarts[0].all() and restarts[1:].sum() >= 6 and not restarts[1:].all(dim=1).any()  # staggered

    def where(window: np.ndarray) -> tuple[int, int]:
        hits = [(i, f) for i, seq in enumerate(frames) for f in range(len(seq) - 2) if np.array_equal(seq[f:f + 3], window)]
        assert len(hits) == 1
        return hits[0]

    for step in range(1, len(batches)):
        for lane in range(3):
            before, now = where(batches[step - 1][1]["lnes"][lane].numpy()), where(batches[step][1]["lnes"][lane].numpy())
            continues = now == (before[0], before[1] + 3)
            assert bool(batches[step][2][lane]) != continues, (step, lane, before, now)


def test_streamed_distillation_carries_each_lanes_states(prepared_small: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--stream-windows`: the teacher's targets and the student's outputs for a window are
    those of one causal run over the lane's whole stream so far (an explicit run over the
    concatenated frames), not of a run from the initial states. Catches: states reset every
    window, carried across lanes, or not reset where a lane starts a new stream."""
    import e3dpsm.compress.distill as module
    from e3dpsm.training.data import stream_batches

    teacher, student = make_teacher(1), make_teacher(2)
    reference = copy.deepcopy(student).eval()
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    real = module.distill_loss

    def record(outputs, target, config):
        seen.append((outputs["pose"].detach().clone(), target["pose"].clone()))
        return real(outputs, target, config)

    monkeypatch.setattr(module, "distill_loss", record)
    config = DistillConfig(steps=6, lr=1e-9, causal=True, freeze_norm_stats=True, stream_windows=4, **FAST)
    distill(teacher, student, prepared_small, config, progress=False)
    dataset = WindowDataset(PreparedData.open(prepared_small).split("all"), config.seq_len)
    batches = stream_batches(dataset, config.batch_size, config.seed, config.stream_windows)
    so_far: list[list[torch.Tensor]] = [[] for _ in range(config.batch_size)]
    continued = 0
    with torch.no_grad():
        for step in range(config.steps):
            _, batch, fresh = next(batches)
            for lane in range(config.batch_size):
                so_far[lane] = [batch["lnes"][lane]] if fresh[lane] else [*so_far[lane], batch["lnes"][lane]]
                continued += not bool(fresh[lane])
                frames = torch.cat(so_far[lane])[None]
                want_target = teacher.forward_sequence(frames, causal=True)["pose"][0, -config.seq_len:]
                want_output = reference.forward_sequence(frames, causal=True)["pose"][0, -config.seq_len:]
                output, target = seen[step][0][lane], seen[step][1][lane]
                assert torch.allclose(target, want_target, atol=1e-3), (step, lane, (target - want_target).abs().max())
                assert torch.allclose(output, want_output, atol=1e-2), (step, lane, (output - want_output).abs().max())
    assert continued >= 6


def test_streams_need_a_causal_run() -> None:
    with pytest.raises(ConfigError, match="add --causal"):
        DistillConfig(stream_windows=4)
    with pytest.raises(ConfigError, match="at least 1"):
        DistillConfig(stream_windows=0, causal=True)
