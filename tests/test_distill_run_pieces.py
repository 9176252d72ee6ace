"""The run behind `e3dpsm distill` (compress/distill_run.py) with the distillation itself
replaced by a recorder: what it is given, what the checkpoint and the reports keep, the
refusals and the Markdown report, fast. The distillation loop runs for real in test_distill.py."""
from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest
import torch

import e3dpsm
from e3dpsm.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from e3dpsm.compress import distill_run
from e3dpsm.compress.distill import DistillConfig
from e3dpsm.errors import ConfigError, DataError, OutputExistsError
from e3dpsm.models import list_models
from tests._quantize_helpers import TRAINED_TINY


def test_a_folder_that_holds_a_run_is_refused_unless_forced(tmp_path) -> None:
    out = tmp_path / "a" / "b"
    distill_run.prepare_out_dir(out, force=False)  # writable: nothing made yet
    assert not (tmp_path / "a").exists()
    out.mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    distill_run.prepare_out_dir(out, force=False)  # other files are not a run
    for name in ("report.md", "checkpoint.pt"):
        (out / name).write_text("old")
    with pytest.raises(OutputExistsError) as error:
        distill_run.prepare_out_dir(out, force=False)
    assert str(error.value) == (f"{out} holds a run (checkpoint.pt, report.md); pass --force to replace it or "
                                "choose another --out")
    distill_run.prepare_out_dir(out, force=True)
    assert (out / "checkpoint.pt").read_text() == "old"  # replaced only when the new one is written
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError) as error:
        distill_run.prepare_out_dir(tmp_path / "file" / "run", force=False)
    assert str(error.value) == f"cannot write to {tmp_path / 'file' / 'run'}: {tmp_path / 'file'} is a file, not a folder"


def test_the_teachers_digest_is_sha256_of_its_bytes(tmp_path) -> None:
    path = tmp_path / "x.bin"
    path.write_bytes(bytes(range(256)) * 1000)
    assert distill_run.sha256_file(path) == hashlib.sha256(path.read_bytes()).hexdigest()


def _teacher(**overrides):
    return e3dpsm.create_model("tiny", height=64, width=96, train_window_ms=25.0, **overrides).eval()


@pytest.mark.parametrize("variant", ["tiny", "small"])
def test_a_variant_student_takes_the_teachers_input_and_window(variant) -> None:
    teacher = _teacher()
    student, kind = distill_run.build_student(variant, teacher)
    assert kind == "variant" and student.config.variant == variant
    for field in ("height", "width", "in_channels", "num_joints", "train_window_ms"):
        assert getattr(student.config, field) == getattr(teacher.config, field), field
    assert (student.config.height, student.config.width, student.config.train_window_ms) == (64, 96, 25.0)


def test_a_checkpoint_student_is_loaded_and_anything_else_refused(tmp_path) -> None:
    student, kind = distill_run.build_student(str(TRAINED_TINY), _teacher())
    reference, _ = load_checkpoint(TRAINED_TINY)
    assert kind == "checkpoint"
    assert all(torch.equal(a, b) for a, b in zip(student.state_dict().values(), reference.state_dict().values()))
    with pytest.raises(ConfigError) as error:
        distill_run.build_student(str(tmp_path / "nope.pt"), _teacher())
    assert str(error.value) == (f"--student {str(tmp_path / 'nope.pt')!r} is neither a variant "
                                f"({', '.join(list_models())}) nor a checkpoint file")


