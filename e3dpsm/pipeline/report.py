"""OUT/report/index.md (and index.html): the key table on top, then every stage's report."""
from __future__ import annotations

import html
import json
import shlex
from pathlib import Path
from typing import Any

from e3dpsm.pipeline.stages import EDGE_ARTIFACTS, EDGE_RECORDS, GRAPH, STAGES
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic

# Which profile target measures which validated variant.
_TARGET_OF = {("pytorch", "fp32"): "torch-eager-cpu", ("onnx", "fp32"): "ort-cpu-fp32",
              ("onnx", "fp16"): "ort-cpu-fp16", ("onnx", "int8"): "ort-cpu-int8"}


def _load(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def key_table(out: Path) -> list[str]:
    validate = _load(out / "validate/report.json") or {}
    profile = _load(out / "profile/report.json") or {}
    targets = {t["name"]: t for t in profile.get("targets", [])}
    rows = validate.get("rows") or validate.get("result", {}).get("rows", [])
    lines = ["| variant | MPJPE (mm) | PA-MPJPE (mm) | e_smooth (mm) | ΔMPJPE vs fp32 ONNX | step p50 (ms) | Hz | size (MB) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        target = targets.get(_TARGET_OF.get((row.get("kind"), row.get("precision")), ""), {})
        latency = (target.get("latency_ms") or {}).get("p50") if target.get("available") else None
        path = Path(row.get("path", ""))
        size = path.stat().st_size / 1e6 if path.suffix == ".onnx" and path.is_file() else None
        lines.append(
            f"| {row['variant']} | {_fmt(row.get('mpjpe_mm'))} | {_fmt(row.get('pa_mpjpe_mm'))} | "
            f"{_fmt(row.get('e_smooth_mm'))} | {_fmt(row.get('delta_mpjpe_pct'))} % | {_fmt(latency)} | "
            f"{_fmt(target.get('hz') if target.get('available') else None, 1)} | {_fmt(size)} |"
        )
    if not rows:
        lines.append("| (validate has not run) | | | | | | | |")
    return lines


def int8_section(int8_report: dict[str, Any]) -> list[str]:
    """The INT8 graph's budget on the held-out split (quantize's report.json): its verdict line
    is the report's first line, its table here."""
    check = int8_report.get("check") or {}
    rows = []
    for runtime, by_runtime in (check.get("by_runtime") or {}).items():
        for name, m in by_runtime["metrics"].items():
            rows.append(f"| {runtime} | {name} | {m['change_pct']:+.3f} | {m['upper_pct']:+.3f} | +{m['limit_pct']:g} | "
                        f"{'yes' if m['within'] else '**no**'} |")
    if not rows:
        return []
    return ["## INT8 against its budget", "",
            f"On {check['frames']} held-out frames ({check['data']}) neither calibration nor search saw; change over "
            "fp32 in %, the budget holding at the upper end of its interval "
            "([quantize/int8/report.md](../quantize/int8/report.md)).", "",
            "| runtime | metric | change % | upper bound % | limit % | within |", "|---|---|---:|---:|---:|---|",
            *rows, ""]


def edge_section(out: Path) -> list[str]:
    """The optional edge stages: each artifact's conversion record (convert.json) and the
    golden check of both; nothing when they did not run."""
    rows = []
    for fmt, rel in EDGE_ARTIFACTS.items():
        record = _load(out / EDGE_RECORDS[fmt])
        if not record:
            continue
        if fmt == "executorch":
            backend = f"XNNPACK runs {record['delegation']['delegated_share']:.1%} of the MACs"
        else:
            backend = f"{record['ops']['xnnpack_partitions']} XNNPACK partitions"
        rows.append(f"| [{rel}](../{rel}) | {record['bytes'] / 1e6:.2f} | {record['seconds']['total']:.0f} | "
                    f"{(record.get('options') or {}).get('attention_form', '-')} | {backend} |")
    if not rows:
        return []
    lines = ["## Edge artifacts", "",
             "The checkpoint converted for the edge runtimes (`e3dpsm convert`, fp32; docs/edge.md in the "
             "repository), each checked against the golden rollout with its own runtime carrying the states, "
             "and timed in the profile beside the ONNX graphs.", "",
             "| artifact | size (MB) | conversion (s) | attention form | backend |", "|---|---:|---:|---|---|",
             *rows, ""]
    summary_md = out / "edge/checks/summary.md"
    if summary_md.is_file():
        lines += [summary_md.read_text().rstrip(), ""]
    return lines


def serve_command(out: Path, threads: int | None = None) -> str | None:
    """The `e3dpsm serve` command that shows the held-out sequence live through the pipeline's
    own step graph (absolute paths, ready to paste); None until both exist."""
    graph = (out / GRAPH).resolve()
    split = out / "data" / "test.txt"
    names = split.read_text().split() if split.is_file() else []
    events = (out / "data" / names[0] / "events.h5").resolve() if names else None
    if not graph.is_file() or events is None or not events.is_file():
        return None
    argv = ["e3dpsm", "serve", "--model", str(graph), "--source", str(events)]
    if threads:
        argv += ["--threads", str(threads)]
    return shlex.join(argv)


def write_index(out: Path, config: dict[str, Any], stages: list[dict[str, Any]]) -> Path:
    out = Path(out)
    report_dir = out / "report"
    parity = _load(out / "parity/report.json") or {}
    export = _load(out / "export/export.json") or {}
    variant = (export.get("model") or {}).get("variant", config.get("variant"))
    trained = (_load(out / "train/report.json") or {}).get("total_steps")
    model = (f"Checkpoint `{config['checkpoint']}` (variant `{variant}`, not trained here)" if config.get("checkpoint")
             else f"Variant `{variant}`" + (f" trained {trained} steps here" if trained else ""))
    int8_report = _load(out / "quantize/int8/report.json") or {}
    verdict = (int8_report.get("verdict") or {}).get("headline")
    lines = ["# E-3DPSM pipeline report", "", *([f"**{verdict}**", ""] if verdict else []),
             f"{model}, synthetic data (seed {config.get('seed')}), "
             f"{config.get('window_ms')} ms windows. Accuracy on the held-out test sequences, streamed "
             "with states never reset; latency on this machine with the stated thread count.", "",
             "## Accuracy and speed of each variant", "", *key_table(out), ""]
    if parity:
        status = "passed" if parity.get("passed") else "FAILED"
        runs = ", ".join(f"{r['window_ms']:g} ms" for r in parity.get("runs", []))
        lines += [f"Parity ONNX Runtime vs PyTorch ({runs}): **{status}** (details in "
                  "[parity/report.json](../parity/report.json)).", ""]
    lines += int8_section(int8_report)
    golden = _load(out / "golden/checks/summary.json")
    if golden:
        record = _load(out / "golden/record/golden.json") or {}
        lines += ["## Golden checks", "",
                  f"Every graph against the golden rollout ({record.get('steps')} steps of the test split recorded "
                  "from the PyTorch checkpoint), torch-free, on each runtime; fp32 at the parity tolerances, "
                  "compressed graphs at their accuracy budget "
                  "([golden/checks/summary.json](../golden/checks/summary.json)).", ""]
        summary_md = out / "golden/checks/summary.md"
        lines += [summary_md.read_text().rstrip() if summary_md.is_file() else "(no summary table)", ""]
    lines += edge_section(out)
    serve = serve_command(out, config.get("threads"))
    if (out / "clip/poses.gif").is_file() or serve:
        lines += ["## Poses you can watch", ""]
    if (out / "clip/poses.gif").is_file():
        lines += ["The first two seconds of the held-out sequence through the exported graph: LNES events "
                  "(red positive, blue negative), predicted skeleton in gold, ground truth in green.", "",
                  "![held-out clip](../clip/poses.gif)", ""]
    if serve:
        lines += ["Live in a browser, the whole held-out sequence at its own pace "
                  "(`e3dpsm serve`, docs/serve.md in the repository):", "",
                  f"`{serve}`", ""]
    lines += ["## Stages", "", "| stage | status | seconds | report |", "|---|---|---:|---|"]
    by_name = {stage.name: stage for stage in STAGES}
    for s in stages:
        stage = by_name.get(s["stage"])
        reports = (stage.human_report, stage.machine_report) if stage else ()
        links = " · ".join(f"[{p}](../{p})" for p in dict.fromkeys(reports) if (out / p).exists())
        lines.append(f"| {s['stage']} | {s['status']} | {s['seconds']} | {links or '-'} |")
    figures = sorted(p for p in out.glob("*/**/*.png") if "report" not in p.parts[len(out.parts):][:1])
    if figures:
        lines += ["", "## Figures", ""]
        for fig in figures[:12]:
            rel = fig.relative_to(out)
            lines += [f"### {rel}", "", f"![{rel}](../{rel})", ""]
    text = "\n".join(lines) + "\n"
    write_text_atomic(report_dir / "index.md", text)
    write_text_atomic(report_dir / "index.html", _html(text))
    summary = report_header("pipeline", config)
    summary["stages"] = stages
    write_json_atomic(report_dir / "pipeline.json", summary)
    return report_dir / "index.md"


def _html(markdown: str) -> str:
    """A dependency-free rendering: tables, headings, images and links become HTML."""
    body, table = [], []

    def flush_table() -> None:
        if table:
            rows = [r for r in table if not set(r.replace("|", "").strip()) <= set("-:")]
            cells = [[html.escape(c.strip()) for c in r.strip().strip("|").split("|")] for r in rows]
            head = "".join(f"<th>{c}</th>" for c in cells[0])
            rest = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells[1:])
            body.append(f"<table><tr>{head}</tr>{rest}</table>")
            table.clear()

    import re

    for line in markdown.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        flush_table()
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{html.escape(line[level:].strip())}</h{level}>")
        elif line.startswith("!["):
            src = line[line.index("(") + 1 : -1]
            body.append(f'<img src="{html.escape(src)}" style="max-width:900px">')
        elif line.strip():
            text = html.escape(line)
            text = re.sub(r"\[([^\]]+)\]\(([^)]+)\)", r'<a href="\2">\1</a>', text)
            text = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", text)
            body.append(f"<p>{text}</p>")
    flush_table()
    style = "body{font-family:sans-serif;max-width:1000px;margin:auto}table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 8px}"
    return f"<!doctype html><html><head><meta charset='utf-8'><title>E-3DPSM report</title><style>{style}</style></head><body>{''.join(body)}</body></html>\n"
