"""Results table of `e3dpsm prune` on the committed trained small, from the run's report and
the checks made on its result (parity, the evaluate command):

    e3dpsm prune --checkpoint benchmarks/checkpoints/small/checkpoint.pt --data prep96 \\
        --eval-data prep96_test --out RUN --target-latency-ms 60% --rounds 1 --extra-rounds 0 \\
        --steps 300 --labels gt --lr 1e-3 --threads 2
    e3dpsm parity --model RUN/graphs/round1.onnx --checkpoint RUN/checkpoint.pt --data prep96_test \\
        --steps 1000 --window-ms 20 25 50 --threads 2 --report RUN/parity.json
    e3dpsm evaluate --checkpoint RUN/checkpoint.pt --data prep96_test --split all --out RUN/eval --causal
    python benchmarks/prune_small_results.py RUN

Writes benchmarks/results/prune_small.md and .json (the front per round, the parity figures,
the evaluate command's MPJPE, the time the recovery took, predicted against measured step).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from e3dpsm.compress.report import front_rows, render_markdown
from e3dpsm.utils.io import write_json_atomic, write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"


def main(run: Path) -> None:
    report = json.loads((run / "report.json").read_text())
    parity = json.loads((run / "parity.json").read_text()) if (run / "parity.json").is_file() else None
    evaluate = json.loads((run / "eval" / "metrics.json").read_text()) if (run / "eval" / "metrics.json").is_file() else None
    rows = front_rows(report)
    out = {"prune_report": {k: v for k, v in report.items() if k != "rounds"},
           "rounds": [{k: v for k, v in r.items() if k != "candidates"} for r in report["rounds"]],
           "front": rows, "parity": parity, "evaluate": evaluate}
    write_json_atomic(RESULTS / "prune_small.json", out)
    md = render_markdown(report, report)
    extra = ["", "## Checks on the result", ""]
    if parity is not None:
        runs = parity.get("runs", [parity])
        for p in runs:
            worst = max(t["max_abs"] for t in p["tensors"] if t["kind"] == "output")
            extra.append(f"- parity ONNX Runtime vs PyTorch, {p['steps']} steps at {p['window_ms']:g} ms: "
                         f"max |pose diff| {worst:.2e} mm ({'passed' if p.get('passed', True) else 'FAILED'})")
    if evaluate is not None:
        extra.append(f"- `e3dpsm evaluate --causal` on prep96_test (all): {json.dumps(evaluate.get('totals', {}))}")
    write_text_atomic(RESULTS / "prune_small.md", md + "\n".join(extra) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
