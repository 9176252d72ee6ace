"""`e3dpsm train` under torchrun with two CPU processes (gloo): the ranks end identical."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from e3dpsm.checkpoint import load_checkpoint
from e3dpsm.training.trainer import PARAM_DUMP_ENV, _param_digest
from _training_helpers import FAST_TRAIN



def test_two_ranks_end_with_identical_weights(prepared_small: Path, tmp_path: Path) -> None:
    dump = tmp_path / "dump"
    env = {**os.environ, PARAM_DUMP_ENV: str(dump), "OMP_NUM_THREADS": "1"}
    at = FAST_TRAIN.index("--threads")
    fast = [*FAST_TRAIN[:at], *FAST_TRAIN[at + 2:], "--threads", "1"]  # one thread per rank
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone",
           "-m", "e3dpsm", "train", "--data", str(prepared_small), "--split", "all",
           "--out", str(tmp_path / "run"), "--steps", "2", *fast]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-1500:] + proc.stderr[:3000]
    rank0 = json.loads((dump / "rank0.json").read_text())
    rank1 = json.loads((dump / "rank1.json").read_text())
    assert rank0["sha256"] == rank1["sha256"]
    model, payload = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert payload["step"] == 2
    assert _param_digest(model)["sha256"] == rank0["sha256"]  # rank 0 wrote what both hold
    # Both ranks trained: each step consumed batch x world windows.
    assert json.loads((tmp_path / "run" / "report.json").read_text())["config"]["world_size"] == 2
