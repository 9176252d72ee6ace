"""`e3dpsm prune --replay` (compress/replay.py) on the tiny, without a prune run: a report's
cuts read back, applied round by round (round 2 cuts round 1's model, its channels ranked on
round 1's weights), checked against the report's MACs, and every refusal whole."""
from __future__ import annotations

import json

import pytest
import torch

import e3dpsm
from _model_helpers import randomised_tiny
from e3dpsm.checkpoint import read_checkpoint, save_checkpoint
from e3dpsm.compress.importance import keep_top
from e3dpsm.compress.plan import total_macs
from e3dpsm.compress.replay import replay_cuts, replay_prune_report, replayable_cuts
from e3dpsm.compress.units import prunable_units
from e3dpsm.errors import ConfigError, OutputExistsError

ROUND1 = {"stages.1.block2": 10, "ssm.3.s5": 8}
ROUND2 = {"stages.1.block2": 6, "attention.2": 0}


@pytest.fixture(scope="module")
def teacher() -> e3dpsm.E3DPSM:
    return randomised_tiny(5)


@pytest.fixture(scope="module")
def replayed(teacher) -> tuple[e3dpsm.E3DPSM, int]:
    """The teacher after both rounds, and its MACs (each replay counts them: about 2 s)."""
    student = replay_cuts(teacher, [ROUND1, ROUND2])
    return student, total_macs(student)


def _report(macs: int, steps: int = 0, best: int = 2) -> dict:
    return {"config": {"steps": steps, "target_macs": 0.8}, "best": best,
            "rounds": [{"cuts": {}, "macs": 1}, {"cuts": ROUND1, "macs": 2}, {"cuts": ROUND2, "macs": macs},
                       {"cuts": {"stages.0.block1": 2}, "macs": 3}]}


def test_the_chosen_rounds_cuts_and_macs_are_read_from_the_report() -> None:
    assert replayable_cuts(_report(123)) == ([ROUND1, ROUND2], 123)
    assert replayable_cuts(_report(7, best=1)) == ([ROUND1], 2)
    assert replayable_cuts(_report(7, best=0)) == ([], 1)


@pytest.mark.parametrize("report, missing", [
    ({"best": 1, "rounds": []}, "'config'"),
    ({"config": {}, "best": 1, "rounds": []}, "'steps'"),
    ({"config": {"steps": 0}, "rounds": []}, "'best'"),
    ({"config": {"steps": 0}, "best": 1}, "'rounds'"),
    ({"config": {"steps": 0}, "best": 3, "rounds": [{"cuts": {}, "macs": 1}]}, "list index out of range"),
    ({"config": {"steps": 0}, "best": 1, "rounds": [{"cuts": {}}, {"cuts": {}}]}, "'macs'"),
    ({"config": {"steps": 0}, "best": "x", "rounds": []}, "invalid literal for int() with base 10: 'x'"),
    ({"config": None, "best": 1, "rounds": []}, "'NoneType' object is not subscriptable"),
])
def test_a_file_that_is_not_a_prune_report_is_refused(report, missing) -> None:
    with pytest.raises(ConfigError) as refused:
        replayable_cuts(report, "r.json")
    assert str(refused.value) == f"r.json is not an `e3dpsm prune` report.json (missing {missing})"
    with pytest.raises(ConfigError, match=r"^the report is not an"):
        replayable_cuts(report)


def test_a_run_that_recovered_between_rounds_is_refused() -> None:
    with pytest.raises(ConfigError) as refused:
        replayable_cuts(_report(1, steps=40), "r.json")
    assert str(refused.value) == (
        "r.json: a prune run with --steps 40; its cuts replay exactly only from a run with --steps 0 (recovery "
        "between rounds changes the weights the next round's cuts were read from)")


