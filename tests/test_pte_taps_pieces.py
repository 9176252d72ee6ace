"""e3dpsm/golden/pte_taps.py and the taps program's checks (export/executorch_taps.py) on the
toy `.pte` of tests/_toy_pte.py and its taps program: what a record holds (the taps digested
against numpy's own codes), where two traces part, the lines it prints, what it refuses, and
the host check that a taps program computes its shipped program's poses. Taps of a real INT8
program: tests/test_executorch_taps_pieces.py (PT2E) and benchmarks/arm_emulation.py --trace."""
from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")

from _golden_fakes import STATE_SHAPE, parted_record, write_golden  # noqa: E402
from _toy_pte import TAPS, toy_pose, toy_pte, toy_taps  # noqa: E402
from e3dpsm.errors import DataError, InputError  # noqa: E402
from e3dpsm.export.executorch_taps import steps_identical, taps_path  # noqa: E402
from e3dpsm.golden.pte_taps import compare, describe, main, program_taps, read_trace, record, summary  # noqa: E402
from e3dpsm.runtime.artifact_metadata import TAPS_METHOD, decode_taps, encode_taps  # noqa: E402

STEPS = 5


@pytest.fixture(scope="module")
def programs(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("taps")
    made = {"shipped": toy_pte(precision="int8", delegated=True),
            "taps": toy_pte(precision="int8", delegated=True, taps=True),
            "other": toy_pte(precision="int8", delegated=True, taps=True, pose_offset=0.5)}
    for name, content in made.items():
        (folder / f"{name}.pte").write_bytes(content)
    return {name: folder / f"{name}.pte" for name in made}


@pytest.fixture(scope="module")
def golden(tmp_path_factory) -> Path:
    return write_golden(tmp_path_factory.mktemp("golden") / "golden", STEPS)


@pytest.fixture(scope="module")
def trace(programs, golden) -> dict:
    return record(programs["taps"], golden)


def _digest(array: np.ndarray) -> str:
    return hashlib.blake2b(np.ascontiguousarray(array).tobytes(), digest_size=8).hexdigest()


def test_a_record_digests_every_tap_at_every_step_against_numpy(trace, golden) -> None:
    from e3dpsm.golden.store import load_golden

    assert trace["steps"] == STEPS and len(trace["digests"]) == STEPS and trace["isa"]["kind"]
    assert trace["taps"] == [{**TAPS[0], "shape": [1, 2, 4, 4], "dtype": "int8"},
                             {**TAPS[1], "shape": [1, *STATE_SHAPE], "dtype": "int8"}]
    stored = load_golden(golden)
    state = np.zeros((1, *STATE_SHAPE), np.float32)
    for step in range(STEPS):
        state = state + np.float32(stored.window_ms(step))  # carried by the runtime from zero
        want = toy_taps(stored.frame(step)[None], state)
        assert trace["digests"][step] == [_digest(w) for w in want], step
    assert len(set(trace["digests"][s][1] for s in range(STEPS))) == STEPS  # the state tap moves every step


def test_a_program_without_taps_is_refused_in_one_line(programs, golden, tmp_path, capsys) -> None:
    with pytest.raises(InputError, match=r"shipped\.pte has no taps: write its taps program with `e3dpsm convert "
                                         r"executorch --quantize int8 --taps`"):
        record(programs["shipped"], golden)
    assert main(["record", str(programs["shipped"]), str(golden), str(tmp_path / "t.json")]) == 2
    assert capsys.readouterr().err.startswith("pte_taps: error: ") and not (tmp_path / "t.json").exists()
    with pytest.raises(InputError, match="^--steps 0: a trace needs at least one step$"):
        record(programs["taps"], golden, steps=0)
    one = record(programs["taps"], golden, steps=1)
    assert one["steps"] == 1 and len(one["digests"]) == 1


def test_the_first_tap_apart_is_at_the_earliest_step_then_in_program_order(trace) -> None:
    same = compare(trace, json.loads(json.dumps(trace)))
    assert same["first_step"] is None and same["apart_by_end"] == 0 and same["taps"] == 2
    assert summary(same) == f"all 2 taps the same at every one of {STEPS} steps"
    device = parted_record(parted_record(trace, 3, [0]), 1, [1])
    report = compare(trace, device)
    assert report["first_step"] == 1 and report["apart_by_end"] == 2
    assert [t["tap"] for t in report["first_departures"]] == [TAPS[1]["tap"]]
    assert [t["first_step"] for t in report["per_tap"]] == [3, 1]
    assert summary(report) == ("taps part first at step 1, first in program order toy.state:codes (tap 1, after "
                               f"add, round, clamp); 2 of 2 taps apart by step {STEPS - 1}")
    both = compare(trace, parted_record(trace, 2, [0, 1]))
    assert summary(both) == ("taps part first at step 2, first in program order toy.frame:codes (tap 0, after mul, "
                             f"round, clamp), then 1 more at that step; 2 of 2 taps apart by step {STEPS - 1}")
    no_segment = json.loads(json.dumps(both["first_departures"][0]))
    no_segment["segment"] = []
    assert describe(no_segment) == "toy.frame:codes (tap 0, a program input)"
    long = {**no_segment, "segment": ["matmul", "sub", "mul", "matmul", "add", "rsqrt", "mul", "add"]}
    assert describe(long) == "toy.frame:codes (tap 0, after matmul, sub, mul, matmul, add, rsqrt, mul, add)"
    long["segment"] = long["segment"] + ["gelu"]
    assert describe(long) == "toy.frame:codes (tap 0, after 9 operators: matmul, sub, mul, add, rsqrt, gelu)"
    renamed = json.loads(json.dumps(trace))
    renamed["taps"][0]["tap"] = "elsewhere:codes"
    with pytest.raises(ValueError, match=r"^the two traces are of different programs \(their taps differ\)$"):
        compare(trace, renamed)
    device["isa"] = {"kind": "dotprod", "flags": ["asimd"]}
    isas = compare(trace, device)
    assert isas["host_isa"] == trace["isa"] and isas["device_isa"] == {"kind": "dotprod", "flags": ["asimd"]}


def test_cli_records_and_compares_in_one_line(programs, golden, tmp_path, capsys) -> None:
    host, out = tmp_path / "host.json", tmp_path / "cmp.json"
    assert main(["record", str(programs["taps"]), str(golden), str(host), "--steps", "3"]) == 0
    assert read_trace(host)["steps"] == 3
    assert main(["compare", str(host), str(host), "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == "all 2 taps the same at every one of 3 steps"
    assert json.loads(out.read_text())["first_step"] is None
    (tmp_path / "bad.json").write_text(json.dumps({"model": "m", "steps": 1, "taps": [{"x": 1}], "digests": [["a"]],
                                                   "isa": {}}))
    assert main(["compare", str(tmp_path / "bad.json"), str(host)]) == 2
    assert capsys.readouterr().err.strip().endswith("its taps are not a list of taps")


def test_the_taps_program_computes_its_shipped_programs_steps(programs) -> None:
    frames = [np.full((1, 2, 4, 4), 0.25 * k, np.float32) for k in range(4)]
    windows = [20.0, 10.0, 20.0, 5.0]
    assert steps_identical(programs["shipped"], programs["taps"], frames, windows) == 4
    assert steps_identical(programs["shipped"], programs["other"], frames, windows) == 0
    assert steps_identical(programs["shipped"], programs["taps"], frames[:2], windows[:2]) == 2
    pose = toy_pose(frames[0], windows[0])
    assert not np.array_equal(pose, pose + np.float32(0.5))  # the offset is visible in float32


def test_the_tap_names_travel_in_the_program(programs) -> None:
    from e3dpsm.runtime.executorch_session import load_program

    assert program_taps(load_program(programs["taps"]), "t") == TAPS
    assert program_taps(load_program(programs["shipped"]), "s") is None
    assert TAPS_METHOD == "e3dpsm_taps" and decode_taps(encode_taps(TAPS), "x") == TAPS
    for text in ("[]", '[{"tap": "a"}]', '[{"tap": 1, "segment": []}]', '[{"tap": "a", "segment": "x"}]', '["a"]',
                 '{"tap": "a", "segment": []}'):
        with pytest.raises(ValueError, match="^src: its e3dpsm_taps is not a list of taps \\(each a name and its "):
            decode_taps(text, "src")
    with pytest.raises(ValueError, match="^src: its e3dpsm_taps is not JSON"):
        decode_taps("{", "src")
    assert taps_path("et8/step.pte") == "et8/step_taps.pte" and taps_path(Path("a.b/p")) == "a.b/p_taps"


def test_a_record_whose_digests_do_not_fit_its_taps_is_refused(trace, tmp_path) -> None:
    short = json.loads(json.dumps(trace))
    short["digests"][2] = short["digests"][2][:1]
    path = tmp_path / "short.json"
    path.write_text(json.dumps(short))
    with pytest.raises(DataError, match=rf"short\.json: its digests are not {STEPS} steps of 2 taps each$"):
        read_trace(path)


def test_a_program_returning_other_than_its_outputs_and_taps_is_refused(golden, tmp_path) -> None:
    path = tmp_path / "liar.pte"
    path.write_bytes(toy_pte(precision="int8", taps=True, declared_taps=[*TAPS, {"tap": "x:y", "segment": []}]))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))} returned 2 values past its 2 outputs, not its 3 taps$"):
        record(path, golden)


def test_the_help_names_both_commands(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert ("record digests of every tap of a taps program at every golden step, on this machine compare where two "
            "machines' taps part (host first) ") in out
