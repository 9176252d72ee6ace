"""Compare two runs' reports (`profile`, `validate` or `pipeline`) and flag regressions, so
that CI can gate on latency, accuracy and size. Torch-free: it reads JSON only.

Each report is reduced to named figures of three kinds, lower is better for all:
- latency: p50 ms per available profile target (`latency:<target>`);
- mpjpe:   held-out MPJPE per validated variant (`mpjpe:<variant>`);
- size:    graph bytes per profile target (`size:<target>`).
A pipeline report folder contributes its validate and profile reports.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from e3dpsm.errors import DataError

UNITS = {"latency": "ms", "mpjpe": "mm", "size": "MB"}


@dataclass(frozen=True)
class Change:
    name: str
    kind: str
    base: float | None
    new: float | None
    limit_pct: float | None

    @property
    def change_pct(self) -> float | None:
        if self.base is None or self.new is None or self.base == 0:
            return None
        return 100.0 * (self.new - self.base) / self.base

    @property
    def regressed(self) -> bool:
        pct = self.change_pct
        return pct is not None and self.limit_pct is not None and pct > self.limit_pct

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "base": self.base, "new": self.new,
                "change_pct": self.change_pct, "limit_pct": self.limit_pct, "regressed": self.regressed}


def _read(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"cannot read report {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise DataError(f"{path} is not an e3dpsm report (a JSON object)")
    return data


def figures(path: str | Path) -> dict[str, tuple[str, float]]:
    """{name: (kind, value)} of one report file, or of a pipeline output folder."""
    path = Path(path)
    if path.is_dir():  # a pipeline output folder
        path = path / "report" / "pipeline.json"
    report = _read(path)
    command = report.get("command")
    if command == "profile":
        out = {}
        for target in report.get("targets", []):
            if target.get("available") and (target.get("latency_ms") or {}).get("p50") is not None:
                out[f"latency:{target['name']}"] = ("latency", float(target["latency_ms"]["p50"]))
            if target.get("available") and target.get("model_bytes"):
                out[f"size:{target['name']}"] = ("size", target["model_bytes"] / 1e6)
        return out
    if command == "validate":
        return {f"mpjpe:{row['variant']}": ("mpjpe", float(row["mpjpe_mm"]))
                for row in report.get("rows", []) if row.get("mpjpe_mm") is not None}
    if command == "pipeline":
        root = path.parent.parent
        out = {}
        for stage in ("validate/report.json", "profile/report.json"):
            if (root / stage).is_file():
                out.update(figures(root / stage))
        return out
    raise DataError(f"{path} is a {command!r} report; compare reads the reports of profile, validate or pipeline")


def compare(base: str | Path, new: str | Path, limits_pct: Mapping[str, float | None]) -> list[Change]:
    """Every figure of either report, with its change; `limits_pct` per kind (None: no limit)."""
    a, b = figures(base), figures(new)
    if not set(a) & set(b):
        raise DataError(f"{base} and {new} have no figure in common (reports of different kinds?)")
    changes = []
    for name in sorted(set(a) | set(b)):
        kind = (a.get(name) or b.get(name))[0]
        value_a, value_b = (a[name][1] if name in a else None), (b[name][1] if name in b else None)
        for value in (value_a, value_b):
            if value is not None and not math.isfinite(value):
                raise DataError(f"{name} is not a finite number in one of the reports")
        changes.append(Change(name, kind, value_a, value_b, limits_pct.get(kind)))
    return changes


def table(changes: list[Change]) -> str:
    lines = ["| figure | base | new | change | limit | verdict |", "|---|---:|---:|---:|---:|---|"]
    for c in changes:
        unit = UNITS[c.kind]
        base = f"{c.base:.3f} {unit}" if c.base is not None else "-"
        new = f"{c.new:.3f} {unit}" if c.new is not None else "-"
        pct = f"{c.change_pct:+.2f}%" if c.change_pct is not None else "-"
        limit = f"+{c.limit_pct:g}%" if c.limit_pct is not None else "-"
        verdict = "REGRESSION" if c.regressed else ("only in one" if c.change_pct is None else "ok")
        lines.append(f"| {c.name} | {base} | {new} | {pct} | {limit} | {verdict} |")
    return "\n".join(lines)
