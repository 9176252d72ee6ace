"""Test helpers for the atomic writes of e3dpsm/utils/io.py."""
from __future__ import annotations

import contextlib
from types import ModuleType


def record_temporaries(monkeypatch, module: ModuleType) -> list[str]:
    """The names of the temporaries `module`'s `atomic_path` yields, in the order it opens them."""
    real = module.atomic_path
    names: list[str] = []

    @contextlib.contextmanager
    def recording(path, **kwargs):
        with real(path, **kwargs) as tmp:
            names.append(tmp.name)
            yield tmp

    monkeypatch.setattr(module, "atomic_path", recording)
    return names
