"""The ablation benchmark: one training run per ablation, each evaluated both ways."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Mapping

from e3dpsm.data.prepared import PreparedData
from e3dpsm.evaluation.core import METRICS
from e3dpsm.evaluation.evaluate import evaluate_checkpoint
from e3dpsm.evaluation.tables import markdown_table
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic


# The paper's qualitative claims (ablation table and text), as thresholds on our figures.
SMOOTHNESS_RATIO_MIN = 1.5    # direct-only e_smooth / learned-fusion e_smooth
CAUSAL_GAP_MAX_PCT = 5.0      # "a few percent": causal vs non-causal MPJPE of the full model
# The paper's ablation table (EE3D-R, MPJPE mm): the full model beats each of the others.
PAPER_FULL_MPJPE = 84.45
PAPER_ABLATION_MPJPE = {"direct_only": 91.26, "static_fusion": 88.31, "no_ssm": 118.53}
_ORDERING_CLAIMS = {"direct_only": "learned fusion beats direct-only",
                    "static_fusion": "learned fusion beats static fusion",
                    "no_ssm": "the SSM blocks lower MPJPE"}


def paper_claims(rows: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Each of the paper's claims that the measured rows can test: the figures it rests on,
    the threshold and whether it holds. Claims whose rows were not run are left out.

    Drift is the causal MPJPE of the last tenth of the sequences over the first tenth: a
    filter that integrates deltas without correction accumulates error along the stream.
    """
    claims: list[dict[str, Any]] = []
    full = rows.get("full")
    if full is None:
        return claims
    causal = full["causal"]
    if "naive_fusion" in rows:
        naive = rows["naive_fusion"]["causal"]
        drift = lambda row: row["error_over_time"][-1] / max(row["error_over_time"][0], 1e-9)  # noqa: E731
        claims.append({
            "claim": "learned fusion beats naive fusion (causal MPJPE)",
            "figures": {"full": causal["mpjpe"], "naive_fusion": naive["mpjpe"]},
            "holds": causal["mpjpe"] < naive["mpjpe"]})
        claims.append({
            "claim": "naive fusion drifts: its error grows along the sequence more than the full model's",
            "figures": {"full_last_over_first": drift(causal), "naive_last_over_first": drift(naive)},
            "holds": drift(naive) > max(drift(causal), 1.0)})
    if "direct_only" in rows:
        direct = rows["direct_only"]["causal"]
        ratio = direct["e_smooth"] / max(causal["e_smooth"], 1e-9)
        claims.append({
            "claim": f"learned fusion gives >= {SMOOTHNESS_RATIO_MIN}x lower e_smooth than direct-only",
            "figures": {"full": causal["e_smooth"], "direct_only": direct["e_smooth"], "ratio": ratio},
            "holds": ratio >= SMOOTHNESS_RATIO_MIN})
    for name, claim in _ORDERING_CLAIMS.items():
        if name in rows:
            other = rows[name]["causal"]["mpjpe"]
            claims.append({
                "claim": f"{claim} (causal MPJPE; paper {PAPER_FULL_MPJPE:g} vs {PAPER_ABLATION_MPJPE[name]:g})",
                "figures": {"full": causal["mpjpe"], name: other},
                "holds": causal["mpjpe"] < other})
    gap = 100.0 * (causal["mpjpe"] - full["non_causal"]["mpjpe"]) / full["non_causal"]["mpjpe"]
    claims.append({
        "claim": f"causal MPJPE within {CAUSAL_GAP_MAX_PCT:g}% of non-causal",
        "figures": {"causal": causal["mpjpe"], "non_causal": full["non_causal"]["mpjpe"], "gap_pct": gap},
        "holds": abs(gap) <= CAUSAL_GAP_MAX_PCT})
    return claims


def claims_markdown(claims: list[dict[str, Any]]) -> str:
    lines = ["| claim | figures | holds |", "|---|---|---|"]
    for c in claims:
        figures = ", ".join(f"{k} {v:.3g}" for k, v in c["figures"].items())
        lines.append(f"| {c['claim']} | {figures} | {'yes' if c['holds'] else '**no**'} |")
    return "\n".join(lines) + "\n"


def run_ablations(args: argparse.Namespace, out: Path, test_data: PreparedData, progress: bool) -> dict[str, Any]:
    from e3dpsm.training.ablations import ablation_overrides
    from e3dpsm.training.trainer import CHECKPOINT_NAME, RunOptions, TrainArgs, train

    rows: dict[str, Any] = {}
    for name in args.ablations:
        run_dir = out / "runs" / name
        train_args = TrainArgs(variant=args.variant, steps=args.steps, seq_len=args.seq_len,
                               batch_size=args.batch_size, seed=args.seed, split=args.split,
                               overrides=ablation_overrides(name))
        # A finished run is reused, so an interrupted benchmark resumes where it stopped.
        finished = (run_dir / "report.json").is_file() and not args.force
        if not finished:
            resume = (run_dir / CHECKPOINT_NAME).is_file() and not args.force
            train(train_args, args.data, run_dir, RunOptions(resume=resume, force=args.force, progress=progress))
        row: dict[str, Any] = {"overrides": {k: list(v) if isinstance(v, tuple) else v
                                             for k, v in ablation_overrides(name).items()}}
        for key, causal in (("causal", True), ("non_causal", False)):
            results, _ = evaluate_checkpoint(run_dir / CHECKPOINT_NAME, test_data, args.test_split, causal)
            row[key] = {**results["totals"], "error_over_time": results["error_over_time"]["mpjpe"]}
        rows[name] = row
    claims = paper_claims(rows)
    table = {**report_header("ablation", {k: v for k, v in vars(args).items() if k != "func"}), "rows": rows,
             "claims": claims}
    write_json_atomic(out / "ablation.json", table)
    flat = {f"{name} ({mode.replace('_', '-')})": row[mode] for name, row in rows.items()
            for mode in ("causal", "non_causal")}
    drift = {name: {f"{(i + 0.5) / 10:.2f}": v for i, v in enumerate(row["causal"]["error_over_time"])}
             for name, row in rows.items()}
    md = (f"# Ablations ({args.variant}, {args.steps} steps each)\n\nmm; totals = unweighted mean of per-action means.\n\n"
          + markdown_table(flat, METRICS, "ablation")
          + "\n## The paper's claims on these figures\n\n" + claims_markdown(claims)
          + "\n## Causal MPJPE along the sequences (tenths of each sequence)\n\n"
          + markdown_table(drift, list(next(iter(drift.values()), {})), "ablation"))
    write_text_atomic(out / "ablation.md", md)
    return table
