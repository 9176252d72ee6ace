"""Speed of the synthetic data generator: 60 s of data covering all ten actions.

    python benchmarks/bench_synth.py [--sequences 6] [--seconds 10] [--workers 2]
                                     [--out benchmarks/results/synth.json]

Target: 60 s of data in at most 3 minutes of wall time on 2 cores. The run writes a real
data set (with previews off) into a temporary folder and deletes it. Besides wall time the
report records the CPU seconds the workers used and the load average before and after, so
a figure taken on a busy machine can be told apart from a slow generator; a stage
breakdown of one short sequence (cProfile, one process) says where the time goes.
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import resource
import tempfile
import time
from pathlib import Path

from e3dpsm.data.synth.dataset import write_dataset
from e3dpsm.data.synth.generator import SynthConfig, generate_sequence
from e3dpsm.joints import ACTIONS
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic

TARGET_WALL_S = 180.0
# Stage -> (module file, function) whose cumulative time measures it.
STAGES = {
    "motion_and_kinematics": ("motion.py", "make_trajectory"),
    "render_total": ("render.py", "render"),
    "render_room": ("render.py", "_room_intensity"),
    "event_simulation": ("event_sim.py", "step"),
    "visibility": ("generator.py", "occlusion"),
}


def stage_breakdown(seconds: float) -> dict[str, float]:
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.runcall(generate_sequence, SynthConfig(seed=0, seconds=seconds), 0)
    total = time.perf_counter() - start
    stats = pstats.Stats(profiler).stats
    out = {"sequence_s": seconds, "total_s": total}
    for stage, (module, func) in STAGES.items():
        out[f"{stage}_s"] = sum(v[3] for (path, _, name), v in stats.items()
                                if name == func and path.endswith(f"synth/{module}"))
    out["render_body_s"] = out["render_total_s"] - out["render_room_s"]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=6)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--profile-seconds", type=float, default=2.0)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "synth.json"))
    parser.add_argument("--breakdown-only", action="store_true", help="print the stage breakdown and exit")
    args = parser.parse_args()
    if args.breakdown_only:
        print(stage_breakdown(args.profile_seconds))
        return 0

    config = SynthConfig(seed=0, seconds=args.seconds)
    load_before = os.getloadavg()
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        report = write_dataset(Path(tmp) / "ds", config, args.sequences, workers=args.workers, progress=True)
        wall = time.perf_counter() - start
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_after = os.getloadavg()
    cpu = (cpu_after.ru_utime - cpu_before.ru_utime) + (cpu_after.ru_stime - cpu_before.ru_stime)
    data_s = args.sequences * args.seconds
    realism = report["realism"]
    result = report_header("bench_synth", {**config.to_json(), "sequences": args.sequences, "workers": args.workers})
    result.update({
        "data_seconds": data_s,
        "wall_s": wall,
        "wall_s_per_60s_of_data": wall * 60.0 / data_s,
        "target_wall_s_per_60s": TARGET_WALL_S,
        "meets_target": wall * 60.0 / data_s <= TARGET_WALL_S,
        "worker_cpu_s": cpu if args.workers > 1 else None,
        "load_average_before_after": [load_before[0], load_after[0]],
        "all_actions_covered": sorted(realism["actions"]) == sorted(ACTIONS),
        "realism": realism,
        "stage_breakdown_one_process": stage_breakdown(args.profile_seconds),
    })
    write_json_atomic(args.out, result)
    print(f"{data_s:.0f} s of data in {wall:.1f} s wall ({result['wall_s_per_60s_of_data']:.1f} s per 60 s; "
          f"target {TARGET_WALL_S:.0f}); load {load_before[0]:.1f}->{load_after[0]:.1f}; "
          f"events/20ms mean {realism['events_per_20ms']['mean']:.0f}; wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