class RecordingDistill:
    """Stands in for compress.distill.distill: records its call, moves the student's weights
    (so the checkpoint shows the distilled student), returns a summary of the real form."""

    def __init__(self, qat: bool = False) -> None:
        self.calls: list[tuple] = []
        self.qat = qat

    def __call__(self, teacher, student, data_dir, config, split=None, progress=True) -> dict:
        self.calls.append((teacher, student, data_dir, config, split, progress))
        with torch.no_grad():
            for p in student.parameters():
                p.add_(0.25)
        student.train()
        log = [{"step": s, "lr": 1e-3 / (s + 1), "loss": 10.0 / (s + 1), "fused": 1.0, "direct": 2.0, "delta": 3.0}
               for s in range(3)]
        summary = {"steps": config.steps, "seconds": 4.0, "seconds_per_step": 4.0 / config.steps,
                   "initial": log[0], "final": log[-1], "log": log,
                   "teacher": {"variant": teacher.config.variant, "parameters": teacher.num_parameters()},
                   "student": {"variant": student.config.variant, "parameters": student.num_parameters()},
                   "prior": config.prior, "prior_seconds": 0.5, "split": split or "train", "windows": 12,
                   "frames": 96, "window_ms": 20.0, "data": str(data_dir), "config": config.to_dict()}
        if self.qat:
            summary["qat_ranges"] = {"quantizers": {"a": [0.0, 1.0], "b": [-1.0, 1.0]}}
            summary["qat_range_start"] = {"rule": "mse", "calibrated": 2, "quantizers": 2, "windows": 4,
                                          "frames_per_window": 8}
        return summary


def test_run_distill_writes_the_distilled_student_its_provenance_and_reports(monkeypatch, tmp_path) -> None:
    fake = RecordingDistill()
    monkeypatch.setattr(distill_run, "distill", fake)
    config = DistillConfig(steps=3, seq_len=4, batch_size=2, lr=2e-3, seed=5, prior="data")
    out = tmp_path / "run"
    report = distill_run.run_distill(TRAINED_TINY, "tiny", "prep", out, config, split="val", progress=False)
    (teacher, student, data_dir, cfg, split, progress), = fake.calls
    assert (teacher.config.variant, data_dir, cfg, split, progress) == ("tiny", "prep", config, "val", False)
    assert student is not teacher and not student.training  # written in eval mode

    payload = read_checkpoint(out / "checkpoint.pt")
    rebuilt, _ = load_checkpoint(out / "checkpoint.pt")
    assert all(torch.equal(a, b) for a, b in zip(rebuilt.state_dict().values(), student.state_dict().values()))
    sha = hashlib.sha256(Path(TRAINED_TINY).read_bytes()).hexdigest()
    teacher_info = {"path": str(TRAINED_TINY), "sha256": sha, "variant": "tiny",
                    "train_step": read_checkpoint(TRAINED_TINY).get("step")}
    assert payload["teacher"] == teacher_info
    assert payload["student_source"] == {"source": "variant", "spec": "tiny", "variant": "tiny"}
    assert payload["step"] == 3 and payload["window_ms"] == 20.0 and payload["data"] == "prep"
    assert payload["distill_config"] == config.to_dict() and "qat_ranges" not in payload
    assert payload["train_args"] == {"variant": "tiny", "steps": 3, "seq_len": 4, "batch_size": 2, "lr": 2e-3,
                                     "warmup_steps": config.warmup_steps, "min_lr_ratio": config.min_lr_ratio,
                                     "clip_norm": config.clip_norm, "seed": 5, "split": "val"}

    assert json.loads((out / "report.json").read_text()) == json.loads(json.dumps(report))
    assert report["command"] == "distill" and report["config"] == {
        "teacher": str(TRAINED_TINY), "student": "tiny", "data": "prep", "split": "val", "distill": config.to_dict()}
    parameters = {"parameters": teacher.num_parameters()}
    assert report["teacher"] == {**teacher_info, "variant": "tiny", **parameters}
    assert report["student"] == {"source": "variant", "spec": "tiny", "variant": "tiny",
                                 "parameters": student.num_parameters()}
    assert report["checkpoint"] == str(out / "checkpoint.pt") and report["device"] == "cpu"
    assert (report["steps"], report["windows"], report["prior"], report["split"]) == (3, 12, "data", "val")
    assert "qat_ranges" not in report and "qat_ranges_learned" not in report
    assert (out / "report.md").read_text() == distill_run.report_markdown(report)


