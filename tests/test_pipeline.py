"""`e3dpsm pipeline --checkpoint`: every stage after training takes the given checkpoint."""
from __future__ import annotations

import pytest

from _quantize_helpers import TRAINED_TINY
from e3dpsm.checkpoint import CheckpointError
from e3dpsm.pipeline import STAGES, PipelineConfig, run_pipeline


def test_stages_use_the_given_checkpoint_and_its_resolution(tmp_path) -> None:
    cfg = PipelineConfig(out=tmp_path / "run", checkpoint=TRAINED_TINY)
    argvs = {s.name: s.argv(cfg) for s in STAGES if s.name != "train"}
    using = {name: argv[argv.index("--checkpoint") + 1] for name, argv in argvs.items() if "--checkpoint" in argv}
    assert set(using) == {"evaluate", "export", "parity", "validate", "profile"}
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
    import json

    from e3dpsm.pipeline_report import write_index

    (tmp_path / "export").mkdir()
    (tmp_path / "export" / "export.json").write_text(json.dumps({"model": {"variant": "released"}}))
    write_index(tmp_path, {"checkpoint": "imported/checkpoint.pt", "variant": "small", "seed": 0, "window_ms": 20.0}, [])
    header = (tmp_path / "report" / "index.md").read_text().splitlines()[2]
    assert header.startswith("Checkpoint `imported/checkpoint.pt` (variant `released`, not trained here)")