def test_each_round_cuts_the_previous_rounds_model(teacher, replayed) -> None:
    student, _ = replayed
    assert student.config.res_hidden[3] == 6 and student.config.ssm_state_dims[-1] == 8
    assert 2 in student.config.attn_removed and not student.training
    # Round 2 ranked stages.1.block2's channels on round 1's model: the 6 it kept are, in round
    # 1's numbering, its top 6 there; in the teacher's numbering, round 1's top 10 then those.
    after_round1 = replay_cuts(teacher, [ROUND1])
    units = {u.name: u for u in prunable_units(after_round1.config)}
    kept1 = keep_top(teacher, {u.name: u for u in prunable_units(teacher.config)}["stages.1.block2"], 10)
    kept2 = keep_top(after_round1, units["stages.1.block2"], 6)
    conv = teacher.get_submodule("stages.1.block2").conv1.weight
    torch.testing.assert_close(student.get_submodule("stages.1.block2").conv1.weight,
                               conv[[kept1[i] for i in kept2]], rtol=0, atol=0)
    assert replay_cuts(teacher, []) is teacher


def test_the_macs_must_be_the_reports(teacher, replayed) -> None:
    _, macs = replayed
    with pytest.raises(ConfigError) as refused:
        replay_cuts(teacher, [ROUND1, ROUND2], macs + 1)
    assert str(refused.value) == (f"the replayed model has {macs:,} MACs, the report's {macs + 1:,}: the report was "
                                  "not made by pruning this checkpoint")


@pytest.mark.parametrize("cuts, error", [
    ({"stages.9.block1": 4}, "'stages.9.block1'"),
    ({"stages.1.block2": 99}, "selected index k out of range"),
])
def test_cuts_that_do_not_fit_the_model_are_refused(teacher, cuts, error) -> None:
    with pytest.raises(ConfigError) as refused:
        replay_cuts(teacher, [ROUND1, cuts])
    assert str(refused.value).startswith("round 2's cuts do not fit this model (")
    assert error in str(refused.value)
    assert str(refused.value).endswith("); was the report made by pruning this checkpoint?")


def test_the_replayed_checkpoint_is_written_with_its_provenance(teacher, replayed, tmp_path) -> None:
    student, macs = replayed
    save_checkpoint(tmp_path / "teacher.pt", teacher, step=500, window_ms=25.0)
    report = tmp_path / "report.json"
    report.write_text(json.dumps(_report(macs)))
    result = replay_prune_report(str(tmp_path / "teacher.pt"), str(report), str(tmp_path / "out"))
    assert result == {"rounds": 2, "params": student.num_parameters(), "macs": macs,
                      "macs_fraction": macs / total_macs(teacher), "checkpoint": str(tmp_path / "out" / "checkpoint.pt")}
    payload = read_checkpoint(tmp_path / "out" / "checkpoint.pt")
    assert payload["step"] == 0 and payload["window_ms"] == 25.0
    assert payload["prune"] == {"round": 2, "source": str(tmp_path / "teacher.pt"), "replayed_from": str(report),
                                "config": {"steps": 0, "target_macs": 0.8}, "cuts": [ROUND1, ROUND2]}
    assert payload["config"] == student.config.to_dict()
    for name, value in student.state_dict().items():
        assert torch.equal(payload["model"][name], value), name
    with pytest.raises(OutputExistsError):  # refused before the teacher loads
        replay_prune_report(str(tmp_path / "missing.pt"), str(report), str(tmp_path / "out"))


def test_an_unreadable_report_is_one_line(teacher, tmp_path) -> None:
    (tmp_path / "r.json").write_text("{not json")
    with pytest.raises(ConfigError) as refused:
        replay_prune_report("unused.pt", str(tmp_path / "r.json"), str(tmp_path / "out"))
    assert str(refused.value).startswith(f"cannot read the prune report {tmp_path / 'r.json'}: Expecting property name")
    with pytest.raises(ConfigError, match="cannot read the prune report .*No such file"):
        replay_prune_report("unused.pt", str(tmp_path / "none.json"), str(tmp_path / "out"))
    assert not (tmp_path / "out").exists()
