"""`e3dpsm pipeline --checkpoint`: every stage after training takes the given checkpoint."""
from __future__ import annotations

import json

import pytest

from _quantize_helpers import TRAINED_TINY
from e3dpsm.checkpoint import CheckpointError
from e3dpsm.pipeline.runner import run_pipeline
from e3dpsm.errors import ConfigError
from e3dpsm.pipeline.stages import STAGES, PipelineConfig, expand_stage_names


def test_stages_use_the_given_checkpoint_and_its_resolution(tmp_path) -> None:
    cfg = PipelineConfig(out=tmp_path / "run", checkpoint=TRAINED_TINY)
    # train is skipped with a checkpoint; clip reads the test split synth writes, edge-check the
    # artifacts the edge stages wrote, so both are built at run time
    argvs = {s.name: s.argv(cfg) for s in STAGES if s.name not in ("train", "clip", "edge-check")}
    using = {name: argv[argv.index("--checkpoint") + 1] for name, argv in argvs.items() if "--checkpoint" in argv}
    assert set(using) == {"evaluate", "export", "parity", "validate", "golden-record", "prune", "executorch",
                          "litert", "profile"}
    assert set(using.values()) == {str(TRAINED_TINY)}
    prepare = argvs["prepare"]
    assert prepare[prepare.index("--height") + 1] == "192" and prepare[prepare.index("--width") + 1] == "256"
    default = {s.name: s.argv(PipelineConfig(out=tmp_path / "run")) for s in STAGES if s.name == "export"}
    assert default["export"][default["export"].index("--checkpoint") + 1] == str(tmp_path / "run/train/checkpoint.pt")


def test_a_bad_checkpoint_is_refused_before_any_stage_runs(tmp_path) -> None:
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        run_pipeline(PipelineConfig(out=tmp_path / "run", checkpoint=bad))
    assert not (tmp_path / "run" / "data").exists()


def test_report_names_the_given_checkpoint_and_its_variant(tmp_path) -> None:
    from e3dpsm.pipeline.report import write_index

    (tmp_path / "export").mkdir()
    (tmp_path / "export" / "export.json").write_text(json.dumps({"model": {"variant": "released"}}))
    write_index(tmp_path, {"checkpoint": "imported/checkpoint.pt", "variant": "small", "seed": 0, "window_ms": 20.0}, [])
    header = (tmp_path / "report" / "index.md").read_text().splitlines()[2]
    assert header.startswith("Checkpoint `imported/checkpoint.pt` (variant `released`, not trained here)")


def test_clip_stage_renders_the_held_out_sequence_into_the_report(tmp_path, synthetic_data,
                                                                   tiny_step_graph) -> None:  # noqa: F811
    import shutil

    from PIL import Image

    run = tmp_path / "run"
    run.mkdir()
    (run / "data").symlink_to(synthetic_data, target_is_directory=True)
    (run / "export").mkdir()
    shutil.copy(tiny_step_graph, run / "export" / "step.onnx")
    run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY), only=["clip"])
    held_out = (synthetic_data / "test.txt").read_text().split()[0]
    report = json.loads((run / "clip" / "poses.report.json").read_text())
    assert held_out in report["config"]["events"]
    with Image.open(run / "clip" / "poses.gif") as gif:
        assert gif.n_frames == min(100, report["windows"])
    assert "![held-out clip](../clip/poses.gif)" in (run / "report" / "index.md").read_text()


def test_prune_stage_is_optional_and_off_by_default(tmp_path, monkeypatch) -> None:
    import e3dpsm.pipeline.runner as runner

    ran: list[list[str]] = []
    monkeypatch.setattr(runner, "run_stage", lambda argv: ran.append(argv) or 0)
    monkeypatch.setattr(runner, "write_index", lambda *a, **k: None)
    run = tmp_path / "run"
    for stage in STAGES:  # every stage done before, so that only the optional one is left
        if not stage.optional:
            (run / stage.marker).parent.mkdir(parents=True, exist_ok=True)
            (run / stage.marker).touch()
    done = run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY))
    assert ran == [] and {d["stage"]: d["status"] for d in done}["prune"] == "skipped"
    run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY, with_stages=("prune",)))
    assert [argv[0] for argv in ran] == ["prune"]
    prune = ran[0]
    assert prune[prune.index("--target-macs") + 1] == "0.5" and prune[prune.index("--checkpoint") + 1] == str(TRAINED_TINY)
    with pytest.raises(Exception, match="unknown stages"):
        run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY, with_stages=("prunee",)))


