"""`e3dpsm serve`: watch a step graph's poses live in a browser (page `/`, WebSocket `/ws`).

Thin: option checks here, the server in e3dpsm/serve/. Torch-free (numpy, onnxruntime, aiohttp).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import math
from pathlib import Path
from e3dpsm.cli._common import add_threads

DEFAULT_OUT_ROOT = "serve-reports"


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "serve",
        help="serve a live pose viewer (browser page + WebSocket) over a replayed recording or a live source",
        description="Replay an event file at its own pace (or read a live dv:// source), step the graph "
        "window by window, and push every pose to the browsers connected to http://HOST:PORT/ (3D skeleton, "
        "event frame, ground truth when the recording has it, Hz and latency readouts). Stops at the end of "
        "the recording, after --duration-s or on Ctrl-C, and writes serve.report.json into --out.",
    )
    parser.add_argument("--model", required=True, help="step graph written by `e3dpsm export` (or quantize)")
    parser.add_argument("--source", required=True,
                        help="event file (.h5/.hdf5/.npz, and what e3dpsm.data.readers reads) or a live dv://HOST:PORT")
    parser.add_argument("--port", type=int, default=8765, help="TCP port (default 8765; 0 picks a free one)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (default 127.0.0.1, this machine only; docs/serve.md#security "
                        "says how to reach the viewer from another one)")
    access = parser.add_mutually_exclusive_group()
    access.add_argument("--token", default=None,
                        help="the secret the page and socket need (default: a random one, printed in the URL)")
    access.add_argument("--no-token", action="store_true",
                        help="no token: any local program may watch (allowed only with a loopback --host)")
    parser.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                        help="another origin whose pages may open the socket, e.g. https://viewer.example.org "
                        "behind a reverse proxy (repeatable; default: only the page this server serves)")
    parser.add_argument("--speed", type=float, default=1.0, help="replay speed factor of a recording (default 1)")
    parser.add_argument("--compare", default=None, metavar="GRAPH",
                        help="a second step graph run on the same events; its skeleton is overlaid")
    add_threads(parser, "onnxruntime intra-op threads per graph")
    parser.add_argument("--window-ms", type=float, default=None,
                        help="window length T in ms (default: the graph's training window)")
    parser.add_argument("--out", default=None,
                        help=f"folder for serve.report.json (default: {DEFAULT_OUT_ROOT}/<UTC time>/ here)")
    parser.add_argument("--duration-s", type=float, default=None, help="stop after this many seconds of replay")
    parser.add_argument("--loop", action="store_true",
                        help="restart the recording at its end, with a fresh state (t_us keeps increasing)")
    parser.add_argument("--wait-clients", type=int, default=0, metavar="N",
                        help="start the replay only once N clients have connected (default 0: at once)")
    parser.add_argument("--client-backlog", type=int, default=250, metavar="POSES",
                        help="poses queued per client before its oldest are dropped (default 250, 5 s at 50 Hz)")
    parser.add_argument("--frame-hz", type=float, default=10.0,
                        help="most event-frame images per second sent to each client (default 10)")
    parser.set_defaults(func=run)
    return parser


def check_options(args: argparse.Namespace) -> None:
    """Refuse bad values before anything is loaded or bound."""
    from e3dpsm.errors import ConfigError
    from e3dpsm.serve.security import is_loopback, normalise_origin

    if args.no_token and not is_loopback(args.host):
        raise ConfigError(f"--no-token is allowed on loopback only: --host {args.host} is reachable from other "
                          "machines; drop --no-token (a token is generated) or bind 127.0.0.1")
    if args.token is not None and not args.token.strip():
        raise ConfigError("--token must not be empty")
    for origin in args.allow_origin:
        try:
            normalise_origin(origin)
        except ValueError as exc:
            raise ConfigError(f"--allow-origin: {exc}") from None
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port must be in 0..65535, got {args.port}")
    for name in ("speed", "frame_hz"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"--{name.replace('_', '-')} must be a positive number, got {value}")
    for name in ("window_ms", "duration_s"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ConfigError(f"--{name.replace('_', '-')} must be a positive number, got {value}")
    if args.threads is not None and args.threads <= 0:
        raise ConfigError(f"--threads must be positive, got {args.threads}")
    if args.wait_clients < 0:
        raise ConfigError(f"--wait-clients must be 0 or more, got {args.wait_clients}")
    if args.client_backlog < 1:
        raise ConfigError(f"--client-backlog must be at least 1, got {args.client_backlog}")


def default_out() -> str:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S")
    return str(Path(DEFAULT_OUT_ROOT) / stamp)


def run(args: argparse.Namespace) -> int:
    check_options(args)
    import asyncio

    from e3dpsm.utils.io import check_writable_folder
    from e3dpsm.joints import JOINT_NAMES, PARENTS
    from e3dpsm.runtime.stepping import open_stepper
    from e3dpsm.serve.clients import ClientHub
    from e3dpsm.serve.estimator import ServeEngine
    from e3dpsm.serve.security import new_token
    from e3dpsm.serve.server import ServeConfig, serve
    from e3dpsm.data.live import is_live_url

    out = args.out or default_out()
    check_writable_folder(Path(out))
    config = ServeConfig(
        model=args.model, source=args.source, out=out, host=args.host, port=args.port,
        token=None if args.no_token else (args.token or new_token()), allow_origins=tuple(args.allow_origin),
        speed=args.speed, compare=args.compare, threads=args.threads, window_ms=args.window_ms,
        duration_s=args.duration_s, loop=args.loop, wait_clients=args.wait_clients,
        client_backlog=args.client_backlog, frame_hz=args.frame_hz,
    )
    # No spinning: between two steps (a window apart) idle ORT workers would busy-wait on the
    # cores the event loop and the browsers need. A bad graph fails before the source opens.
    session = open_stepper(args.model, threads=args.threads, spin=False)
    compare = open_stepper(args.compare, threads=args.threads, spin=False) if args.compare else None
    window_ms = float(args.window_ms if args.window_ms is not None else session.meta.train_window_ms)
    from e3dpsm.events import window_us_from_ms

    source, ground_truth = _open_source(args, window_us_from_ms(window_ms))
    hub = ClientHub(args.client_backlog)
    engine = ServeEngine(source, hub, session, window_ms=window_ms, compare=compare, ground_truth=ground_truth,
                         frame_hz=args.frame_hz)
    joints = list(session.meta.joints)
    index = {name: i for i, name in enumerate(joints)}
    bones = [(index[JOINT_NAMES[child]], index[JOINT_NAMES[parent]]) for child, parent in enumerate(PARENTS)
             if child != parent and JOINT_NAMES[child] in index and JOINT_NAMES[parent] in index]
    hello_fields = {
        "joints": joints, "bones": bones, "models": [Path(args.model).name] + ([Path(args.compare).name] if compare else []),
        "window_ms": window_ms, "sensor_hw": tuple(source.sensor_hw), "frame_hw": tuple(session.meta.frame_hw),
        "source": args.source if is_live_url(args.source) else Path(args.source).name, "live": source.live,
        "ground_truth": ground_truth is not None, "speed": args.speed,
    }
    graphs = {"model": _graph_info(session), "compare": _graph_info(compare) if compare else None}
    try:
        report = asyncio.run(serve(config, source, engine, hub, hello_fields, graphs,
                                   announce=lambda line: print(line, flush=True)))
    finally:
        source.close()
    page = report["latency_ms"]["page"]
    print(f"{report['poses']} poses to {report['clients_seen']} client(s), stopped: {report['stop_reason']}; "
          f"step p50 {report['step_ms']['p50']} ms, page latency p50 {page['p50']} ms -> "
          f"{Path(out) / 'serve.report.json'}", flush=True)
    return 0


def _open_source(args: argparse.Namespace, window_us: int):
    from e3dpsm.data.live import is_live_url, open_live_source
    from e3dpsm.serve.source import LiveFeed, RecordingReplay

    if is_live_url(args.source):
        if args.loop:
            from e3dpsm.errors import ConfigError

            raise ConfigError("--loop replays a recording; a live source cannot restart")
        return LiveFeed(open_live_source(args.source)), None
    from e3dpsm.data.readers import read_events
    from e3dpsm.runtime.render_stream import ground_truth_beside

    stream = read_events(args.source)
    return RecordingReplay(stream, window_us, speed=args.speed, loop=args.loop), ground_truth_beside(args.source)


def _graph_info(session) -> dict:
    meta = session.meta
    return {"path": str(session.path), "variant": meta.config.get("variant"), "quantization": meta.quantization,
            "frame_hw": list(meta.frame_hw), "train_window_ms": meta.train_window_ms}
