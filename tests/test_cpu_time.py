"""CPU time shares from /proc/stat readings (committed text, hand-computed shares)."""
from __future__ import annotations

from pathlib import Path

import pytest

from e3dpsm.profiles.report import cpu_time_sentence
from e3dpsm.utils.cpu_time import CpuShareMeter, CpuTimes, cpu_shares, read_cpu_times

BEFORE = "cpu  100 0 50 800 0 0 0 50 0 0\ncpu0 50 0 25 400 0 0 0 25 0 0\nintr 1\n"
# 200 ticks later: user +80, nice +10, system +10, idle +40, iowait +10, irq +5, softirq +5, steal +40.
AFTER = "cpu  180 10 60 840 10 5 5 90 7 0\ncpu0 90 5 30 420 5 2 3 45 3 0\n"


def test_shares_between_two_readings_by_hand() -> None:
    shares = cpu_shares(CpuTimes.parse(BEFORE), CpuTimes.parse(AFTER))
    assert shares == pytest.approx({"busy": 110 / 200, "idle": 50 / 200, "steal": 40 / 200})
    assert cpu_time_sentence({"timed_steps": shares, "outside_timers": None}) == (
        " The machine's CPU time during the timed steps: busy 55%, idle 25%, stolen by the hypervisor 20%.")
    assert cpu_time_sentence(None) == "" and cpu_time_sentence({"timed_steps": None}) == ""


def test_missing_or_odd_readings_give_no_shares(tmp_path: Path) -> None:
    assert cpu_shares(None, CpuTimes.parse(AFTER)) is None
    same = CpuTimes.parse(BEFORE)
    assert cpu_shares(same, same) is None  # no time between the readings
    with pytest.raises(ValueError, match="not a /proc/stat"):
        CpuTimes.parse("intr 1 2 3\n")
    with pytest.raises(ValueError, match="not a /proc/stat"):
        CpuTimes.parse("cpu 1 2 3\n")  # too few fields
    assert read_cpu_times(tmp_path / "absent") is None
    odd = tmp_path / "stat"
    odd.write_text("nonsense\n")
    assert read_cpu_times(odd) is None


def test_meter_reads_the_file_at_entry_and_exit(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    stat.write_text(BEFORE)
    with CpuShareMeter(stat) as meter:
        stat.write_text(AFTER)
    assert meter.shares == pytest.approx({"busy": 0.55, "idle": 0.25, "steal": 0.2})


def test_the_aggregate_line_is_read_with_exactly_the_eight_fields_it_needs() -> None:
    """Kernels before 2.6.33 print no guest fields: 'cpu' and eight numbers are enough."""
    assert CpuTimes.parse("cpu 1 2 3 4 5 6 7 8\n") == CpuTimes(1, 2, 3, 4, 5, 6, 7, 8)
    with pytest.raises(ValueError, match=r"^not a /proc/stat aggregate cpu line: 'cpu 1 2'$"):
        CpuTimes.parse("cpu 1 2 3 4 5 6 7\n")
    with pytest.raises(ValueError, match=r"^not a /proc/stat aggregate cpu line: 'intr 1 2'$"):
        CpuTimes.parse("intr 1 2 3 4 5 6 7 8 9\n")  # long enough, but not the cpu line
    with pytest.raises(ValueError, match="not a /proc/stat"):
        CpuTimes.parse("")
    with pytest.raises(AttributeError):
        CpuTimes.parse(BEFORE).steal = 0  # frozen: a reading is a fact


def test_one_tick_between_readings_is_enough() -> None:
    one_more = BEFORE.replace("cpu  100 ", "cpu  101 ", 1)
    assert cpu_shares(CpuTimes.parse(BEFORE), CpuTimes.parse(one_more)) == {"busy": 1.0, "idle": 0.0, "steal": 0.0}


def test_the_meter_has_no_shares_until_the_block_ends(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    stat.write_text(BEFORE)
    meter = CpuShareMeter(stat)
    with meter:
        assert meter.shares is None
        stat.write_text(AFTER)
    assert meter.shares is not None


@pytest.mark.skipif(not Path("/proc/stat").is_file(), reason="Linux only: no /proc/stat here")
def test_this_machine_is_read_by_default() -> None:
    now = read_cpu_times()
    assert now is not None and now.user + now.system + now.idle > 0
    with CpuShareMeter() as meter:
        sum(i * i for i in range(200_000))  # a few ms of work, so the readings differ
    assert meter.shares is None or sum(meter.shares.values()) == pytest.approx(1.0)