def test_int8_stage_calibrates_searches_and_checks_on_three_splits(tmp_path) -> None:
    """Calibration on train, the search on val, the final check on test (where the golden check
    runs too); the argv parses as `e3dpsm quantize` arguments."""
    from e3dpsm.cli import build_parser

    argv = next(s for s in STAGES if s.name == "quantize-int8").argv(PipelineConfig(out=tmp_path / "run"))
    args = build_parser().parse_args(argv)
    assert (args.split, args.search_split, args.holdout_split) == ("train", "val", "test")


def _train_stage_steps(cfg: PipelineConfig) -> int:
    from e3dpsm.cli import build_parser

    argv = next(s for s in STAGES if s.name == "train").argv(cfg)
    return build_parser().parse_args(argv).steps


def test_default_training_is_a_fixed_step_count_and_minutes_fit_it_to_a_probe(tmp_path, monkeypatch) -> None:
    """Without --minutes every host and rerun trains the same model; --minutes fits the steps
    to the host by a timing probe (stubbed here: the probe itself is a timing)."""
    from e3dpsm.pipeline import stages

    probed = []
    monkeypatch.setattr(stages, "estimate_train_steps", lambda cfg: probed.append(cfg.minutes) or 77)
    assert _train_stage_steps(PipelineConfig(out=tmp_path)) == stages.DEFAULT_TRAIN_STEPS
    assert _train_stage_steps(PipelineConfig(out=tmp_path, train_steps=33)) == 33
    assert probed == []
    assert _train_stage_steps(PipelineConfig(out=tmp_path, minutes=4.0)) == 77
    assert probed == [4.0]


def test_train_steps_and_minutes_exclude_each_other(tmp_path, capsys) -> None:
    from e3dpsm.cli import main
    from e3dpsm.errors import ConfigError

    with pytest.raises(ConfigError, match="either --train-steps or --minutes"):
        PipelineConfig(out=tmp_path, train_steps=10, minutes=5.0)
    with pytest.raises(ConfigError, match="--train-steps must be positive"):
        PipelineConfig(out=tmp_path, train_steps=0)
    with pytest.raises(SystemExit) as exit_info:
        main(["pipeline", "--out", str(tmp_path / "run"), "--train-steps", "10", "--minutes", "5"])
    assert exit_info.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_index_says_how_many_steps_the_model_trained(tmp_path) -> None:
    from e3dpsm.pipeline.report import write_index

    (tmp_path / "train").mkdir()
    (tmp_path / "train" / "report.json").write_text(json.dumps({"total_steps": 120}))
    write_index(tmp_path, {"variant": "small", "seed": 0, "window_ms": 20.0}, [])
    header = (tmp_path / "report" / "index.md").read_text().splitlines()[2]
    assert header.startswith("Variant `small` trained 120 steps here, synthetic data (seed 0)")


def _stage(name: str):
    return next(s for s in STAGES if s.name == name)


def test_the_edge_stages_are_optional_and_edge_names_all_three(tmp_path, monkeypatch, caplog) -> None:
    """Off by default; `--with edge` runs executorch, litert and edge-check in that order, after
    the golden record they check against and before the profile that times them."""
    import logging

    import e3dpsm.pipeline.runner as runner

    names = [s.name for s in STAGES]
    assert all(_stage(n).optional for n in ("executorch", "litert", "edge-check"))
    assert names.index("golden-record") < names.index("executorch") < names.index("litert") \
        < names.index("edge-check") < names.index("profile")
    assert expand_stage_names(["prune", "edge", "litert"]) == ["prune", "executorch", "litert", "edge-check"]
    ran: list[list[str]] = []
    monkeypatch.setattr(runner, "run_stage", lambda argv: ran.append(argv) or 0)
    monkeypatch.setattr(runner, "write_index", lambda *a, **k: None)
    run = tmp_path / "run"
    for stage in STAGES:
        if not stage.optional and stage.name != "train":  # train: skipped for the checkpoint
            (run / stage.marker).parent.mkdir(parents=True, exist_ok=True)
            (run / stage.marker).touch()
    (run / "edge/litert").mkdir(parents=True)
    (run / "edge/litert/step.tflite").touch()  # what the litert stage leaves, for edge-check's argv
    with caplog.at_level(logging.INFO, logger=runner.__name__):
        done = run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY))
    assert ran == [] and done == [{"stage": s.name, "status": "skipped", "seconds": 0.0} for s in STAGES]
    logged = [r.getMessage() for r in caplog.records]
    index = names.index("executorch") + 1
    assert f"[{index}/{len(STAGES)}] executorch: optional, not asked for (--with executorch or --with edge)" in logged
    assert f"[{names.index('prune') + 1}/{len(STAGES)}] prune: optional, not asked for (--with prune)" in logged
    assert f"[3/{len(STAGES)}] train: skipped, --checkpoint {TRAINED_TINY} given" in logged
    run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY, with_stages=("edge",)))
    assert [argv[:2] for argv in ran] == [["convert", "executorch"], ["convert", "litert"], ["golden", "check"]]
    ran.clear()
    caplog.clear()
    with caplog.at_level(logging.INFO, logger=runner.__name__):
        run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY), only=["edge"])
    assert [argv[:2] for argv in ran] == [["convert", "executorch"], ["convert", "litert"], ["golden", "check"]]
    logged = [r.getMessage() for r in caplog.records]
    assert f"[1/{len(STAGES)}] synth: not in --only, left as it is" in logged
    assert not any("done before" in line for line in logged)
    with pytest.raises(ConfigError, match=r"^unknown stages \['edges'\]; stages: synth, .* \(groups: edge: "
                                          r"executorch litert edge-check\)$"):
        run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY, with_stages=("edges",)))


