"""`e3dpsm run`'s request (runtime/run_command.py) without a graph: every refusal in full, the
edges it accepts, what it normalises, and the output checks made before any model is opened."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from e3dpsm.errors import ConfigError, DataError, OutputExistsError
from e3dpsm.runtime.run_command import RunRequest, RunResult, run_poses


def _request(tmp_path: Path, **fields) -> RunRequest:
    return RunRequest(**{"model": "missing.onnx", "events": ("a.h5",), "out": tmp_path / "p.csv", **fields})


@pytest.mark.parametrize("fields, message", [
    ({"events": ()}, "give at least one --events file"),
    ({"events": ("a.h5", "b.h5"), "render": "x.mp4"}, "--render draws one stream: pass a single --events file"),
    ({"events": ("a.h5", "b.h5"), "render_max_frames": 3}, "--render draws one stream: pass a single --events file"),
    ({"chunk_events": 0}, "--chunk-events must be positive, got 0"),
    ({"chunk_events": -5}, "--chunk-events must be positive, got -5"),
    ({"threads": 0}, "--threads must be positive, got 0"),
    ({"max_gap_s": 0.0}, "--max-gap-s must be positive, got 0.0"),
    ({"max_gap_s": float("nan")}, "--max-gap-s must be positive, got nan"),
    ({"events": ("a.h5", "dv://h:1")}, "a live dv:// source runs alone: pass it as the only --events"),
    ({"events": ("dv://h:1",), "render": "x.mp4"},
     "--render draws a recording; it is not available for a live dv:// source"),
    ({"events": ("dv://h:1",), "max_seconds": 0.0}, "--max-seconds must be positive, got 0.0"),
    ({"render_max_frames": 3}, "--render-max-frames needs --render PATH"),
])
def test_each_refusal_is_its_whole_line(tmp_path, fields, message) -> None:
    with pytest.raises(ConfigError) as info:
        _request(tmp_path, **fields)
    assert str(info.value) == message
    assert list(tmp_path.iterdir()) == []


def test_the_edges_are_accepted_and_the_request_is_normalised_and_frozen(tmp_path) -> None:
    request = RunRequest(model="m.onnx", events=[tmp_path / "a.h5"], out=str(tmp_path / "p.csv"), chunk_events=1,
                         threads=1, max_gap_s=1e-6)
    assert request.events == (str(tmp_path / "a.h5"),) and request.out == tmp_path / "p.csv"
    assert not request.live and not request.force and not request.progress
    assert RunRequest(model="m", events=("dv://h:1",), out="p.csv", max_seconds=1e-3).live
    assert RunRequest(model="m", events=("a.h5",), out="p.csv", render="v.mp4", render_max_frames=1).render == "v.mp4"
    with pytest.raises(dataclasses.FrozenInstanceError):
        request.force = True
    with pytest.raises(dataclasses.FrozenInstanceError):
        RunResult({}, ()).summary = ("changed",)


def test_the_output_is_checked_before_the_model_is_opened(tmp_path) -> None:
    (tmp_path / "p.csv").write_text("old")
    with pytest.raises(OutputExistsError) as info:
        run_poses(_request(tmp_path))  # the default: never replace
    assert str(info.value) == f"{tmp_path / 'p.csv'} exists; pass --force to replace it"
    with pytest.raises(DataError) as info:
        run_poses(_request(tmp_path, out=tmp_path))
    assert str(info.value) == f"--out {tmp_path} is a folder; expected a CSV file path"
    # With --force the output passes and the missing model is what stops it, the old file kept.
    with pytest.raises(DataError) as info:
        run_poses(_request(tmp_path, force=True))
    assert str(info.value) == "model missing.onnx does not exist"
    assert (tmp_path / "p.csv").read_text() == "old"


def test_two_files_are_the_many_file_form_even_into_a_folder(tmp_path) -> None:
    """Several --events write into a folder: the one-file form's 'is a folder' check is not theirs."""
    with pytest.raises(DataError) as info:
        run_poses(_request(tmp_path, events=("a.h5", "b.h5"), out=tmp_path))
    assert str(info.value) == "model missing.onnx does not exist"
