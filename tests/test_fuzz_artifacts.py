"""Fuzzing what e3dpsm reads besides event files, each input in a bounded child process:

- the released checkpoint importer, on damaged copies of what torch.save wrote (a small
  Lightning-like checkpoint; the full released one in the slow pass): it must end with the
  tensors or one CheckpointError line, never running pickled code (weights_only);
- `golden check` on damaged copies of what `golden record` wrote (rollout.npz byte by byte,
  golden.json byte by byte and value by value): exit 0 or 1 (a verdict) or 2 with one
  `e3dpsm golden: error:` line and nothing written;
- the viewer's client-message parser on arbitrary text and damaged valid messages: a
  message or a close code with a one-line reason.
"""
from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from _bounded import BoundedWorker
from _fuzz import (BOUND_S, CLI_BOUND_S, FUZZ_EXAMPLES, SLOW_EXAMPLES, Counts, Seed, damaged, fuzz_settings,
                   json_damaged, outcome_label, write_input, zip_fields)
from e3dpsm.cli import main

GOLDEN_EXAMPLES = 5  # each runs the graph: fewer in the default pass


@pytest.fixture(scope="module")
def worker():
    preload = ("_fuzz_targets", "torch", "e3dpsm.importers.released", "e3dpsm.golden.verify", "e3dpsm.serve.protocol")
    with BoundedWorker(preload=preload) as bounded:
        yield bounded


# -- the released checkpoint --------------------------------------------------------------------
def small_lightning_checkpoint() -> dict:
    """What a Lightning checkpoint of the released code holds, at a small size: a few network
    tensors, the Kalman filter's, a BatchNorm counter, hyper-parameters and the version."""
    g = torch.Generator().manual_seed(0)
    state = {"event_3d_posenet.conv1.0.weight": torch.randn(8, 2, 3, 3, generator=g),
             "event_3d_posenet.conv1.0.bias": torch.zeros(8),
             "event_3d_posenet.encoder_backbone.0.0.res_blocks.0.bn1.num_batches_tracked": torch.tensor(1000),
             "kalman_filter.F": torch.eye(48), "kalman_filter.log_process_var": torch.randn(48, generator=g)}
    return {"epoch": 14, "global_step": 52_500, "pytorch-lightning_version": "2.1.3",
            "hyper_parameters": {"lr": 1e-3, "betas": (0.9, 0.999), "name": "E3DPSM"},
            "state_dict": {f"model.{k}": v for k, v in state.items()}}


def checkpoint_seed(path: Path, payload: dict) -> Seed:
    torch.save(payload, path)
    data = path.read_bytes()
    fields, hot = zip_fields(data)
    return Seed(path.name, data, "torch.save", fields=fields, hot=hot)


@pytest.fixture(scope="module")
def small_checkpoint(tmp_path_factory) -> Seed:
    return checkpoint_seed(tmp_path_factory.mktemp("released_seed") / "epoch=14.ckpt", small_lightning_checkpoint())


def checkpoint_pass(seed: Seed, worker: BoundedWorker, folder: Path, target: str, examples: int,
                    derandomize: bool = True, bound_s: float = BOUND_S) -> None:
    counts = Counts(f"{target.split(':')[1]} {seed.name} ({seed.writer})", bound_s)

    @fuzz_settings(examples, derandomize)
    @given(damaged(seed))
    def read_damaged(case):
        outcome = worker.call(target, str(write_input(folder, seed, case.data)), bound_s=bound_s)
        counts.add(outcome_label(outcome), outcome.seconds, "; ".join(case.steps))
        assert outcome.kind in ("returned", "refused"), f"{list(case.steps)}: {outcome.kind}: {outcome.detail}"
        if outcome.kind == "refused":
            assert outcome.detail.startswith("CheckpointError: ") and "\n" not in outcome.detail, outcome.detail

    try:
        read_damaged()
    finally:
        counts.report()


