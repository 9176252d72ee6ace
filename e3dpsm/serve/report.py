"""serve.report.json: what a serving session did, written atomically when it stops."""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.serve.clients import ClientHub
    from e3dpsm.serve.estimator import EngineStats
    from e3dpsm.serve.security import Refusals

REPORT_NAME = "serve.report.json"


def build_report(config: dict[str, Any], graphs: dict[str, Any], stats: EngineStats, hub: ClientHub,
                 *, started_wall_s: float, stopped_wall_s: float, rss_mb: dict[str, float],
                 refusals: Refusals) -> dict[str, Any]:
    from e3dpsm.utils.env import report_header

    clients = hub.summaries()
    return {
        **report_header("serve", config),
        "graphs": graphs,
        "stop_reason": stats.stop_reason,
        "seconds": round(stopped_wall_s - started_wall_s, 3),
        "poses": stats.poses,
        "passes": stats.passes,
        "events": stats.events,
        "late_ticks": stats.late_ticks,
        "step_ms": stats.step_ms.summary(),
        "compare_step_ms": stats.compare_step_ms.summary() if stats.compare_step_ms.count else None,
        "latency_ms": {
            "definition": "from the window end's arrival (scheduled replay time, or a live chunk's arrival) "
                          "on the server's wall clock",
            "ready": stats.ready_latency_ms.summary(),  # pose message built (after the step)
            "sent": hub.latency_ms("sent").summary(),  # written to a socket
            "page": hub.latency_ms("page").summary(),  # drawn, as the pages report it
        },
        "clients_seen": hub.seen,
        "clients_not_listed": hub.retired - len(hub.closed_summaries),  # closed before the latest listed ones
        "drops": {str(c["client_id"]): {"poses": c["poses_dropped"], "frames": c["frames_dropped"]} for c in clients},
        "clients": clients,
        "refused": asdict(refusals),  # requests and clients refused, by rule
        "rss_mb": rss_mb,
    }


def report_path(out: str | Path) -> Path:
    return Path(out) / REPORT_NAME
