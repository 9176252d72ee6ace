"""Where the machine's CPU time went during a measurement, from Linux's /proc/stat.

On a virtual machine the hypervisor can give a vCPU's time to another guest ("steal"); a
timing taken while steal is high runs slower for reasons outside the process, and a report
that records the steal share beside its figures lets a reader tell such a run from a
regression. Zero steal does not make a host quiet: on the shared 2-core AVX-512 VNNI host
(2026-12-04) the guest saw 0% steal while the same OpenVINO graph's median moved between 10
and 17 ms within seconds (neighbours on the same physical cores or memory are invisible to
it); the busy and idle shares say whether this machine itself was loaded.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

PROC_STAT = Path("/proc/stat")
# The aggregate "cpu" line's fields, in order (proc(5)); guest times are already counted in user.
_FIELDS = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")


@dataclass(frozen=True)
class CpuTimes:
    """Cumulative clock ticks of all CPUs, by kind."""

    user: int
    nice: int
    system: int
    idle: int
    iowait: int
    irq: int
    softirq: int
    steal: int

    @classmethod
    def parse(cls, text: str) -> "CpuTimes":
        """From /proc/stat's text (its first line, `cpu  user nice system idle ...`)."""
        first = text.splitlines()[0].split() if text.strip() else []
        if not first or first[0] != "cpu" or len(first) < 1 + len(_FIELDS):
            raise ValueError(f"not a /proc/stat aggregate cpu line: {' '.join(first[:3])!r}")
        return cls(*(int(value) for value in first[1:1 + len(_FIELDS)]))


def read_cpu_times(path: Path = PROC_STAT) -> CpuTimes | None:
    """The machine's CPU times now; None where /proc/stat is absent (macOS, Windows) or unreadable."""
    try:
        return CpuTimes.parse(path.read_text(encoding="ascii"))
    except (OSError, ValueError):
        return None


def cpu_shares(before: CpuTimes | None, after: CpuTimes | None) -> dict[str, float] | None:
    """Each kind's share of the CPU time between two readings (busy = user + nice + system +
    irq + softirq); None without both readings or with no time between them."""
    if before is None or after is None:
        return None
    delta = {name: getattr(after, name) - getattr(before, name) for name in _FIELDS}
    total = sum(delta.values())
    if total <= 0:
        return None
    busy = delta["user"] + delta["nice"] + delta["system"] + delta["irq"] + delta["softirq"]
    return {"busy": busy / total, "idle": (delta["idle"] + delta["iowait"]) / total, "steal": delta["steal"] / total}


class CpuShareMeter:
    """`with CpuShareMeter() as meter: ...` -> meter.shares (cpu_shares over the block)."""

    def __init__(self, path: Path = PROC_STAT) -> None:
        self.path = path
        self.shares: dict[str, float] | None = None
        self._before: CpuTimes | None = None

    def __enter__(self) -> "CpuShareMeter":
        self._before = read_cpu_times(self.path)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.shares = cpu_shares(self._before, read_cpu_times(self.path))