def test_qat_ranges_travel_in_the_checkpoint_and_are_counted_in_the_report(monkeypatch, tmp_path) -> None:
    monkeypatch.setattr(distill_run, "distill", RecordingDistill(qat=True))
    config = DistillConfig(steps=3, qat=True, qat_ranges_only=True)
    report = distill_run.run_distill(TRAINED_TINY, str(TRAINED_TINY), "prep", tmp_path / "q", config, progress=False)
    payload = read_checkpoint(tmp_path / "q" / "checkpoint.pt")
    assert payload["qat_ranges"] == {"quantizers": {"a": [0.0, 1.0], "b": [-1.0, 1.0]}}
    assert report["qat_ranges_learned"] == 2 and "qat_ranges" not in report
    assert report["qat_range_start"]["calibrated"] == 2
    assert report["student"]["source"] == "checkpoint"


@pytest.mark.parametrize("student, config, device, message", [
    ("tiny", DistillConfig(qat=True, qat_ranges_only=True), "cpu",
     "--qat-ranges-only learns INT8 ranges for a trained model and keeps its weights; --student tiny is a fresh "
     "variant: give a checkpoint (e.g. the teacher's)"),
    ("tiny", DistillConfig(), "tpu", "--device must be one of ['auto', 'cpu', 'cuda'], got 'tpu'"),
])
def test_refusals_come_before_anything_is_read_or_written(monkeypatch, tmp_path, student, config, device,
                                                          message) -> None:
    monkeypatch.setattr(distill_run, "distill", RecordingDistill())
    monkeypatch.setattr(distill_run, "load_checkpoint", lambda *_: pytest.fail("read the teacher"))
    with pytest.raises(ConfigError) as error:
        distill_run.run_distill(TRAINED_TINY, student, "prep", tmp_path / "out", config, device=device)
    assert str(error.value) == message and not (tmp_path / "out").exists()


def test_a_student_that_does_not_fit_the_teacher_is_refused_before_distilling(monkeypatch, tmp_path) -> None:
    fake = RecordingDistill()
    monkeypatch.setattr(distill_run, "distill", fake)
    other = tmp_path / "other.pt"
    save_checkpoint(other, e3dpsm.create_model("tiny", height=64, width=96))
    with pytest.raises(ConfigError, match=re.escape("64")):
        distill_run.run_distill(TRAINED_TINY, str(other), "prep", tmp_path / "out", DistillConfig(), progress=False)
    assert not fake.calls and not (tmp_path / "out").exists()  # no empty folder left


def _report(log_steps: int = 3, **cfg) -> dict:
    config = DistillConfig(**cfg).to_dict()
    log = [{"step": s, "lr": 0.001234, "loss": 1.5 + s, "fused": 0.25, "direct": 0.5, "delta": 0.125}
           for s in range(log_steps)]
    return {"teacher": {"variant": "small", "path": "runs/t.pt", "sha256": "0123456789abcdef" * 4,
                        "parameters": 1234567},
            "student": {"variant": "tiny", "source": "variant", "spec": "tiny", "parameters": 54321},
            "config": {"distill": config}, "prior": "data", "data": "prep", "split": "train", "windows": 1234,
            "window_ms": 20.0, "steps": 300, "seconds": 61.25, "seconds_per_step": 0.2041666,
            "machine": {"cpu_model": "Some CPU", "isa": {"kind": "vnni"}}, "final": log[-1], "log": log}


def test_the_markdown_report_line_by_line() -> None:
    text = distill_run.report_markdown(_report(causal=True, stream_windows=4, seq_len=8, batch_size=6))
    assert text == "\n".join([
        "# Distillation: small -> tiny", "",
        "- teacher: `runs/t.pt` (sha256 `0123456789abcdef...`, 1,234,567 parameters)",
        "- student: variant `tiny` (54,321 parameters), prior `data`",
        "- data: `prep` split `train`, 1,234 windows of 8 frames, 20 ms; labels `none`, causal; states carried "
        "over 4 consecutive windows per lane",
        "- 300 steps x 6 windows in 61.2 s (0.204 s/step) on cpu; CPU Some CPU, ISA `vnni`",
        "", "Loss terms (mm, Charbonnier distance per joint; `labels`: the paper's loss):", "",
        "| step | lr | loss | fused | direct | delta |", "|---:|---:|---:|---:|---:|---:|",
        "| 0 | 1.23e-03 | 1.500 | 0.250 | 0.500 | 0.125 |",
        "| 1 | 1.23e-03 | 2.500 | 0.250 | 0.500 | 0.125 |",
        "| 2 | 1.23e-03 | 3.500 | 0.250 | 0.500 | 0.125 |",
    ]) + "\n"
    plain = distill_run.report_markdown(_report())
    assert "non-causal\n" in plain and "states carried" not in plain and "- QAT" not in plain


