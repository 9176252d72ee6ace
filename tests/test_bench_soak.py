"""benchmarks/bench_soak.py's judgement, on made-up samples (fast): the steady state after the
warm-up (RSS growth and slope, descriptors, threads), the tiling of a recording to a longer
stream, the page verdicts; and the whole bench on a tiny duration (slow: browsers, minutes)."""
from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from _serve_helpers import write_recording

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_soak.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_soak", _PATH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _samples(seconds: float, rss_at, fds_at=lambda t: 20, threads_at=lambda t: 9, period: float = 5.0):
    return [{"t_s": t, "rss_mb": rss_at(t), "fds": fds_at(t), "threads": threads_at(t)}
            for t in np.arange(0.0, seconds + period / 2, period)]


def test_steady_state_after_the_warmup(bench):
    rng = np.random.default_rng(0)
    # Loading until 60 s, then flat with +-0.5 MB of noise: flat, whatever the climb before.
    flat = bench.steady_state(_samples(1800.0, lambda t: 100.0 + min(t, 60.0) + rng.uniform(-0.5, 0.5),
                                       fds_at=lambda t: 30 if t < 200 else 25))
    assert flat["warmup_s"] == 180.0 and flat["rss_flat"] and abs(flat["rss_growth_mb"]) <= 1.0
    assert abs(flat["rss_slope_mb_per_hour"]) < 1.0 and (flat["fds_after_warmup"], flat["fds_end"]) == (30, 25)
    # A leak of 10 MB an hour: 9 MB over the last 54 minutes, more than the 5 MB allowed.
    leak = bench.steady_state(_samples(3600.0, lambda t: 100.0 + t / 360.0))
    assert not leak["rss_flat"] and leak["rss_growth_mb"] == pytest.approx(9.0, abs=0.02)
    assert leak["rss_slope_mb_per_hour"] == pytest.approx(10.0, abs=0.01)
    short = bench.steady_state(_samples(60.0, lambda t: 50.0))  # a smoke run: at least 30 s of warm-up
    assert short["warmup_s"] == 30.0 and short["rss_growth_mb"] == 0.0
    with pytest.raises(RuntimeError):
        bench.steady_state(_samples(0.0, lambda t: 1.0))


def test_tiling_repeats_the_thinned_recording_on_one_window_grid(bench, tmp_path):
    from e3dpsm.data.readers import read_events

    source = write_recording(tmp_path / "seq", 30)  # 0.6 s
    original = read_events(source)
    got = bench.tile_recording(source, hours=2.0 / 3600, keep_every=3, out=tmp_path / "hour" / "events.npz")
    tiled = read_events(tmp_path / "hour" / "events.npz")
    per_copy = len(original.t_us[::3])
    span_us = got["stream_s"] * 1e6 / got["copies"]
    assert got["copies"] == int(np.ceil(2e6 / span_us)) and span_us % 20_000 == 0
    assert len(tiled) == got["events"] == got["copies"] * per_copy and got["stream_s"] >= 2.0
    assert np.all(np.diff(tiled.t_us) >= 0) and tiled.sensor_hw == original.sensor_hw
    t0 = original.t_us[::3] - original.t_us[0]
    for k in (0, got["copies"] - 1):  # each copy is the thinned recording, shifted by whole spans
        part = slice(k * per_copy, (k + 1) * per_copy)
        np.testing.assert_array_equal(tiled.t_us[part], t0 + int(k * span_us))
        np.testing.assert_array_equal(tiled.x[part], original.x[::3])


def _serve_report(poses: int) -> dict:
    summary = {"count": poses, "p50": 5.0, "p90": 6.0, "p99": 8.0, "max": 9.0}
    return {"poses": poses, "passes": 2, "late_ticks": 0, "step_ms": summary, "clients_seen": 5,
            "drops": {"0": {"poses": 10, "frames": 3}}, "refused": {"rate_limited": 0},
            "rss_mb": {"start": 90.0, "end": 95.0, "max": 96.0}}


def test_a_page_that_lost_a_pose_fails_the_verdict(bench):
    page = {"latencies": [7.5, 10.0, 12.5], "received": 100, "drawn": 100, "gaps": 0, "outOfOrder": 0}
    samples = _samples(600.0, lambda t: 100.0)
    good = bench.serve_result(_serve_report(100), [page, page], samples, None, (1.0, 1.0, 1.0), 10.0)
    assert good["pages"][0]["p50_over_step"] == 2.0 and good["pages"][0]["lost"] == 0
    lost = bench.serve_result(_serve_report(101), [page, page], samples, None, (1.0, 1.0, 1.0), 10.0)
    run = {"poses": 50, "windows": 50, "out_of_order": 0, "gaps": 0, "process": bench.steady_state(samples)}
    assert all(bench.verdicts(good, run).values())
    failed = [name for name, holds in bench.verdicts(lost, run).items() if not holds]
    assert failed == ["serve: every pose reached each page, in order"]


@pytest.mark.slow
def test_the_whole_soak_on_a_tiny_duration(tmp_path, tmp_path_factory):
    """Everything the 30-minute run does, for 40 s of serve and 20 s of stream through run."""
    from _runtime_helpers import exported_tiny

    if not (shutil.which("chromium") and shutil.which("chromedriver")):
        pytest.skip("chromium and chromedriver are needed (apt-get install chromium chromium-driver)")
    spec = importlib.util.spec_from_file_location("bench_soak_run", _PATH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    graph = exported_tiny(str(tmp_path_factory.getbasetemp()))[1]
    recording = write_recording(tmp_path / "seq", 100)
    out = tmp_path / "soak"
    assert bench.main(["--model", str(graph), "--events", str(recording), "--serve-minutes", str(40 / 60),
                       "--run-hours", str(20 / 3600), "--keep-every", "2", "--threads", "1", "--out", str(out)]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert result["verdicts"]["serve: every pose reached each page, in order"]
    assert result["verdicts"]["run: every window's pose, in order"] and result["run"]["windows"] >= 999
    assert result["serve"]["reconnects"]["hellos"] >= 20 and len(result["serve"]["pages"]) == 3
    assert "| serve page |" in out.with_suffix(".md").read_text()