def test_the_checkpoint_seed_reads(small_checkpoint, worker, tmp_path):
    outcome = worker.call("_fuzz_targets:read_released", str(write_input(tmp_path, small_checkpoint,
                                                                           small_checkpoint.data)), bound_s=BOUND_S)
    assert outcome.kind == "returned" and outcome.value == ("lightning checkpoint", 5), outcome


def test_damaged_checkpoints_end_with_tensors_or_one_error_line(small_checkpoint, worker, tmp_path):
    checkpoint_pass(small_checkpoint, worker, tmp_path, "_fuzz_targets:read_released", FUZZ_EXAMPLES)


@pytest.mark.slow
def test_damaged_checkpoints_long_pass(small_checkpoint, worker, tmp_path):
    checkpoint_pass(small_checkpoint, worker, tmp_path, "_fuzz_targets:read_released", SLOW_EXAMPLES, False)


@pytest.mark.slow
def test_damaged_full_released_checkpoints_import_or_refuse(worker, tmp_path):
    """The whole import (read, map onto the `released` variant, check) on the 26 MB released
    checkpoint; positions drawn mostly in its pickle and zip structure (`hot`)."""
    from tests.fixtures.released.weights import lightning_checkpoint, make_state_dict

    manifest = json.loads((Path(__file__).parent / "fixtures" / "released" / "manifest.json").read_text())
    seed = checkpoint_seed(tmp_path / "seed.ckpt", lightning_checkpoint(make_state_dict(manifest["layout"],
                                                                                          manifest["seed"])))
    # the import builds the 6.6 M-parameter model and maps 26 MB: a command's bound, not a read's
    checkpoint_pass(seed, worker, tmp_path, "_fuzz_targets:import_released", max(SLOW_EXAMPLES // 10, 20), False,
                    bound_s=CLI_BOUND_S)


# -- the golden record ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def golden(tmp_path_factory, quant_data, trained_graph) -> tuple[Path, Path]:
    """(graph, golden folder): 6 steps recorded by the project's writer with ONNX Runtime."""
    out = tmp_path_factory.mktemp("golden_seed") / "golden"
    assert main(["golden", "record", "--model", str(trained_graph), "--data", str(quant_data), "--steps", "6",
                 "--threads", "1", "--out", str(out)]) == 0
    return trained_graph, out


def golden_seed(folder: Path, name: str) -> Seed:
    data = (folder / name).read_bytes()
    if name.endswith(".npz"):
        fields, hot = zip_fields(data)
        return Seed(name, data, "golden record", fields=fields, hot=hot)
    return Seed(name, data, "golden record")


GOLDEN_CASES = {"rollout.npz": damaged, "golden.json": damaged, "golden.json values": json_damaged}


def golden_pass(golden: tuple[Path, Path], worker: BoundedWorker, folder: Path, case_name: str, examples: int,
                derandomize: bool = True) -> None:
    graph, record = golden
    seed = golden_seed(record, case_name.split()[0])
    counts = Counts(f"golden check, {case_name} ({seed.writer})", CLI_BOUND_S)
    runs = itertools.count()

    @fuzz_settings(examples, derandomize)
    @given(GOLDEN_CASES[case_name](seed))
    def check_damaged(case):
        run = next(runs)
        damaged_record = folder / f"golden_{run}"
        shutil.copytree(record, damaged_record, dirs_exist_ok=True)
        write_input(damaged_record, seed, case.data)
        out = folder / f"check_{run}"
        outcome = worker.call("_fuzz_targets:run_cli", ["golden", "check", "--model", str(graph), "--golden",
                                                         str(damaged_record), "--out", str(out), "--threads", "1"],
                              bound_s=CLI_BOUND_S)
        where = f"{case_name} after {list(case.steps)}"
        assert outcome.kind == "returned", f"{where}: {outcome.kind}: {outcome.detail}"
        code, _, err = outcome.value
        counts.add(f"exit_{code}", outcome.seconds, "; ".join(case.steps))
        assert code in (0, 1, 2), f"{where}: exit {code}: {err}"
        if code == 2:
            assert len(err.splitlines()) == 1 and err.startswith("e3dpsm golden: error: "), f"{where}: {err}"
            assert not out.exists(), f"{where}: exit 2 but {out} was written"
        else:
            assert (out / "check.json").is_file(), where
        shutil.rmtree(damaged_record)
        shutil.rmtree(out, ignore_errors=True)

    try:
        check_damaged()
    finally:
        counts.report()


@pytest.mark.parametrize("case_name", GOLDEN_CASES)
def test_damaged_goldens_give_a_verdict_or_one_error_line(golden, worker, tmp_path, case_name):
    golden_pass(golden, worker, tmp_path, case_name, GOLDEN_EXAMPLES)


@pytest.mark.slow
@pytest.mark.parametrize("case_name", GOLDEN_CASES)
def test_damaged_goldens_long_pass(golden, worker, tmp_path, case_name):
    golden_pass(golden, worker, tmp_path, case_name, max(SLOW_EXAMPLES // 4, GOLDEN_EXAMPLES), False)


def test_the_undamaged_golden_passes(golden, worker, tmp_path):
    graph, record = golden
    outcome = worker.call("_fuzz_targets:run_cli", ["golden", "check", "--model", str(graph), "--golden", str(record),
                                                     "--out", str(tmp_path / "check")], bound_s=CLI_BOUND_S)
    assert outcome.kind == "returned" and outcome.value[0] == 0, outcome


# -- the viewer's client messages ----------------------------------------------------------------
VALID_MESSAGES = ['{"type": "ping", "t": 12.5}', '{"type": "hello", "agent": "Chromium"}',
                  '{"type": "latency", "samples_ms": [1.5, 2], "received": 3, "drawn": 3, "gaps": 0, '
                  '"out_of_order": 0}']


@st.composite
def client_messages(draw: st.DrawFn) -> str:
    """Arbitrary text, JSON objects of the known types with fields of any JSON type, and valid
    messages damaged byte by byte."""
    from _fuzz import JSON_VALUES

    kind = draw(st.sampled_from(("text", "object", "damaged")))
    if kind == "text":
        return draw(st.text(max_size=200))
    if kind == "object":
        fields = draw(st.dictionaries(st.sampled_from(("t", "agent", "samples_ms", "received", "drawn", "gaps",
                                                       "out_of_order", "x")), JSON_VALUES, max_size=6))
        return json.dumps({"type": draw(st.sampled_from(("ping", "hello", "latency", "pose", ""))), **fields})
    text = draw(st.sampled_from(VALID_MESSAGES))
    return draw(damaged(Seed("m", text.encode()))).data.decode("utf-8", "replace")


def message_pass(worker: BoundedWorker, examples: int, derandomize: bool = True) -> None:
    counts = Counts("serve protocol parse_client_message", BOUND_S)

    @fuzz_settings(examples, derandomize)
    @given(client_messages())
    def parse(text):
        outcome = worker.call("_fuzz_targets:parse_client_message", text, bound_s=BOUND_S)
        assert outcome.kind == "returned", f"{text!r}: {outcome.kind}: {outcome.detail}"
        counts.add(outcome.value[0], outcome.seconds, repr(text)[:80])
        if outcome.value[0] == "closed":
            _, code, reason = outcome.value
            assert code in (1007, 1008) and reason and "\n" not in reason and len(reason.encode()) <= 120, outcome

    try:
        parse()
    finally:
        counts.report()


def test_client_messages_are_accepted_or_close_the_client_with_a_reason(worker):
    message_pass(worker, 4 * FUZZ_EXAMPLES)


@pytest.mark.slow
def test_client_messages_long_pass(worker):
    message_pass(worker, 4 * SLOW_EXAMPLES, False)
