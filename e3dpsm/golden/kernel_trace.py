"""Where a quantised graph's integer arithmetic parts between two machines, node by node.

`golden check` tells whether a device computes what the host computed for one INT8 graph;
this says where it stops doing so. The host steps the graph (quantised activations exposed,
kernel_cut.py) over the golden's frames, states carried, and keeps every quantised
activation's codes at every step: the trace. The device then runs the same graph twice:
- propagated: its own rollout from the same frames, states carried; the first step and the
  first quantised activation whose codes differ say where the two machines part;
- isolated: the cut graph, each segment fed the host's codes of the activations it reads and
  the host's states; a segment's departures there are its own arithmetic's (a fused integer
  kernel and its requantisation, or the float ops between two quantised activations), none
  received from upstream.
Codes are compared exactly (a departure is a code one or more steps of the scale away).
Torch-free and onnx-free: the device needs numpy and onnxruntime only.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

FEED_SUFFIX = "__host_codes"  # the cut graph's input that feeds a segment the host's codes (kernel_cut.py)
IN, CODE, OUT = "in.", "q.", "out."  # trace keys: graph inputs, quantised activations, graph outputs


@dataclass(frozen=True)
class CodeDiff:
    """One quantised activation's departures over a rollout (codes: integers)."""

    name: str
    first_step: int | None   # first step with any code apart (None: identical throughout)
    steps_apart: int         # steps with any code apart
    elements: int            # codes compared at every step
    apart: int               # codes apart, summed over the steps
    max_codes: int           # largest |host - device| in code steps
    mean_signed: float       # mean (device - host) over the codes apart: a rounding bias shows here

    @property
    def fraction(self) -> float:
        return self.apart / max(self.elements * max(self.steps_apart, 1), 1)

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "fraction_of_apart_steps": self.fraction}


def compare_codes(name: str, host: np.ndarray, device: np.ndarray) -> CodeDiff:
    """Exact comparison of one activation's codes, [steps, ...] on each side (one step or more)."""
    if host.shape != device.shape:
        raise ValueError(f"{name}: host codes {host.shape}, device codes {device.shape}")
    if host.ndim == 0 or not len(host):
        raise ValueError(f"{name}: no steps to compare (codes of shape {host.shape})")
    diff = device.astype(np.int32) - host.astype(np.int32)
    per_step = np.count_nonzero(diff.reshape(len(diff), -1), axis=1)
    apart_steps = np.flatnonzero(per_step)
    nonzero = diff[diff != 0]
    return CodeDiff(name, int(apart_steps[0]) if apart_steps.size else None, int(apart_steps.size),
                    int(diff[0].size), int(per_step.sum()),
                    int(np.abs(nonzero).max()) if nonzero.size else 0,
                    float(nonzero.mean()) if nonzero.size else 0.0)


def compare_traces(host: Mapping[str, np.ndarray], device: Mapping[str, np.ndarray],
                   order: Sequence[str]) -> list[CodeDiff]:
    """Every quantised activation in `order` (graph order), host codes against device codes."""
    return [compare_codes(name, host[CODE + name], device[CODE + name]) for name in order]


def first_departures(diffs: Sequence[CodeDiff], limit: int = 5) -> list[CodeDiff]:
    """The activations that depart first: by step, then by graph order."""
    apart = [(d.first_step, i, d) for i, d in enumerate(diffs) if d.first_step is not None]
    return [d for _, _, d in sorted(apart, key=lambda a: (a[0], a[1]))[:limit]]


def _session(path: str | os.PathLike, threads: int | None) -> Any:
    from e3dpsm.runtime.session import make_session

    return make_session(path, threads=threads)


def _state_pairs(session: Any) -> list[tuple[str, str]]:
    """(input, output) name of every state, from the graph's metadata."""
    from e3dpsm.graph_metadata import GraphMetadata

    meta = GraphMetadata.from_session(session)
    return [(s.input_name, s.output_name) for s in meta.states]


def _run(session: Any, feeds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    names = [o.name for o in session.get_outputs()]
    return dict(zip(names, session.run(names, dict(feeds))))


def rollout(exposed: str | os.PathLike, inputs: Iterator[dict[str, np.ndarray]], codes: Sequence[str],
            threads: int | None = 1) -> dict[str, np.ndarray]:
    """Step the exposed graph over `inputs` (each step's frame and window; states as given at
    the first step, then carried), keeping every graph input, code and output per step."""
    session = _session(exposed, threads)
    pairs = _state_pairs(session)
    kept: dict[str, list[np.ndarray]] = {}
    carried: dict[str, np.ndarray] = {}
    for feeds in inputs:
        feeds = {**feeds, **carried}
        got = _run(session, feeds)
        carried = {i: got[o] for i, o in pairs}
        for key, value in [*((IN + k, v) for k, v in feeds.items()), *((CODE + c, got[c]) for c in codes),
                           *((OUT + o, got[o]) for _, o in pairs)]:
            kept.setdefault(key, []).append(np.asarray(value))
    return {k: np.stack(v) for k, v in kept.items()}


def isolated(cut: str | os.PathLike, host: Mapping[str, np.ndarray], codes: Sequence[str],
             threads: int | None = 1) -> dict[str, np.ndarray]:
    """The cut graph at every step of the host's trace, each segment fed the host's codes and
    the host's graph inputs (states included)."""
    session = _session(cut, threads)
    wanted = {i.name for i in session.get_inputs()}
    steps = len(next(iter(v for k, v in host.items() if k.startswith(IN))))
    kept: dict[str, list[np.ndarray]] = {CODE + c: [] for c in codes}
    for step in range(steps):
        feeds = {k[len(IN):]: v[step] for k, v in host.items() if k.startswith(IN) and k[len(IN):] in wanted}
        feeds.update({c + FEED_SUFFIX: host[CODE + c][step] for c in codes if c + FEED_SUFFIX in wanted})
        got = _run(session, feeds)
        for c in codes:
            kept[CODE + c].append(got[c])
    return {k: np.stack(v) for k, v in kept.items()}


def load_trace(path: str | os.PathLike) -> dict[str, np.ndarray]:
    with np.load(Path(path), allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}