def test_edge_stage_commands_parse_and_check_and_profile_what_was_written(tmp_path) -> None:
    from e3dpsm.cli import build_parser

    cfg = PipelineConfig(out=tmp_path / "run", checkpoint=TRAINED_TINY, threads=3)
    parser = build_parser()
    for name, out in (("executorch", "edge/executorch"), ("litert", "edge/litert")):
        args = parser.parse_args(_stage(name).argv(cfg))
        assert (args.checkpoint, args.out, args.force, args.quantize) == (str(TRAINED_TINY), str(cfg.out / out),
                                                                          True, None)
        assert _stage(name).marker == f"{out}/convert.json"
    profile = _stage("profile").argv(cfg)
    assert "--edge-models" not in profile
    with pytest.raises(ConfigError, match=r"^edge-check has no artifact to check: run it with --with executorch "
                                          r"and/or litert \(or --with edge\)$"):
        _stage("edge-check").argv(cfg)
    written = [cfg.out / "edge/executorch/step.pte", cfg.out / "edge/litert/step.tflite"]
    for path in written[::-1]:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()
        check = parser.parse_args(_stage("edge-check").argv(cfg))
        assert check.model == [str(p) for p in written if p.exists()]
    assert (check.golden, check.out, check.threads, check.exit_zero) == (
        str(cfg.out / "golden/record"), str(cfg.out / "edge/checks"), 3, False)
    assert _stage("edge-check").marker == "edge/checks/summary.json"
    profile = parser.parse_args(_stage("profile").argv(cfg))
    assert profile.edge_models == [str(p) for p in written]
    assert (profile.targets, profile.data, profile.out) == ("all", str(cfg.out / "prepared"), str(cfg.out / "profile"))


def test_each_edge_stage_links_the_reports_its_command_writes() -> None:
    """What the index's stage table links: convert's convert.json, golden check's summary."""
    reports = {s.name: (s.marker, s.human_report, s.machine_report) for s in STAGES}
    assert reports["executorch"] == ("edge/executorch/convert.json",) * 3
    assert reports["litert"] == ("edge/litert/convert.json",) * 3
    assert reports["edge-check"] == ("edge/checks/summary.json", "edge/checks/summary.md", "edge/checks/summary.json")
    assert reports["profile"] == ("profile/report.json", "profile/report.md", "profile/report.json")


@pytest.mark.slow
def test_the_edge_stages_convert_check_and_report_the_trained_tiny(tmp_path, prepared_data) -> None:
    """`--only edge` on a run that has its golden: the two fp32 artifacts converted by their
    commands, both passing their golden check on their own runtimes, the index's edge section."""
    pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")
    pytest.importorskip("litert_torch", reason="litert-torch (pip extra litert) is not installed")
    from e3dpsm.cli import main

    run = tmp_path / "run"
    assert main(["golden", "record", "--checkpoint", str(TRAINED_TINY), "--data", str(prepared_data), "--split",
                 "test", "--steps", "20", "--out", str(run / "golden/record")]) == 0
    done = run_pipeline(PipelineConfig(out=run, checkpoint=TRAINED_TINY), only=["edge"])
    assert [d["stage"] for d in done if d["status"] == "ran"] == ["executorch", "litert", "edge-check"]
    summary = json.loads((run / "edge/checks/summary.json").read_text())
    checks = {(c["model"].rsplit("/", 1)[-1], c["runtime"]): c for c in summary["checks"]}
    assert summary["passed"] and set(checks) == {("step.pte", "executorch"), ("step.tflite", "litert")}
    assert all(c["status"] == "passed" and c["profile"] == "fp32" and c["pose_max"] < 0.01 for c in checks.values())
    index = (run / "report/index.md").read_text()
    section = index[index.index("## Edge artifacts"):index.index("## Stages")]
    assert "| [edge/executorch/step.pte](../edge/executorch/step.pte) |" in section
    assert "| [edge/litert/step.tflite](../edge/litert/step.tflite) |" in section and "**passed**" in section
