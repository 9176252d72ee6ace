"""A clock that moves only where a test says time is spent: stand in for time.perf_counter and
charge chosen functions a fixed cost per call, so timing splits can be checked exactly."""
from __future__ import annotations

from typing import Any


class ManualClock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


def charge(monkeypatch: Any, owner: Any, name: str, clock: ManualClock, seconds: float) -> None:
    """`owner.name` (a function or a method) advances `clock` by `seconds` on each call."""
    original = getattr(owner, name)

    def charged(*args: Any, **kwargs: Any) -> Any:
        clock.advance(seconds)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, charged)
