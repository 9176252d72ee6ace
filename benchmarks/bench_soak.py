"""Soak: `e3dpsm serve` left running with browsers, then `e3dpsm run` over an hour of events
(writes benchmarks/results/soak.json + soak.md).

    python benchmarks/bench_soak.py [--serve-minutes 30] [--run-hours 1] [--threads 2] [--keep-every 8]

Serve: the committed trained `small` (exported unless --model) replays a synthetic recording
(20 s, 96 x 128 render scale, synthesised unless --events) looped at 20 ms windows (50 Hz) for
--serve-minutes, to 3 headless Chromium pages, a stalled client (handshakes, never reads) and a
client that reconnects every second. Run: the same recording thinned to every --keep-every-th
event (`run` reads a file whole: an hour at full density is ~460 M events, 6 GB) and tiled to
--run-hours of stream time, through `e3dpsm run`.

Measured from outside the server and run processes (psutil, every few seconds): RSS, open file
descriptors, threads. Checks: RSS flat after the warm-up (the first 10% of the run, at least
30 s): growth at most 5 MB; every pose reached each healthy page in order; p50 / p99 latency
(pages) or per-window time (run) against the median step; descriptors and threads at the end
no more than after the warm-up.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_serve import SYNTH_ARGS, chromium, export_small, stalled_client  # noqa: E402  (same folder)

from e3dpsm.utils.stats import percentiles  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks/results"
PAGES = 3
SAMPLE_PERIOD_S = 5.0
RSS_GROWTH_LIMIT_MB = 5.0


class ProcessSampler(threading.Thread):
    """RSS (MB), open descriptors and threads of one process every `period_s`, until it exits."""

    def __init__(self, pid: int, period_s: float = SAMPLE_PERIOD_S) -> None:
        super().__init__(daemon=True)
        import psutil

        self.process, self.period_s = psutil.Process(pid), period_s
        self.samples: list[dict[str, float]] = []
        self.began = time.monotonic()
        self._halt = threading.Event()

    def run(self) -> None:
        import psutil

        while not self._halt.is_set():
            try:
                with self.process.oneshot():
                    self.samples.append({"t_s": round(time.monotonic() - self.began, 1),
                                         "rss_mb": round(self.process.memory_info().rss / 2**20, 2),
                                         "fds": self.process.num_fds(), "threads": self.process.num_threads()})
            except psutil.Error:  # it ended
                return
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=10)


def steady_state(samples: list[dict[str, float]], warmup_fraction: float = 0.1, min_warmup_s: float = 30.0) -> dict:
    """RSS, descriptors and threads after the warm-up and at the end, the RSS growth between and
    its least-squares slope; `flat` when the growth is at most RSS_GROWTH_LIMIT_MB."""
    if len(samples) < 2:
        raise RuntimeError(f"only {len(samples)} process samples: the run was too short to judge")
    end_s = samples[-1]["t_s"]
    warmup_s = min(max(min_warmup_s, warmup_fraction * end_s), end_s)
    after = [s for s in samples if s["t_s"] >= warmup_s] or samples[-1:]
    first, last = after[0], after[-1]
    t = np.array([s["t_s"] for s in after])
    rss = np.array([s["rss_mb"] for s in after])
    slope = float(np.polyfit(t, rss, 1)[0]) * 3600.0 if len(after) > 2 and np.ptp(t) > 0 else 0.0
    growth = round(last["rss_mb"] - first["rss_mb"], 2)
    return {"warmup_s": round(warmup_s, 1), "end_s": end_s, "rss_mb_after_warmup": first["rss_mb"],
            "rss_mb_end": last["rss_mb"], "rss_mb_max_after_warmup": float(rss.max()), "rss_growth_mb": growth,
            "rss_slope_mb_per_hour": round(slope, 2), "rss_flat": growth <= RSS_GROWTH_LIMIT_MB,
            "fds_after_warmup": first["fds"], "fds_end": last["fds"],
            "threads_after_warmup": first["threads"], "threads_end": last["threads"]}


class Reconnector(threading.Thread):
    """A client that connects every `period_s`, waits for the hello and closes."""

    def __init__(self, ws_url: str, period_s: float = 1.0) -> None:
        super().__init__(daemon=True)
        self.ws_url, self.period_s = ws_url, period_s
        self.connects = self.hellos = self.failures = 0
        self.last_error: str | None = None
        self._halt = threading.Event()

    def run(self) -> None:
        asyncio.run(self._loop())

    async def _loop(self) -> None:
        import aiohttp

        async with aiohttp.ClientSession() as session:
            while not self._halt.is_set():
                began = time.monotonic()
                self.connects += 1
                try:
                    async with session.ws_connect(self.ws_url, timeout=aiohttp.ClientWSTimeout(ws_close=2.0)) as ws:
                        first = await ws.receive(timeout=5.0)
                        self.hellos += first.type == aiohttp.WSMsgType.TEXT and '"hello"' in first.data
                except Exception as exc:  # noqa: BLE001 - counted: the server is gone or refused it
                    self.failures += 1
                    self.last_error = f"{type(exc).__name__}: {exc}"[:200]
                await asyncio.sleep(max(0.0, self.period_s - (time.monotonic() - began)))

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=15)


def _start_server(model: Path, events: Path, seconds: float, threads: int, out: Path) -> tuple[subprocess.Popen, str]:
    server = subprocess.Popen(
        [sys.executable, "-m", "e3dpsm", "serve", "--model", str(model), "--source", str(events), "--port", "0",
         "--threads", str(threads), "--duration-s", str(seconds), "--loop", "--wait-clients", str(PAGES + 1),
         "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = server.stdout.readline()
    if not line.startswith("serving"):
        raise RuntimeError(f"serve did not start: {line} {server.stderr.read()[-2000:]}")
    return server, line.split()[1]


def serve_soak(model: Path, events: Path, minutes: float, threads: int, work: Path) -> dict:
    seconds = minutes * 60.0
    load_before = os.getloadavg()
    server, url = _start_server(model, events, seconds, threads, work / "serve")
    parts = urlsplit(url)
    token = parse_qs(parts.query)["token"][0]
    sampler = ProcessSampler(server.pid)
    sampler.start()
    held = stalled_client(parts.port, token)
    drivers = [chromium(work / f"profile-{i}") for i in range(PAGES)]
    reconnector = Reconnector(f"http://127.0.0.1:{parts.port}/ws?token={token}")
    try:
        for driver in drivers:
            driver.get(url)
        reconnector.start()
        server.wait(timeout=seconds + 600)
        reconnector.stop()
        pages = [d.execute_script("return {latencies: e3dpsm.latencies, received: e3dpsm.received, "
                                  "drawn: e3dpsm.poseCount, gaps: e3dpsm.gaps, outOfOrder: e3dpsm.outOfOrder}")
                 for d in drivers]
    finally:
        reconnector.stop()
        sampler.stop()
        for driver in drivers:
            driver.quit()
        held.close()
        if server.poll() is None:
            server.kill()
    report = json.loads((work / "serve" / "serve.report.json").read_text())
    return serve_result(report, pages, sampler.samples, reconnector, load_before, minutes)


def serve_result(report: dict, pages: list[dict], samples: list[dict], reconnector: Reconnector | None,
                 load_before: tuple[float, ...], minutes: float) -> dict:
    step_p50 = report["step_ms"]["p50"]
    measured = []
    for state in pages:
        latency = percentiles(state["latencies"])
        measured.append({
            "received": state["received"], "drawn": state["drawn"], "gaps": state["gaps"],
            "out_of_order": state["outOfOrder"], "lost": report["poses"] - state["received"],
            "latency_ms": latency, "p50_over_step": round(latency["p50"] / step_p50, 3),
            "p99_over_step": round(latency["p99"] / step_p50, 3)})
    return {
        "minutes": minutes, "poses": report["poses"], "passes": report["passes"], "late_ticks": report["late_ticks"],
        "step_ms": report["step_ms"], "pages": measured, "clients_seen": report["clients_seen"],
        "drops": report["drops"], "refused": report.get("refused"),
        "reconnects": None if reconnector is None else {
            "connects": reconnector.connects, "hellos": reconnector.hellos, "failures": reconnector.failures,
            "last_error": reconnector.last_error},
        "process": steady_state(samples), "process_samples": samples,
        "server_rss_mb": {k: report["rss_mb"][k] for k in ("start", "end", "max")},
        "load_avg_before": [round(v, 2) for v in load_before], "load_avg_after": [round(v, 2) for v in os.getloadavg()],
    }


def tile_recording(events: Path, hours: float, keep_every: int, out: Path) -> dict:
    """`events` thinned to every `keep_every`-th event and repeated end to end (each copy shifted
    by the recording's span in whole 20 ms windows) up to `hours` of stream time, as .npz with
    an event_meta.json beside it; returns what was written."""
    from e3dpsm.data.readers import read_events

    stream = read_events(events)
    keep = slice(None, None, keep_every)
    x, y, t, p = stream.x[keep], stream.y[keep], stream.t_us[keep] - stream.t_us[0], stream.p[keep]
    span_us = (int(t[-1]) // 20_000 + 1) * 20_000
    copies = max(1, int(np.ceil(hours * 3600e6 / span_us)))
    total = copies * len(t)
    columns = {name: np.empty(total, dtype=a.dtype) for name, a in (("x", x), ("y", y), ("t", t), ("p", p))}
    for k in range(copies):
        part = slice(k * len(t), (k + 1) * len(t))
        columns["x"][part], columns["y"][part], columns["p"][part] = x, y, p
        columns["t"][part] = t + k * span_us
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **columns)
    height, width = stream.sensor_hw
    (out.parent / "event_meta.json").write_text(json.dumps({"height": int(height), "width": int(width)}))
    return {"events": total, "copies": copies, "stream_s": round(copies * span_us / 1e6, 3),
            "windows": copies * span_us // 20_000, "keep_every": keep_every, "source_events": len(stream)}


def run_soak(model: Path, events: Path, threads: int, work: Path) -> dict:
    out = work / "run" / "poses.csv"
    load_before = os.getloadavg()
    began = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "e3dpsm", "run", "--model", str(model), "--events", str(events),
                             "--out", str(out), "--threads", str(threads), "--no-progress"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sampler = ProcessSampler(proc.pid)
    sampler.start()
    _, err = proc.communicate()
    sampler.stop()
    if proc.returncode != 0:
        raise RuntimeError(f"e3dpsm run failed ({proc.returncode}): {err[-2000:]}")
    report = json.loads(out.with_suffix(".report.json").read_text())
    t_us = np.loadtxt(out, delimiter=",", skiprows=1, usecols=0, dtype=np.int64, ndmin=1)
    steps = np.diff(t_us)
    return {"wall_s": round(time.monotonic() - began, 1), "windows": report["windows"], "poses": int(t_us.size),
            "out_of_order": int((steps <= 0).sum()), "gaps": int((steps > 20_000).sum()),
            "step_ms": report.get("step_ms"), "window_ms": report.get("window_ms"),
            "window_p50_over_step": _ratio(report, "p50"), "window_p99_over_step": _ratio(report, "p99"),
            "mean_step_ms": report["mean_step_ms"], "mean_overhead_ms": report["mean_overhead_ms"],
            "process": steady_state(sampler.samples), "process_samples": sampler.samples,
            "load_avg_before": [round(v, 2) for v in load_before],
            "load_avg_after": [round(v, 2) for v in os.getloadavg()]}


def _ratio(report: dict, q: str) -> float | None:
    window, step = report.get("window_ms"), report.get("step_ms")
    if not window or not step or not step.get("p50"):
        return None
    return round(window[q] / step["p50"], 3)


def verdicts(serve: dict, run: dict) -> dict[str, bool]:
    def no_more(process: dict, what: str) -> bool:
        return process[f"{what}_end"] <= process[f"{what}_after_warmup"]

    return {
        f"serve: RSS growth after warm-up <= {RSS_GROWTH_LIMIT_MB:g} MB": serve["process"]["rss_flat"],
        "serve: every pose reached each page, in order": all(
            p["lost"] == 0 and p["gaps"] == 0 and p["out_of_order"] == 0 for p in serve["pages"]),
        "serve: descriptors and threads at the end <= after warm-up": no_more(serve["process"], "fds")
        and no_more(serve["process"], "threads"),
        f"run: RSS growth after warm-up <= {RSS_GROWTH_LIMIT_MB:g} MB": run["process"]["rss_flat"],
        "run: every window's pose, in order": run["poses"] == run["windows"] and run["out_of_order"] == 0
        and run["gaps"] == 0,
        "run: descriptors and threads at the end <= after warm-up": no_more(run["process"], "fds")
        and no_more(run["process"], "threads"),
    }


def markdown(result: dict) -> str:
    machine, serve, run = result["machine"], result["serve"], result["run"]
    isa = machine.get("isa", {})
    sp, rp = serve["process"], run["process"]
    lines = [
        "# Soak: `e3dpsm serve` and `e3dpsm run` left running", "",
        f"`python benchmarks/bench_soak.py --serve-minutes {serve['minutes']:g} --run-hours {result['run_hours']:g} "
        f"--threads {result['threads']} --keep-every {result['tiling']['keep_every']}`, {result['created']}. "
        f"Graph: {result['model']}. CPU: {machine.get('cpu_model')} ({machine.get('cpu_count')} cores, ISA "
        f"{isa.get('kind')}: {', '.join(isa.get('flags', []))}); {result['note']}", "",
        f"Serve: {serve['minutes']:g} min at 50 Hz (20 ms windows, looped recording), {len(serve['pages'])} headless "
        f"Chromium pages, a stalled client, a client reconnecting every second ({serve['reconnects']['connects']} "
        f"connects, {serve['reconnects']['hellos']} hellos, {serve['reconnects']['failures']} failures); "
        f"{serve['poses']} poses, {serve['late_ticks']} late ticks. Run: {run['windows']} windows "
        f"({result['tiling']['stream_s'] / 3600:.2f} h of stream, {result['tiling']['events']:,} events: every "
        f"{result['tiling']['keep_every']}th event of the recording, tiled) in {run['wall_s']:.0f} s.", "",
        "| process | RSS after warm-up (MB) | RSS at the end (MB) | growth (MB) | slope (MB/h) | "
        "fds after warm-up / end | threads after warm-up / end |",
        "|---|---:|---:|---:|---:|---:|---:|"]
    for name, p in (("serve", sp), ("run", rp)):
        lines.append(f"| {name} (warm-up {p['warmup_s']:g} s of {p['end_s']:g} s) | {p['rss_mb_after_warmup']} | "
                     f"{p['rss_mb_end']} | {p['rss_growth_mb']} | {p['rss_slope_mb_per_hour']} | "
                     f"{p['fds_after_warmup']} / {p['fds_end']} | {p['threads_after_warmup']} / {p['threads_end']} |")
    lines += ["", "| serve page | received / sent | lost | gaps | out of order | latency p50 (ms) | p99 (ms) | "
              "step p50 (ms) | p50 / step | p99 / step |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for i, page in enumerate(serve["pages"]):
        lines.append(f"| {i} | {page['received']} / {serve['poses']} | {page['lost']} | {page['gaps']} | "
                     f"{page['out_of_order']} | {page['latency_ms']['p50']} | {page['latency_ms']['p99']} | "
                     f"{serve['step_ms']['p50']} | {page['p50_over_step']} | {page['p99_over_step']} |")
    window, step = run.get("window_ms") or {}, run.get("step_ms") or {}
    lines += ["", "| run | poses / windows | out of order | gaps | time per window p50 (ms) | p99 (ms) | step p50 (ms) "
              "| p50 / step | p99 / step |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
              f"| {run['poses']:,} poses | {run['poses']} / {run['windows']} | {run['out_of_order']} | {run['gaps']} | "
              f"{window.get('p50')} | {window.get('p99')} | {step.get('p50')} | {run['window_p50_over_step']} | "
              f"{run['window_p99_over_step']} |", "",
              f"Drops per serve client (poses / frames): " + ", ".join(
                  f"#{k}: {v['poses']} / {v['frames']}" for k, v in list(serve["drops"].items())[:PAGES + 1]) +
              f"; refused: {serve['refused']}. Load average before -> after: serve {serve['load_avg_before'][0]} -> "
              f"{serve['load_avg_after'][0]}, run {run['load_avg_before'][0]} -> {run['load_avg_after'][0]}.", "",
              "| check | holds |", "|---|---|"]
    lines += [f"| {k} | {'yes' if v else '**no**'} |" for k, v in result["verdicts"].items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None, help="step graph (default: the committed small, exported)")
    parser.add_argument("--events", type=Path, default=None, help="recording (default: synthesised, 20 s)")
    parser.add_argument("--serve-minutes", type=float, default=30.0)
    parser.add_argument("--run-hours", type=float, default=1.0)
    parser.add_argument("--keep-every", type=int, default=8, help="run: keep every Nth event of the recording")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--note", default="the machine was shared with other jobs (load averages below).",
                        help="a sentence on the conditions, for the results file")
    parser.add_argument("--out", type=Path, default=RESULTS / "soak")
    args = parser.parse_args(argv)
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    with tempfile.TemporaryDirectory(prefix="bench_soak_") as tmp:
        work = Path(tmp)
        model = args.model or export_small(work)
        events = args.events
        if events is None:
            subprocess.run([sys.executable, "-m", "e3dpsm", "synth", "--out", str(work / "data"), *SYNTH_ARGS,
                            "--no-progress"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
            events = next((work / "data").glob("*/events.h5"))
        serve = serve_soak(model, events, args.serve_minutes, args.threads, work)
        tiling = tile_recording(events, args.run_hours, args.keep_every, work / "hour" / "events.npz")
        run = run_soak(model, work / "hour" / "events.npz", args.threads, work)
    config = {"serve_minutes": args.serve_minutes, "run_hours": args.run_hours, "keep_every": args.keep_every,
              "threads": args.threads}
    result = {**report_header("bench_soak", config),
              "model": str(args.model or "benchmarks/checkpoints/small (exported)"),
              "events": str(args.events or "synthesised: e3dpsm synth " + " ".join(SYNTH_ARGS)),
              "threads": args.threads, "run_hours": args.run_hours, "note": args.note, "tiling": tiling,
              "serve": serve, "run": run}
    result["verdicts"] = verdicts(serve, run)
    write_json_atomic(args.out.with_suffix(".json"), result)
    write_text_atomic(args.out.with_suffix(".md"), markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