@pytest.mark.parametrize("cfg, start, line", [
    ({"qat": True}, {"weight_bits": 8, "calibrated": 3, "quantizers": 5, "rule": "mse", "windows": 4,
                     "frames_per_window": 8},
     "- QAT: the default INT8 graph simulated (`--float-outputs {outputs}`, 8-bit weights); 3 of 5 learned ranges "
     "started from `mse` calibration on 4 windows of 8 frames"),
    ({"qat": True, "qat_full_integer": True}, {},
     "- QAT: the full-integer INT8 graph simulated (`--float-outputs {outputs}`); learned ranges started from the "
     "first batch each quantiser saw"),
    ({"qat": True, "qat_ranges_only": True}, {"calibrated": 0},
     "- QAT: the default INT8 graph simulated (`--float-outputs {outputs}`); learned ranges started from the first "
     "batch each quantiser saw; the ranges alone learned, the student's weights and prior kept (its fp32 graph "
     "unchanged)"),
])
def test_the_qat_line(cfg, start, line) -> None:
    config = DistillConfig(**cfg)
    report = {**_report(**cfg), "qat_range_start": start}
    outputs = config.qat_config.simulated_float_outputs
    assert line.format(outputs=outputs) in distill_run.report_markdown(report).splitlines()
    assert distill_run._qat_line(config.to_dict(), start) == line.format(outputs=outputs)


@pytest.mark.parametrize("count, kept", [
    (12, list(range(12))),  # no more than asked: all of them
    (13, list(range(0, 13, 2))),  # stride 2 ends on the last
    (14, [*range(0, 13, 2), 13]),  # the last added
    (21, list(range(0, 21, 2))),  # ceil(21 / 11) = 2
    (25, list(range(0, 25, 3))),
    (100, [*range(0, 100, 10), 99]),
])
def test_the_log_is_thinned_evenly_first_and_last_kept(count, kept) -> None:
    records = [{"step": s} for s in range(count)]
    assert [r["step"] for r in distill_run._thin(records, 12)] == kept


def test_the_library_defaults_no_force_and_a_progress_bar(monkeypatch, tmp_path) -> None:
    fake = RecordingDistill()
    monkeypatch.setattr(distill_run, "distill", fake)
    out = tmp_path / "run"
    distill_run.run_distill(TRAINED_TINY, "tiny", "prep", out, DistillConfig(steps=3))
    assert fake.calls[0][5] is True and fake.calls[0][4] is None  # progress on, the config's own split
    with pytest.raises(OutputExistsError):
        distill_run.run_distill(TRAINED_TINY, "tiny", "prep", out, DistillConfig(steps=3))


def test_the_labels_term_gets_its_column_when_the_run_had_labels() -> None:
    report = _report(labels="gt")
    for record in report["log"]:
        record["labels"] = 2.0
    lines = distill_run.report_markdown(report).splitlines()
    assert "| step | lr | loss | fused | direct | delta | labels |" in lines
    assert "| 0 | 1.23e-03 | 1.500 | 0.250 | 0.500 | 0.125 | 2.000 |" in lines


def test_the_markdown_report_names_the_device_and_the_machine_as_known() -> None:
    report = {**_report(log_steps=24, causal=True, stream_windows=2), "device": "cuda:0 (Some GPU)",
              "machine": {}}
    lines = distill_run.report_markdown(report).splitlines()
    assert "- 300 steps x 4 windows in 61.2 s (0.204 s/step) on cuda:0 (Some GPU); CPU ?, ISA `?`" in lines
    assert any(line.endswith("states carried over 2 consecutive windows per lane") for line in lines)
    rows = [line for line in lines if line.startswith("| ") and line[2].isdigit()]
    assert [int(r.split(" | ")[0][2:]) for r in rows] == [*range(0, 24, 3), 23]  # 24 records thinned to about 12
