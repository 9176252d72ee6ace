"""The bodies of `e3dpsm profile` and `e3dpsm model-info` once their options are parsed:
graphs exported or taken, inputs made, targets measured, reports built and written
(e3dpsm/cli only parses options and calls these)."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from e3dpsm.profiles.graphs import GRAPH_NAME, add_static_graph, export_fp32, graph_metadata
from e3dpsm.profiles.inputs import Frames, moving_edge_frames, prepared_frames
from e3dpsm.profiles.profiler import ProfileSettings, profile_targets
from e3dpsm.profiles.targets import Target

log = logging.getLogger(__name__)
SYNTHETIC_FRAMES_MAX = 400  # frames are replayed beyond this; states keep running


@dataclass(frozen=True)
class ProfileRequest:
    """One `e3dpsm profile` run. `graphs`: the graphs given (profiles.graphs.given_graphs);
    `source`: what the model came from, for the report; `config`: the command's options, as
    the report header records them."""

    targets: tuple[Target, ...]
    graphs: Mapping[str, Path | None]
    out: Path
    settings: ProfileSettings
    source: str
    config: Mapping[str, Any]
    data: str | None = None
    checkpoint: str | None = None
    force: bool = False
    progress: bool = False


def _frames(request: ProfileRequest, fp32_graph: Path) -> Frames:
    meta = graph_metadata(fp32_graph)
    height, width = meta.frame_hw
    needed = request.settings.steps + request.settings.warmup
    if request.data:
        return prepared_frames(request.data, needed, height, width)
    return moving_edge_frames(min(needed, SYNTHETIC_FRAMES_MAX), height, width, meta.train_window_ms)


def run_profile(request: ProfileRequest, model: Any = None) -> dict[str, Any]:
    """Measure, then write OUT/report.json, report.md, latency.png, macs_per_module.png (and
    the graphs exported here) into a fresh folder; returns the report."""
    from e3dpsm.profiles.report import plot_latency, plot_macs, profile_markdown
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, write_json_atomic, write_text_atomic

    with atomic_dir(request.out, force=request.force) as tmp:
        graphs = dict(request.graphs)
        if model is not None:
            graphs["fp32"] = export_fp32(model, tmp)
        frames = _frames(request, graphs["fp32"])
        if model is not None:
            graphs = add_static_graph(model, tmp, request.targets, graphs, frames.lnes, frames.window_ms)
        exported = sorted(path.name for path in graphs.values() if path is not None and path.parent == tmp)
        log.info("profiling %d target(s) on %s", len(request.targets), frames.source)
        body, times = profile_targets(list(request.targets), graphs, model, frames, request.settings,
                                      checkpoint=request.checkpoint, progress=request.progress)
        report = report_header("profile", dict(request.config))
        report.update(model=_model_section(request, graphs, exported, body), inputs=_inputs_section(request, frames),
                      **body)
        write_json_atomic(tmp / "report.json", report)
        write_text_atomic(tmp / "report.md", profile_markdown(report))
        if times:
            plot_latency({name: t * 1e3 for name, t in times.items()}, tmp / "latency.png")
        plot_macs(report["counting"]["pytorch"] or report["counting"]["onnx"], tmp / "macs_per_module.png")
    return report


def _model_section(request: ProfileRequest, graphs: Mapping[str, Path | None], exported: list[str],
                   body: Mapping[str, Any]) -> dict[str, Any]:
    meta = graph_metadata(graphs["fp32"])
    return {"variant": meta.config.get("variant", "?"), "source": request.source,
            "params": body["targets"][0]["params"] if body["targets"] else None,
            "graph": GRAPH_NAME if GRAPH_NAME in exported else str(graphs["fp32"]), "graphs_exported": exported}


def _inputs_section(request: ProfileRequest, frames: Frames) -> dict[str, Any]:
    settings = request.settings
    return {"source": frames.source, "window_ms": frames.window_ms, "frames": int(len(frames.lnes)),
            "steps": settings.steps, "warmup": settings.warmup, "chunk": settings.chunk,
            "threads": request.targets[0].threads, "outside_seconds": settings.outside_seconds,
            "outside_turns": settings.outside_turns}


def summary_lines(report: Mapping[str, Any]) -> list[str]:
    """What `e3dpsm profile` prints: the verdict, each target's medians, the ratios."""
    from e3dpsm.profiles.verdict import verdict_line

    lines = [verdict_line(report.get("verdict")).replace("**", "").replace("`", "")]
    for entry in report["targets"]:
        if not entry["available"]:
            lines.append(f"{entry['name']:>34}: unavailable ({entry['reason']})")
            continue
        lat = entry["latency_ms"]
        line = (f"{entry['name']:>34}: p50 {lat['p50']:.2f} ms, p90 {lat['p90']:.2f}, p99 {lat['p99']:.2f} "
                f"-> {entry['hz']:.1f} Hz")
        if entry.get("overhead_ms"):
            line += f"; runtime {entry['runtime_ms']['p50']:.2f} + Python {entry['overhead_ms']['p50']:.3f}"
        outside = entry.get("outside") or {}
        if outside.get("p50_ms") is not None:
            line += (f"; {outside['tool']} {outside['p50_ms']:.2f} ms against runtime {entry['beside_ms']:.2f} "
                     "in turns with it")
            # No ratio where the tool executed another graph than the runner, or no turn was
            # steady (profiles.agreement): the note, or the reason.
            line += f" ({entry['agreement']:.2f}x)" if entry.get("agreement") is not None else \
                f" ({outside.get('note') or 'no ratio: the host changed speed across every turn'})"
        lines.append(line)
    lines += [f"  {name}: {ratio:.2f}x" for name, ratio in report["ratios"].items()]
    return lines


def model_info_report(model: Any, config: Mapping[str, Any]) -> dict[str, Any]:
    """`e3dpsm model-info`'s report: the PyTorch counts per module with the header."""
    from e3dpsm.profiles.flops_torch import count_torch
    from e3dpsm.utils.env import report_header

    counts = count_torch(model).to_dict()
    report = report_header("model-info", dict(config))
    report.update(model={"variant": model.config.variant, "params": counts["params"],
                         "model_config": model.config.to_dict()},
                  counting={"pytorch": counts})
    return report
