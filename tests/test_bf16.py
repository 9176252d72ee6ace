"""bf16 as a precision a user can choose and check: OpenVINO's INFERENCE_PRECISION_HINT=bf16
on CPUs with bf16 units, the `openvino-cpu-bf16` profile targets, `golden check --runtime
openvino-bf16` held to the bf16 profile; refused or reported unavailable where the CPU has
no bf16 units (OpenVINO would run f32 under a bf16 label)."""
from __future__ import annotations

import json

import pytest

from _quantize_helpers import TRAINED_TINY

from e3dpsm.cli import main
from e3dpsm.profiles.targets import load_targets, runtime_availability
from e3dpsm.utils import isa as isa_module
from e3dpsm.utils.isa import CpuIsa, detect_isa

pytest.importorskip("openvino", reason="OpenVINO is not installed (pip install -e '.[openvino]')")

AVX2_ONLY = CpuIsa(("avx2", "fma"))


@pytest.fixture(scope="module")
def golden_dir(tmp_path_factory, quant_data):  # noqa: F811
    """40 steps of the trained tiny, recorded from its checkpoint."""
    out = tmp_path_factory.mktemp("golden_bf16") / "tiny"
    assert main(["golden", "record", "--checkpoint", str(TRAINED_TINY), "--data", str(quant_data),
                 "--steps", "40", "--out", str(out)]) == 0
    return out


@pytest.fixture
def no_bf16_units(monkeypatch):
    monkeypatch.setattr(isa_module, "detect_isa", lambda cpuinfo="/proc/cpuinfo": AVX2_ONLY)


@pytest.mark.parametrize("name", ["openvino-cpu-bf16", "openvino-cpu-stateful-bf16"])
def test_bf16_targets_are_unavailable_without_bf16_units(no_bf16_units, name) -> None:
    verdict = runtime_availability(load_targets()[name])
    assert not verdict.available and "no bf16 units" in verdict.reason


def test_f32_targets_do_not_need_bf16_units(no_bf16_units) -> None:
    assert runtime_availability(load_targets()["openvino-cpu-fp32"]).available


def test_golden_check_in_bf16_is_refused_without_bf16_units(no_bf16_units, trained_graph, golden_dir, tmp_path,
                                                             capsys) -> None:
    out = tmp_path / "chk"
    code = main(["golden", "check", "--model", str(trained_graph), "--golden", str(golden_dir), "--out", str(out),
                 "--runtime", "openvino-bf16"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "bf16 needs a CPU with bf16 units" in err and "\n" not in err and not out.exists()


@pytest.mark.skipif(not detect_isa().bf16, reason="this CPU has no bf16 units (avx512_bf16, amx_bf16)")
def test_bf16_runs_in_bf16_and_is_held_to_its_budget(trained_graph, golden_dir, tmp_path) -> None:
    """In bf16 the poses move beyond the fp32 parity tolerance (so the hint reached the CPU
    plugin), and stay within the bf16 budget."""
    args = ["golden", "check", "--model", str(trained_graph), "--golden", str(golden_dir), "--runtime", "openvino-bf16"]
    assert main([*args, "--out", str(tmp_path / "bf16")]) == 0
    report = json.loads((tmp_path / "bf16" / "check.json").read_text())
    assert report["profile"]["name"] == "bf16" and report["machine"]["isa"]["bf16"]
    pose = next(t for t in report["tensors"] if t["name"] == "pose")
    assert pose["max"] > 0.01  # not f32: the fp32 profile's 0.01 mm would fail
    assert main([*args, "--profile", "fp32", "--out", str(tmp_path / "as_fp32")]) == 1
