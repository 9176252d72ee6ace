"""serve.report.json: what a serving session did, written atomically when it stops."""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from e3dpsm.utils.stats import percentiles

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.serve.clients import ClientHub
    from e3dpsm.serve.estimator import EngineStats
    from e3dpsm.serve.security import Refusals

REPORT_NAME = "serve.report.json"


def build_report(config: dict[str, Any], graphs: dict[str, Any], stats: EngineStats, hub: ClientHub,
                 *, started_wall_s: float, stopped_wall_s: float, rss_mb: dict[str, float],
                 refusals: Refusals) -> dict[str, Any]:
    from e3dpsm.utils.env import report_header

    clients = [c.summary() for c in hub.clients]
    page_samples = [s for c in hub.clients for s in c.page_latency_ms]
    return {
        **report_header("serve", config),
        "graphs": graphs,
        "stop_reason": stats.stop_reason,
        "seconds": round(stopped_wall_s - started_wall_s, 3),
        "poses": stats.poses,
        "passes": stats.passes,
        "events": stats.events,
        "late_ticks": stats.late_ticks,
        "step_ms": percentiles(stats.step_ms),
        "compare_step_ms": percentiles(stats.compare_step_ms) if stats.compare_step_ms else None,
        "latency_ms": {
            "definition": "from the window end's arrival (scheduled replay time, or a live chunk's arrival) "
                          "on the server's wall clock",
            "ready": percentiles(stats.ready_latency_ms),  # pose message built (after the step)
            "sent": percentiles([s for c in hub.clients for s in c.sent_latency_ms]),  # written to a socket
            "page": percentiles(page_samples),  # drawn, as the pages report it
        },
        "clients_seen": len(clients),
        "drops": {str(c["client_id"]): {"poses": c["poses_dropped"], "frames": c["frames_dropped"]} for c in clients},
        "clients": clients,
        "refused": asdict(refusals),  # requests and clients refused, by rule
        "rss_mb": rss_mb,
    }


def report_path(out: str | Path) -> Path:
    return Path(out) / REPORT_NAME
