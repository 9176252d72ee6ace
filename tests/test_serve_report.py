"""serve.report.json's body (serve/report.py) from a session's counters, a fake client hub and
the refusals, compared whole: each figure from where docs/serve.md says it comes."""
from __future__ import annotations

from pathlib import Path

from e3dpsm.serve.estimator import EngineStats
from e3dpsm.serve.report import REPORT_NAME, build_report, report_path
from e3dpsm.serve.security import Refusals
from e3dpsm.utils.stats import LogHistogram


def _histogram(*values: float) -> LogHistogram:
    histogram = LogHistogram()
    histogram.extend(values)
    return histogram


class FakeHub:
    """What the report reads of serve.clients.ClientHub: the listed clients, the latencies by
    kind, how many were seen and retired, and the retired ones still listed."""

    def __init__(self) -> None:
        self.seen, self.retired = 7, 5
        self.closed_summaries = [{"client_id": 0}, {"client_id": 3}]  # the latest retired listed
        self.clients = [{"client_id": 0, "poses_dropped": 2, "frames_dropped": 0},
                        {"client_id": 3, "poses_dropped": 0, "frames_dropped": 4},
                        {"client_id": 6, "poses_dropped": 1, "frames_dropped": 9}]
        self.latencies = {"sent": _histogram(4.0, 6.0), "page": _histogram(20.0)}

    def summaries(self) -> list[dict]:
        return self.clients

    def latency_ms(self, kind: str) -> LogHistogram:
        return self.latencies[kind]


def _stats(compare_steps: tuple[float, ...] = ()) -> EngineStats:
    stats = EngineStats(poses=120, passes=2, events=4567, late_ticks=3, stop_reason="end of replay")
    stats.step_ms.extend([9.0, 10.0, 11.0])
    stats.compare_step_ms.extend(compare_steps)
    stats.ready_latency_ms.extend([12.0, 13.0])
    return stats


def test_the_report_holds_each_figure_from_its_source() -> None:
    hub, refusals = FakeHub(), Refusals(host=1, origin=2, token_missing=3, token_wrong=4, rate_limited=5)
    config = {"model": "m.onnx", "port": 8765}
    graphs = {"main": {"path": "m.onnx"}}
    report = build_report(config, graphs, _stats(), hub, started_wall_s=100.0, stopped_wall_s=130.1234567,
                          rss_mb={"after_warmup": 80.0, "end": 81.5}, refusals=refusals)
    assert report["command"] == "serve" and report["config"] == config
    assert {"created", "versions", "machine"} <= set(report)
    body = {key: value for key, value in report.items() if key not in ("command", "config", "created", "versions",
                                                                       "machine")}
    assert body == {
        "graphs": graphs,
        "stop_reason": "end of replay",
        "seconds": 30.123,
        "poses": 120,
        "passes": 2,
        "events": 4567,
        "late_ticks": 3,
        "step_ms": _histogram(9.0, 10.0, 11.0).summary(),
        "compare_step_ms": None,  # no --compare graph stepped
        "latency_ms": {
            "definition": "from the window end's arrival (scheduled replay time, or a live chunk's arrival) "
                          "on the server's wall clock",
            "ready": _histogram(12.0, 13.0).summary(),
            "sent": _histogram(4.0, 6.0).summary(),
            "page": _histogram(20.0).summary(),
        },
        "clients_seen": 7,
        "clients_not_listed": 3,  # 5 retired, the latest 2 of them listed
        "drops": {"0": {"poses": 2, "frames": 0}, "3": {"poses": 0, "frames": 4}, "6": {"poses": 1, "frames": 9}},
        "clients": hub.clients,
        "refused": {"host": 1, "origin": 2, "token_missing": 3, "token_wrong": 4, "rate_limited": 5},
        "rss_mb": {"after_warmup": 80.0, "end": 81.5},
    }
    # the histogram's own figures: the count exact, the median within its bins' 0.5% of numpy's
    assert body["step_ms"]["count"] == 3 and abs(body["step_ms"]["p50"] - 10.0) <= 0.05


def test_the_compared_graphs_steps_are_reported_when_it_stepped() -> None:
    report = build_report({}, {}, _stats(compare_steps=(30.0,)), FakeHub(), started_wall_s=0.0, stopped_wall_s=1.0,
                          rss_mb={}, refusals=Refusals())
    assert report["compare_step_ms"] == _histogram(30.0).summary() and report["compare_step_ms"]["count"] == 1


def test_the_report_lies_in_the_output_folder_by_its_documented_name() -> None:
    assert REPORT_NAME == "serve.report.json"
    assert report_path("out/run") == Path("out/run/serve.report.json") == report_path(Path("out/run"))
